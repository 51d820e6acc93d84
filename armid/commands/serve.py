"""``armid serve``: the estimator service (``armid/serve.py``) until Ctrl-C, SIGTERM or ``--duration``."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

from .arguments import ROBOT_HELP, load_robot_argument, positive_number, whole_count
from .output import inputs_read, strict_json
from .ros2 import add_ros2_arguments, ros2_bridge
from .session import add_zenoh_arguments, open_zenoh


def _serve(args: argparse.Namespace) -> int:
    """The estimator service (``armid/serve.py``) until Ctrl-C, SIGTERM or ``--duration``."""
    import signal
    import tempfile
    import threading
    import time

    from armid.daq.stream import drops_line

    from ..serve import EstimatorService, ServiceOptions

    robot = load_robot_argument(args.robot)
    inputs_read()
    from armid.drivers.realtime import ordinary_priority, realtime_allowed

    ordinary_priority()  # started from a real-time thread, it would have inherited that policy
    if not realtime_allowed():  # acquisition here runs at real-time priority where allowed; else it needs our nice
        try:  # never slow acquisition on the same machine: the arithmetic runs at a lower priority
            os.nice(5)
        except OSError:
            pass
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    out_json = open(args.json, "a") if args.json else None  # noqa: SIM115 - closed below
    tmp = None if args.out else tempfile.TemporaryDirectory(prefix="armid-serve-")
    out = Path(args.out) if args.out else Path(tmp.name)  # type: ignore[union-attr]

    def published(doc: dict[str, Any]) -> None:
        e = doc["experiment"]
        what = e.get("note") or (f"links done {doc['links_done']}" if e.get("kind") == "single_link" else f"whole arm from {e['run']}")
        v = doc.get("validation")
        print(f"armid serve: {e['run']}: {what}; {len(doc['base_parameters'])} base parameters published"
              + (f", validation error {100 * v['relative_error']:.3g} %" if v else "")
              + (f" ({e['missing']} records of the run not received)" if e.get("missing") else ""), file=sys.stderr, flush=True)
        if out_json is not None:
            out_json.write(strict_json(doc) + "\n")
            out_json.flush()

    options = ServiceOptions(max_backlog=args.max_backlog, whole_arm=args.whole_arm, payload=not args.no_payload, experiments=args.experiments)
    try:
        with open_zenoh(args) as session, ros2_bridge(args, session, robot.name, [j.name for j in robot.joints],
                                                      ("estimate/parameters", "estimate/payload", "events")):
            service = EstimatorService(session, robot, out, options, on_publish=published,
                                       log=lambda m: print(f"armid serve: {m}", file=sys.stderr, flush=True))
            print(f"armid serve: {robot.name}: listening on armid/{robot.name}/joint_state and events; publishing "
                  f"armid/{robot.name}/estimate/parameters (Ctrl-C stops)", file=sys.stderr, flush=True)
            try:
                deadline = time.monotonic() + args.duration if args.duration else None
                while not stop.wait(0.1):
                    if (deadline is not None and time.monotonic() >= deadline) or service.done:
                        break
            finally:
                service.close()
        bad = f", {service.bad} unreadable" + (f" (last: {service.last_bad})" if service.last_bad else "")
        payload = service.payload_service
        drops = "" if payload is None else drops_line(payload.stream.counts())
        print(f"armid serve: {service.received} records received, {service.skipped} skipped, {service.lost} lost{bad}; "
              f"{service.published} estimates published" + (f"; the payload estimator did not use: {drops}" if drops else ""), file=sys.stderr)
    finally:
        if out_json is not None:
            out_json.close()
        if tmp is not None:
            tmp.cleanup()
    if service.still_running:  # the executable ends without finalization (armid.cli.run), which would abort it
        print(f"armid serve: {', '.join(service.still_running)} still inside a step at the stop: not waited for", file=sys.stderr, flush=True)
    return 0


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``armid serve``: its options."""
    p = sub.add_parser("serve", help="the estimator service: streamed experiments in, estimate/parameters (and estimate/payload) out")
    p.add_argument("--robot", required=True, help=ROBOT_HELP)
    p.add_argument("--out", metavar="DIR", help="where the service keeps its copy of each experiment it received (default: a temporary folder)")
    p.add_argument("--whole-arm", choices=("identify", "drives"), default="identify",
                   help="identify a whole-arm run as 'armid identify RUN.mcap' does (default), or as 'armid demo' does (excitation window, no low-pass)")
    p.add_argument("--no-payload", action="store_true", help="do not run the payload estimator once the arm is identified")
    p.add_argument("--max-backlog", type=whole_count, default=2500, help="records queued before the service skips to the newest (default 2500: 5 s at 2 ms)")
    p.add_argument("--duration", type=positive_number, help="stop after this many seconds (default: until Ctrl-C)")
    p.add_argument("--experiments", type=whole_count, metavar="N",
                   help="file the first N experiments streamed, none after them, and stop once they are published (default: every one, until Ctrl-C)")
    p.add_argument("--json", metavar="JSONL", help="also write every published estimate/parameters document as a JSON line")
    add_zenoh_arguments(p)
    add_ros2_arguments(p)
    p.set_defaults(run=_serve)

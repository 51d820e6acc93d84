"""``armid estimate``: the on-line payload estimator, live on the Zenoh stream or on a recording
(``--replay``), always on the records' own time stamps."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from armid.schema.errors import RecordingError, UsageError

from .arguments import RECORDINGS, add_topic_argument, load_robot_argument
from .output import show_warnings
from .ros2 import add_ros2_arguments, ros2_bridge
from .session import add_zenoh_arguments, open_zenoh

if TYPE_CHECKING:
    from armid.schema.joint_states import JointStates


def _replay_records(path: Path, robot: Any, period_s: float | None, topic: str | None = None) -> tuple[JointStates, list[str]]:
    """The replay's records by :func:`armid.pipeline.replay_records` (identify's checks: ms stamps,
    degrees refused; their warnings held), and ``--period`` against their stamps."""
    import numpy as np

    from ..pipeline import replay_records

    records, notes, found = replay_records(path, robot, topic)
    show_warnings(found)
    t = records.time
    if t.size >= 2 and period_s is not None:
        step = float(np.median(np.diff(t)))
        if abs(step - period_s) > 0.1 * period_s:
            raise RecordingError(str(path), f"its time stamps say a {1000 * step:.4g} ms period, --period says {1000 * period_s:.4g} ms "
                                            "(the estimator always uses the time stamps; leave --period out)")
    return records, notes


def identification_document(path: str, robot: Any) -> dict[str, Any]:
    """The ``armid identify --json`` document, checked for what the estimator reads."""
    import numpy as np

    try:
        doc = json.loads(Path(path).read_text())
    except json.JSONDecodeError as err:
        raise RecordingError(path, f"not JSON: line {err.lineno}: {err.msg}") from None
    except UnicodeDecodeError as err:
        raise RecordingError(path, f"not a text file ({err.reason})") from None
    if not isinstance(doc, dict):
        raise RecordingError(path, f"must be a JSON object (the output of armid identify --json), got a JSON {type(doc).__name__}")
    base = doc.get("base_parameters")
    if not isinstance(base, list):
        raise RecordingError(path, "base_parameters: missing or not a list")
    for k, b in enumerate(base):
        if not isinstance(b, dict) or not isinstance(b.get("expression"), str):
            raise RecordingError(path, f"base_parameters[{k}]: must be an object with an 'expression' string and a 'value'")
        v = b.get("value")
        if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v):
            raise RecordingError(path, f"base_parameters[{k}].value: must be a finite number, got {v!r}")
    sigma = doc.get("joint_noise_sigma")
    if sigma is not None:
        ok = isinstance(sigma, list) and len(sigma) == robot.n_joints and all(
            isinstance(x, int | float) and not isinstance(x, bool) and np.isfinite(x) and x > 0 for x in sigma)
        if not ok:
            raise RecordingError(path, f"joint_noise_sigma: must be {robot.n_joints} positive numbers, got {sigma!r}")
    return doc


def _estimate_summary(n: int, docs: list[dict[str, Any]], seconds: float, stream: Any) -> str:
    est = stream.estimator
    head = f"armid estimate: {n} updates, {len(docs)} estimates in {seconds:.2f} s"
    extra = [f"{v} {k.replace('_', ' ')}" for k, v in (("rate_changes", est.rate_changes_), ("rejected", est.rejected_),
                                                       ("lost", stream.lost), ("invalid", stream.invalid)) if v]
    if stream.dropped:
        reasons = ", ".join(f"{v} {k}" for k, v in stream.dropped.items())
        extra.append(f"dropped {reasons}; last: {stream.last_drop}")
    if not docs:
        return head + "; no estimate (too few records to differentiate)"
    last = docs[-1]
    if last["mass"] is None:
        what = "mass not excited: the motion does not determine it (no estimate)"
    else:
        com = "" if last["com"] is None else ", centre of mass [" + ", ".join(f"{100 * c:.1f}" for c in last["com"]) + "] cm"
        what = (f"mass {last['mass']:.3f} +- {last['mass_std']:.3f} kg (1 sigma: data {last['mass_std_data']:.3f}, torque constants "
                f"{last['mass_std_torque_constants']:.3f}){com}, {last['status']}")
    label = f"final, over {last['excited_s']:.1f} s of motion since the last restart" if last.get("final") else "last"
    return head + f"; {label}: {what}" + (f" ({', '.join(extra)})" if extra else "")


def _replay_problem(n_records: int, docs: list[dict[str, Any]], stream: Any) -> str | None:
    """What makes a replay's input unusable: no record the estimator could take (each dropped
    by the screen: not finite, invalid), or most of them gross outliers against the identified
    arm (torque in mN*m, another arm's parameters). None when the replay says something."""
    dropped = sum(stream.dropped.values()) + stream.invalid
    if not docs:
        reasons = ", ".join(f"{v} {k}" for k, v in stream.dropped.items()) or "too few records to differentiate"
        return f"no estimate from {n_records} records ({dropped} dropped: {reasons}; last: {stream.last_drop})" if dropped else \
               f"no estimate from {n_records} records ({reasons})"
    rejected = stream.estimator.rejected_
    if rejected > 0.5 * max(n_records - dropped, 1):
        return (f"{rejected} of {n_records - dropped} records are gross outliers against the identified arm: is the torque in N*m "
                "(not mN*m), and are --params this arm's?")
    return None


def _estimate(args: argparse.Namespace) -> int:
    """On-line payload estimation, live or on a recording; always on the records' time stamps."""
    import time

    import numpy as np

    from armid.daq.payload_service import EstimateStream
    from armid.identify.payload.rls import PayloadRLS, ReferenceRun, arm_model_from_identification

    if not args.replay and args.mode != "live":
        raise UsageError("say what to run on: 'live' (the Zenoh stream) or --replay DATA")
    if args.period is not None and not (np.isfinite(args.period) and args.period > 0):
        raise UsageError(f"--period must be a positive number of seconds, got {args.period:g}")
    if args.publish_every < 1:
        raise UsageError(f"--publish-every must be a whole number of records >= 1, got {args.publish_every}")
    if not (np.isfinite(args.forgetting) and 0 < args.forgetting <= 1):
        raise UsageError(f"--forgetting must be in (0, 1] (a factor per 2 ms of the arm's time; 0.998: about 1 s), got {args.forgetting:g}")
    if args.duration is not None and not (np.isfinite(args.duration) and args.duration > 0):
        raise UsageError(f"--duration must be a positive number of seconds, got {args.duration:g}")
    robot = load_robot_argument(args.robot)
    doc = identification_document(args.params, robot)
    arm = arm_model_from_identification(robot, doc)
    reference = None
    if args.reference:
        ref_records, ref_notes = _replay_records(Path(args.reference), robot, args.period, args.topic)
        for note in ref_notes:
            print(f"{args.reference}: {note}", file=sys.stderr)
        unusable = ref_records.unusable(velocity=False)  # the records the estimator would drop
        kept = ref_records[~np.logical_or.reduce(list(unusable.values()))]
        if len(kept) < 2:
            why = ", ".join(f"{int(m.sum())} {reason}" for reason, m in unusable.items() if m.any())
            raise RecordingError(args.reference, f"only {len(kept)} usable records of {len(ref_records)} ({why}): no reference run")
        try:
            reference = ReferenceRun(arm, kept.time, kept.position, kept.torque)
        except ValueError as err:
            raise RecordingError(args.reference, str(err)) from None
    estimator = PayloadRLS(arm, forgetting=args.forgetting, reference=reference)
    stream = EstimateStream(estimator, publish_every=args.publish_every, strict_time=bool(args.replay),
                            source=str(args.replay or "stream"))
    if args.replay:
        records, notes = _replay_records(Path(args.replay), robot, args.period, args.topic)
        for note in notes:
            print(f"{args.replay}: {note}", file=sys.stderr)
    out = open(args.out, "w") if args.out else sys.stdout  # noqa: SIM115 - closed below
    try:
        if args.replay:
            start = time.perf_counter()
            docs = stream.feed(records)
            if docs:  # the run's one answer, over all it excited since the last restart
                docs.append(stream.final())
            for d in docs:
                out.write(json.dumps(d, allow_nan=False) + "\n")
            seconds = time.perf_counter() - start
            print(_estimate_summary(estimator.n_updates_ if hasattr(estimator, "n_updates_") else 0, docs, seconds, stream), file=sys.stderr)
            problem = _replay_problem(len(records), docs, stream)
            if problem is not None:  # the estimates made are written; the input is named
                raise RecordingError(str(args.replay), problem)
            return 0
        from armid.daq.payload_service import PayloadService
        from armid.daq.stream import drops_line
        from armid.drivers.realtime import ordinary_priority

        ordinary_priority()  # the arithmetic never at a real-time policy inherited from what started it
        session = open_zenoh(args)
        def write(doc: dict[str, Any]) -> None:
            out.write(json.dumps(doc, allow_nan=False) + "\n")

        service = PayloadService(session, robot.name, stream, on_estimate=write,
                                 log=lambda line: print(f"armid estimate: {line}", file=sys.stderr, flush=True))
        # SIGINT and SIGTERM stop it through handlers of its own: a process started in the
        # background by a shell inherits SIGINT ignored, and a stop sent to it (the demo's,
        # a supervisor's) went unheard until it was killed 30 s later. Installed before it says
        # it listens: a stop sent on that line found SIGTERM's default (beside two busy loops)
        from .rig import run_until, stopped_by_signals

        try:
            with stopped_by_signals() as stop, ros2_bridge(args, session, robot.name, [j.name for j in robot.joints], ("estimate/payload",)):
                print(f"armid estimate: listening on armid/{robot.name}/joint_state (Ctrl-C stops)", file=sys.stderr, flush=True)
                run_until(stop, args.duration)
        finally:
            service.close()
            session.close()
        drops = drops_line(stream.counts())
        print(f"armid estimate: {service.published} estimates published" + (f"; not used: {drops}" if drops else ""), file=sys.stderr, flush=True)
        if service.running:  # the executable ends without finalization (armid.cli.run), which would abort it
            print("armid estimate: the estimator was still inside a batch at the stop: not waited for", file=sys.stderr, flush=True)
        return 0
    finally:
        if out is not sys.stdout:
            out.close()


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``armid estimate``: its options."""
    p = sub.add_parser("estimate", help="on-line payload recursive least squares (live over Zenoh, or --replay a recording)")
    p.add_argument("mode", nargs="?", choices=["live"], help="live: subscribe to armid/<robot>/joint_state")
    p.add_argument("--robot", required=True, help="robot description")
    p.add_argument("--params", required=True, metavar="IDENT.json", help="the arm's identification (armid identify --json)")
    p.add_argument("--replay", metavar="DATA", help=f"run on a recording ({RECORDINGS}) and write what would have been published")
    add_topic_argument(p)
    p.add_argument("--out", metavar="JSONL", help="write the estimates as JSON lines (default: standard output)")
    p.add_argument("--reference", metavar="UNLOADED",
                   help="a run of the same trajectory without the payload (a recording as --replay takes): estimate from the torque difference at the "
                        "same positions, so that arm-model and friction errors cancel")
    p.add_argument("--period", type=float, default=None,
                   help="expected sample period in s: only checked against the time stamps, which the estimator always uses")
    p.add_argument("--forgetting", type=float, default=0.998,
                   help="forgetting factor per 2 ms of the arm's time while it moves, in (0, 1] (default 0.998: about 1 s)")
    p.add_argument("--publish-every", type=int, default=10, help="publish on every Nth record (default 10: 50 Hz at 2 ms)")
    p.add_argument("--duration", type=float, help="live: stop after this many seconds")
    add_zenoh_arguments(p)
    add_ros2_arguments(p)
    p.set_defaults(run=_estimate)

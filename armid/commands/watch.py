"""``armid watch``: a live view of the stream in the terminal."""

from __future__ import annotations

import argparse
import sys

from .arguments import positive_number
from .rig import stopped_by_signals
from .session import add_zenoh_arguments, open_zenoh


def _watch(args: argparse.Namespace) -> int:
    """Until ``--duration`` or SIGINT/SIGTERM: a viewer started from a script in the background
    inherits SIGINT ignored, and stopped only on Ctrl-C's ``KeyboardInterrupt`` it heard
    neither (as ``armid estimate live`` did)."""
    from ..watch import watch

    # the handlers before the line that says it watches: a signal on that line stops it
    with open_zenoh(args) as session, stopped_by_signals() as stop:
        print(f"armid watch: watching armid/{args.robot}/ (Ctrl-C or SIGTERM stops)", file=sys.stderr, flush=True)
        state = watch(session, args.robot, args.duration, stop=stop, raw=args.raw)
    print(f"armid watch: {state.received} records, {state.gaps} gaps ({state.missing} missing), {state.bad} unreadable; "
          f"{state.published} parameter sets, {state.payloads} payload estimates", file=sys.stderr)
    return 0


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``armid watch``: its options."""
    p = sub.add_parser("watch", help="a live view of the stream in the terminal (joints, rate, gaps, the published parameters, payload, findings, events)")
    p.add_argument("--robot", required=True, help="robot name, as in armid/<robot>/... (e.g. puma560)")
    p.add_argument("--duration", type=positive_number, help="stop after this many seconds (default: until Ctrl-C)")
    p.add_argument("--raw", action="store_true",
                   help="show the events' documents as they come (trajectory coefficients, drive settings) instead of their lines in words")
    add_zenoh_arguments(p)
    p.set_defaults(run=_watch)

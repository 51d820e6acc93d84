"""``armid demo``: the whole job on the simulated arm (``armid/demo.py``)."""

from __future__ import annotations

import argparse
from pathlib import Path

from .arguments import _seed


def _demo(args: argparse.Namespace) -> int:
    from ..demo import run_demo

    return run_demo(Path(args.out), Path(args.rig) if args.rig else None, seed=args.seed)


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``armid demo``: its options."""
    p = sub.add_parser("demo", help="the whole job on the simulated arm: excitation, recording, identification, diagnosis, payload, report")
    p.add_argument("--out", default="report", help="report folder (default: report)")
    p.add_argument("--rig", help="rig file (default: the embedded config/rigs/sim.yaml)")
    p.add_argument("--seed", type=_seed, default=0, help="seed of the trajectory optimiser's starts")
    p.set_defaults(run=_demo)

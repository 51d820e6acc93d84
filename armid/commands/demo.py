"""``armid demo``: the whole job on the simulated arm (``armid/demo.py``)."""

from __future__ import annotations

import argparse
from pathlib import Path

from .arguments import seed_number


def _demo(args: argparse.Namespace) -> int:
    from ..demo import run_demo

    return run_demo(Path(args.out), Path(args.rig) if args.rig else None, seed=args.seed, arm_seed=args.arm_seed)


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``armid demo``: its options."""
    p = sub.add_parser("demo", help="the whole job on the simulated arm: excitation, recording, identification, diagnosis, payload, report")
    p.add_argument("--out", default="report", help="report folder (default: report)")
    p.add_argument("--rig", help="rig file (default: the embedded config/rigs/sim.yaml)")
    p.add_argument("--seed", type=seed_number, default=0, help="seed of the trajectory optimiser's starts")
    p.add_argument("--arm-seed", type=seed_number, default=None,
                   help="seed of the simulated arm's current noise (default: a fresh one, printed and kept in demo.json)")
    p.set_defaults(run=_demo)

"""A command imports what it uses, when it uses it (issue 65): ``armid --version``, ``armid
--help`` and every command's ``--help`` import argparse and the options, none of the numerical
or network libraries (whose imports cost ten times the answer). Checked on what a fresh
interpreter actually imported (``python -X importtime``), not on a clock:
``benchmarks/bench_startup.py`` times it.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from armid.cli import build_parser

ROOT = Path(__file__).resolve().parent.parent
HEAVY = {"numpy", "scipy", "pinocchio", "zenoh", "numba", "cvxpy", "clarabel", "matplotlib", "ray", "rich"}
"""Top-level packages a start-up must not import: each costs tens to hundreds of milliseconds."""


def _commands() -> list[str]:
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    return sorted(sub.choices)  # type: ignore[arg-type]


def imported(*argv: str) -> set[str]:
    """The top-level packages the command line imported for ``armid ARGV`` (which must exit 0)."""
    done = subprocess.run([sys.executable, "-X", "importtime", "-c", "from armid.cli import run; run()", *argv],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    names = [line.rsplit("|", 1)[1].strip() for line in done.stderr.splitlines() if line.startswith("import time:") and "|" in line]
    assert "armid.cli" in names  # the measure sees the command line's own imports
    return {name.split(".")[0] for name in names}


@pytest.mark.parametrize("argv", [["--version"], ["--help"]] + [[c, "--help"] for c in _commands()], ids=" ".join)
def test_start_up_imports_no_numerical_or_network_library(argv: list[str]) -> None:
    assert imported(*argv) & HEAVY == set()


def test_the_measure_sees_a_heavy_import() -> None:
    """The check can fail: a command that does run imports what it computes with."""
    done = subprocess.run([sys.executable, "-X", "importtime", "-c", "import armid.pipeline"], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    names = {line.rsplit("|", 1)[1].strip().split(".")[0] for line in done.stderr.splitlines() if line.startswith("import time:")}
    assert "numpy" in names

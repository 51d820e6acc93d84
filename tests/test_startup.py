"""A command imports what it uses, when it uses it (issue 65): ``armid --version``, ``armid
--help`` and every command's ``--help`` import argparse and the options, none of the numerical
or network libraries (whose imports cost ten times the answer). Checked on what a fresh
interpreter actually imported (``python -X importtime``), not on a clock:
``benchmarks/bench_startup.py`` times it.
"""

from __future__ import annotations

import io
import subprocess
import sys
from pathlib import Path

import pytest

from armid.cli import build_parser
from armid.kernels import announce_compilation

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


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _compiled_in(module: str) -> None:
    import numba

    def probe(x: float) -> float:
        return x + 1.0

    probe.__module__ = module
    numba.njit(probe)(1.0)  # no cache: compiled here, the event raised


def test_a_kernel_that_compiles_says_so_on_a_terminal_once() -> None:
    """The first-run compilation is announced (a wait of up to a minute is not a hang), on a
    terminal only, for armid's kernels only, once."""
    terminal, pipe = _Terminal(), io.StringIO()
    announce_compilation(terminal)
    announce_compilation(pipe)
    _compiled_in("someone_else.module")
    assert terminal.getvalue() == ""
    _compiled_in("armid.identify.kernels.probe")
    _compiled_in("armid.identify.kernels.probe2")
    assert terminal.getvalue().count("compiling the numerical kernels") == 1
    assert pipe.getvalue() == ""


def test_the_demo_compiles_ahead_only_what_the_kernels_process_has_not_built(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``armid demo`` starts the kernels process beside its first design unless that process has
    built the rig's kernels where numba caches them now (its stamp, named by the kernels'
    sources, numba's and Python's versions, the rig and the cache's place); another cache
    place, another rig or a changed kernel source is not built."""
    from armid import kernels

    rig = ROOT / "config" / "rigs" / "sim.yaml"
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    assert not kernels._built(rig)
    stamp = kernels._stamp(rig)
    assert stamp.parent == tmp_path / "cache"
    stamp.parent.mkdir()
    stamp.touch()  # as `python -m armid.kernels RIG` does once it has compiled
    assert kernels._built(rig)
    assert not kernels._built(ROOT / "config" / "rigs" / "sim_dynamixel.yaml")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "elsewhere"))
    assert not kernels._built(rig)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(kernels, "KERNEL_MODULES", (*kernels.KERNEL_MODULES[:-1], "armid.identify.kernels.regressor_lanes"))
    assert not kernels._built(rig)

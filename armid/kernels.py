"""numba's compiled kernels, compiled ahead of their first use in a process of their own.

On a fresh install numba's cache is empty and the first call of each kernel compiles it: on
the 2-core machine the payload projection 5.2 s, the simulated arm's sub-step 2.5 s, the
zero-phase filter 1.6 s (and the regressor 8.4 s, which the first design compiles). ``armid
demo`` starts this module beside its first design, so that these compile on the other core
while the regressor does, and every later process (the simulated arm, ``armid serve``,
``armid estimate live``) loads them from numba's cache instead of compiling them on the
real-time process's clock or before the payload estimator can start. Each kernel is called
as its users call it, so that the cached signature is theirs.

``python -m armid.kernels`` (no rig) builds the cache of every kernel, the regressor's
included, for the shipped simulated rig: the step after ``pip install`` that spares the first
``armid identify`` its compilation (30 s measured on the 2-core machine beside other work). Without
it, a command that starts compiling says so on a terminal (:func:`announce_compilation`), so that
the wait is not taken for a hang.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TextIO

KERNEL_MODULES = ("armid.identify.kernels.projection", "armid.identify.kernels.filter", "armid.sim_bus.physics_kernel")
"""The modules whose numba kernels :func:`_compile` builds for a rig."""


def _stamp(rig_path: Path) -> Path:
    """Where the kernels process says it built the rig's kernels: a file named by what the cache
    depends on (the kernels' sources as numba stamps them, size and time; numba's and Python's
    versions; the rig; the cache's place), beside the simulated arm's own cached kernel."""
    import hashlib
    import platform
    from importlib.metadata import version
    from importlib.util import find_spec

    sources = [Path(str(getattr(find_spec(m), "origin", ""))) for m in KERNEL_MODULES]
    stamps = [f"{s}:{s.stat().st_size}:{s.stat().st_mtime_ns}" for s in sources]
    cache_dir = os.environ.get("NUMBA_CACHE_DIR", "")
    key = "|".join([*stamps, version("numba"), platform.python_version(), str(Path(rig_path).resolve()), cache_dir])
    name = f"armid-kernels-{hashlib.sha256(key.encode()).hexdigest()[:16]}.built"
    return (Path(cache_dir) if cache_dir else sources[-1].parent / "__pycache__") / name


def _built(rig_path: Path) -> bool:
    """Whether this machine's kernels process has built the rig's kernels since their sources last changed."""
    try:
        return _stamp(rig_path).exists()
    except (OSError, ImportError, ValueError):  # a module or numba's metadata not found: built ahead as before
        return False


@contextmanager
def compiled_ahead(rig_path: Path) -> Iterator[None]:
    """Compile (or load) the kernels in a process of its own while the block runs, at a lower
    priority than the caller's: on a busy machine it yields, and a kernel not ready in time is
    compiled where it is first used, as without it. Ended with the block if still running.
    Nothing is started where the kernels process has built them already (its stamp, :func:`_stamp`):
    it would only load them, 1.35 s of a core that the designs beside it want (measured)."""
    if _built(rig_path):
        yield
        return
    proc = subprocess.Popen([sys.executable, "-m", "armid.kernels", str(rig_path)], stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        yield
    finally:
        if proc.poll() is None:
            proc.terminate()
        proc.wait()


def announce_compilation(stream: TextIO | None = None) -> None:
    """On a terminal, one line on ``stream`` (stderr) when the first of armid's kernels
    starts compiling in this process (numba's ``numba:compile`` event, which a kernel loaded
    from the cache does not raise); nothing when the cache is built, or where no one watches
    (a pipe, a file, a test)."""
    stream = sys.stderr if stream is None else stream
    if not stream.isatty():
        return
    from numba.core import event

    class _Once(event.Listener):
        said = False

        def on_start(self, ev: event.Event) -> None:
            module = getattr(getattr(ev.data.get("dispatcher"), "py_func", None), "__module__", "") or ""
            if not self.said and module.startswith("armid."):
                self.said = True
                print("armid: compiling the numerical kernels for this machine, once (up to a minute on a busy 2-core machine; later runs load them "
                      "from numba's cache; `python -m armid.kernels` builds it ahead)", file=stream, flush=True)

        def on_end(self, ev: event.Event) -> None:
            pass

    event.register("numba:compile", _Once())


def _compile(rig_path: Path, regressor: bool = False) -> None:
    """Each kernel called as its users call it (the regressor too with ``regressor``: the
    demo leaves it to its first design)."""
    import numpy as np

    from armid.identify.filtering import lowpass
    from armid.identify.payload.projection import project_feasible
    from armid.io.rig_file import load_rig
    from armid.sim_bus.physics import ArmPhysics, simulation_config

    rig = load_rig(rig_path)
    ArmPhysics(rig.robot, simulation_config(rig.simulation, rig.robot.n_joints), rig.period_s)  # compiles its sub-step as it is made
    project_feasible(-0.01 * np.ones(10), np.eye(10))  # as PayloadRLS.warm
    lowpass(np.random.default_rng(0).normal(size=(500, rig.robot.n_joints)), rig.period_s, 10.0)
    if regressor:
        from armid.identify.dynamics import regressor as compute

        q = np.random.default_rng(0).normal(size=(3, 300, rig.robot.n_joints))
        compute(rig.robot, *q)


if __name__ == "__main__":
    if len(sys.argv) > 1:  # the demo's, beside its first design
        os.nice(5)
        built = Path(sys.argv[1])
        _compile(built)
    else:
        from armid.resources import config_file

        built = config_file("rigs/sim.yaml")
        _compile(built, regressor=True)
    try:
        stamp = _stamp(built)
        stamp.parent.mkdir(parents=True, exist_ok=True)
        stamp.touch()
    except OSError:  # a cache place this user may not write: the next demo compiles ahead again
        pass

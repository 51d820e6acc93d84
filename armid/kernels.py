"""numba's compiled kernels, compiled ahead of their first use in a process of their own.

On a fresh install numba's cache is empty and the first call of each kernel compiles it: on
the 2-core machine the payload projection 5.2 s, the simulated arm's sub-step 2.5 s, the
zero-phase filter 1.6 s (and the regressor 8.4 s, which the first design compiles). ``armid
demo`` starts this module beside its first design, so that these compile on the other core
while the regressor does, and every later process (the simulated arm, ``armid serve``,
``armid estimate live``) loads them from numba's cache instead of compiling them on the
real-time process's clock or before the payload estimator can start. Each kernel is called
as its users call it, so that the cached signature is theirs.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def compiled_ahead(rig_path: Path) -> Iterator[None]:
    """Compile (or load) the kernels in a process of its own while the block runs, at a lower
    priority than the caller's: on a busy machine it yields, and a kernel not ready in time is
    compiled where it is first used, as without it. Ended with the block if still running."""
    proc = subprocess.Popen([sys.executable, "-m", "armid.kernels", str(rig_path)], stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        yield
    finally:
        if proc.poll() is None:
            proc.terminate()
        proc.wait()


def _compile(rig_path: Path) -> None:
    import numpy as np

    from armid.identify.filtering import lowpass
    from armid.identify.payload.projection import project_feasible
    from armid.io.rig_file import load_rig
    from armid.sim_bus.physics import ArmPhysics, simulation_config

    rig = load_rig(rig_path)
    ArmPhysics(rig.robot, simulation_config(rig.simulation, rig.robot.n_joints), rig.period_s)  # compiles its sub-step as it is made
    project_feasible(-0.01 * np.ones(10), np.eye(10))  # as PayloadRLS.warm
    lowpass(np.random.default_rng(0).normal(size=(500, rig.robot.n_joints)), rig.period_s, 10.0)


if __name__ == "__main__":
    os.nice(5)
    _compile(Path(sys.argv[1]))

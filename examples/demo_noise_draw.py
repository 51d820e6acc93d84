"""Is the demo's single-link figure one noise draw? The demo's link-6 and link-5 designs on the
bus (the simulated arm, seed 0 as the demo's rig has it), with and without a pause before link 5.

The simulated arm draws its current noise per SYNC from its seed, and the demo starts each run at
nearly the same SYNC count every time, so every demo run re-draws almost the same noise. A pause
shifts the noise against the trajectory: another draw. Prints the z of each combination of
links 6 and 5 against the simulator's truth (docs/figures.md, "Why the demo's link 3 sits near
3 sigma").

    python examples/demo_noise_draw.py [PAUSE_S ...]      (default: 0 0 0.5 1.3)
"""

from __future__ import annotations

import sys
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np

from armid.demo import DEFAULT_RIG, true_parameters
from armid.experiments import design_experiments, prepared_runs
from armid.identify.single_link import single_link_sequence
from armid.io.rig_file import load_rig
from armid.simulated import excitation_session


def draw(pause_s: float, out: Path) -> str:
    """Links 6 and 5 of the demo's designs on the bus, ``pause_s`` between them: their z."""
    rig = load_rig(DEFAULT_RIG)
    rig = rig.with_bus(channel=f"armid-draw-{uuid.uuid4().hex[:8]}")
    robot = rig.robot
    start = np.asarray(rig.simulation["initial_position"], float)
    experiments = design_experiments(robot, start, [robot.n_joints - 1, robot.n_joints - 2], [], rig.period_s, seed=0)
    reports = []
    with excitation_session(rig, simulate=True) as session:
        for k, e in enumerate(experiments):
            if k == 1 and pause_s:
                time.sleep(pause_s)
            reports.append(session.run(e.plan, out / e.name, e.name))
    prepared = prepared_runs(reports, robot, rig.period_s)
    seq = single_link_sequence(robot, {e.link: [prepared[e.name]] for e in experiments})
    phi = true_parameters(rig, seq.names)
    z = (seq.beta - np.array([f.row @ phi for f in seq.functionals])) / seq.std
    return "  ".join(f"{f.expression if len(f.expression) < 16 else f.expression[:13] + '...'} {v:+.2f}" for f, v in zip(seq.functionals, z))


if __name__ == "__main__":
    pauses = [float(x) for x in sys.argv[1:]] or [0.0, 0.0, 0.5, 1.3]
    with tempfile.TemporaryDirectory() as tmp:
        for k, pause in enumerate(pauses):
            print(f"pause {pause:g} s: {draw(pause, Path(tmp) / str(k))}", flush=True)

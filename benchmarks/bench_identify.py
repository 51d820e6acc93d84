"""``armid identify``'s pipeline on 100,000 samples of a 6-joint arm against one
numpy.linalg.lstsq of its final matrix, in the same process (target: at most 3x).

    python benchmarks/bench_identify.py [n_samples]
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from figures_json import recorded

from armid.identify.dynamics import regressor
from armid.identify.identification import identify, stacked_regressor, structural_base
from armid.identify.preprocess import PrepareOptions, prepare
from armid.identify.trajectories import random_fourier_trajectory
from armid.io.recordings import read_recording, write_csv
from armid.io.robot_file import load_robot

ROBOT = Path(__file__).resolve().parent.parent / "config" / "robots" / "puma560.yaml"


def main(n: int = 100_000) -> None:
    robot = load_robot(ROBOT)
    traj = random_fourier_trajectory(robot, seed=1)
    t = np.arange(n) * 0.002
    q, qd, qdd = traj.evaluate(t)
    tau = regressor(robot, q, qd, qdd) @ robot.modeled_parameters() + np.random.default_rng(0).normal(size=q.shape)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "run.csv"
        write_csv(path, t, {"q": q, "qd": qd, "tau": tau})
        start = time.perf_counter()
        prep = prepare(read_recording(path, robot), robot, PrepareOptions(lowpass_hz=None))
        t_read = time.perf_counter() - start
    start = time.perf_counter()
    result = identify(robot, [prep])
    t_identify = time.perf_counter() - start
    seg = prep.segments[0]
    w = stacked_regressor(robot, result.effects, seg.q, seg.qd, seg.qdd)[:, structural_base(robot).independent]
    start = time.perf_counter()
    np.linalg.lstsq(w, seg.tau.reshape(-1), rcond=None)
    t_lstsq = time.perf_counter() - start
    print(
        f"identify, {robot.n_joints} joints, {seg.n_samples} samples: identification {t_identify:.3f} s "
        f"(+ reading and preprocessing the CSV {t_read:.3f} s), one lstsq of the final matrix {w.shape} {t_lstsq:.3f} s, "
        f"ratio {t_identify / t_lstsq:.2f}x"
    )


if __name__ == "__main__":
    with recorded("identify"):
        main(int(sys.argv[1]) if len(sys.argv) > 1 else 100_000)

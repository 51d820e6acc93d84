"""The physically consistent fit against the unconstrained one, on 100,000 samples of a
6-joint arm (the PUMA 560 with its declared friction and rotor inertia), in one process.

    python benchmarks/bench_feasible.py [n_samples] [repeats]

The unconstrained fit is ``identify()`` (regressor, QR per joint, weighted least squares,
covariance). The feasible fit (``feasible_estimate``) starts from its result: it works on
the (p x p) triangle of the weighted regressor, so its time does not grow with the samples.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import numpy as np
from figures_json import recorded

from armid.identify.dynamics import regressor
from armid.identify.feasible import feasible_estimate
from armid.identify.identification import identify
from armid.identify.preprocess import Prepared, Segment
from armid.identify.trajectories import random_fourier_trajectory
from armid.io.robot_file import load_robot

ROBOT = Path(__file__).resolve().parent.parent / "config" / "robots" / "puma560.yaml"


def main(n: int = 100_000, repeats: int = 3) -> None:
    robot = load_robot(ROBOT)
    traj = random_fourier_trajectory(robot, seed=1)
    t = np.arange(n) * 0.002
    q, qd, qdd = traj.evaluate(t)
    rng = np.random.default_rng(0)
    tau = regressor(robot, q, qd, qdd) @ robot.modeled_parameters() + 0.5 * qd + 0.3 * np.sign(qd) + rng.normal(size=q.shape)
    prep = Prepared([Segment("<benchmark>", t, q, qd, qdd, tau)])
    identify(robot, [Prepared([Segment("<warm-up>", t[:2000], q[:2000], qd[:2000], qdd[:2000], tau[:2000])])])  # compile
    t_ls, t_f = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        result = identify(robot, [prep])
        t_ls.append(time.perf_counter() - start)
        start = time.perf_counter()
        fr = feasible_estimate(result)
        t_f.append(time.perf_counter() - start)
        assert fr.consistent
    ls, f = statistics.median(t_ls), statistics.median(t_f)
    print(
        f"{robot.name}, {robot.n_joints} joints, {n} samples, {len(result.names)} standard and {result.base.n_base} base parameters; "
        f"median of {repeats}: unconstrained identify() {ls:.3f} s, feasible fit after it {f:.3f} s "
        f"(solver {fr.fit.seconds:.3f} s, {fr.fit.iterations} iterations), ratio feasible / unconstrained {f / ls:.3f}; "
        f"every run: {', '.join(f'{a:.3f}/{b:.3f}' for a, b in zip(t_ls, t_f))} s"
    )


if __name__ == "__main__":
    with recorded("feasible"):
        main(int(sys.argv[1]) if len(sys.argv) > 1 else 100_000, int(sys.argv[2]) if len(sys.argv) > 2 else 3)

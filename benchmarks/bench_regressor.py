"""Batched regressor (6 joints, 100,000 samples) against a per-sample loop over Pinocchio's
computeJointTorqueRegressor, in the same process. Prints the ratio (target: >= 10x).

    python benchmarks/bench_regressor.py [n_samples]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pinocchio as pin

from identify.dynamics import regressor
from identify.identification import random_motion
from identify.pinocchio_bridge import to_pinocchio
from identify.robot_file import load_robot

ROBOT = Path(__file__).resolve().parent.parent / "config" / "robots" / "puma560.yaml"


def best_of(fn, repeats: int = 3) -> float:  # type: ignore[no-untyped-def]
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main(n: int = 100_000) -> None:
    robot = load_robot(ROBOT)
    q, qd, qdd = random_motion(robot, n, seed=0)
    model = to_pinocchio(robot)
    data = model.createData()
    out = np.empty((n, 6, 60))

    def loop() -> None:
        for k in range(n):
            out[k] = pin.computeJointTorqueRegressor(model, data, q[k], qd[k], qdd[k])

    t_batched = best_of(lambda: regressor(robot, q, qd, qdd))
    t_loop = best_of(loop)
    print(f"regressor, {robot.n_joints} joints, {n} samples: batched {t_batched:.3f} s, Pinocchio loop {t_loop:.3f} s, speed-up {t_loop / t_batched:.2f}x")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 100_000)

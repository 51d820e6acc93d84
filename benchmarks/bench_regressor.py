"""Batched regressor (6 joints, 100,000 samples) against a per-sample loop over Pinocchio's
computeJointTorqueRegressor, in the same process. Prints the ratios (target: >= 10x).

The output alone is n * 6 * 60 doubles (288 MB at 100,000 samples). The Pinocchio loop
writes into an array allocated beforehand, so "into the same array" is the like-for-like
figure; a fresh array also pays the kernel's zeroing of its pages on first touch, printed
for reference as numpy allocating and filling one.

    python benchmarks/bench_regressor.py [n_samples]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pinocchio as pin
from figures_json import recorded

from armid.identify.dynamics import regressor
from armid.identify.identification import random_motion
from armid.identify.pinocchio_bridge import to_pinocchio
from armid.io.robot_file import load_robot

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

    regressor(robot, q[:10], qd[:10], qdd[:10])  # compile (or load the cached kernel) first
    t_batched = best_of(lambda: regressor(robot, q, qd, qdd))
    t_into = best_of(lambda: regressor(robot, q, qd, qdd, out=out))
    t_loop = best_of(loop)
    t_fresh_fill = best_of(lambda: np.empty((n, 6, 60)).fill(0.0))
    print(
        f"regressor, {robot.n_joints} joints, {n} samples: Pinocchio loop into a preallocated array {t_loop:.3f} s; "
        f"batched {t_batched:.3f} s ({t_loop / t_batched:.2f}x), batched into the same array {t_into:.3f} s ({t_loop / t_into:.2f}x); "
        f"for reference, numpy allocating and filling a fresh array of that size {t_fresh_fill:.3f} s"
    )


if __name__ == "__main__":
    with recorded("regressor"):
        main(int(sys.argv[1]) if len(sys.argv) > 1 else 100_000)

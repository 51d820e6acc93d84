"""The plain script ``armid identify`` is compared with (``bench_identify_process.py``): what one
writes in an afternoon with Pinocchio and numpy, sharing no code with armid.

    python benchmarks/plain_identify.py RUN.csv ROBOT.urdf

Reads the CSV (t, q1..qn, qd1..qdn, tau1..taun) with numpy, differentiates the velocity with
``numpy.gradient``, builds Pinocchio's joint-torque regressor sample by sample
(``computeJointTorqueRegressor``) beside a viscous and a Coulomb column per joint, and solves
the stacked system with ``numpy.linalg.lstsq``. Prints the parameters' count and the relative
fit error.
"""

from __future__ import annotations

import sys

import numpy as np
import pinocchio as pin


def main(csv_path: str, urdf_path: str) -> None:
    model = pin.buildModelFromUrdf(urdf_path)
    data = model.createData()
    n = model.nv
    a = np.loadtxt(csv_path, delimiter=",", skiprows=1)
    t, q, qd, tau = a[:, 0], a[:, 1:1 + n], a[:, 1 + n:1 + 2 * n], a[:, 1 + 2 * n:1 + 3 * n]
    qdd = np.gradient(qd, t, axis=0)
    rows = np.empty((len(t), n, 10 * n + 2 * n))
    for k in range(len(t)):
        rows[k, :, :10 * n] = pin.computeJointTorqueRegressor(model, data, q[k], qd[k], qdd[k])
    rows[:, :, 10 * n:] = 0.0
    idx = np.arange(n)
    rows[:, idx, 10 * n + idx] = qd
    rows[:, idx, 11 * n + idx] = np.sign(qd)
    Y, y = rows.reshape(-1, rows.shape[2]), tau.reshape(-1)
    theta, *_ = np.linalg.lstsq(Y, y, rcond=None)
    error = np.linalg.norm(y - Y @ theta) / np.linalg.norm(y)
    print(f"{len(t)} samples, {theta.size} parameters, relative fit error {error:.4g}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])

"""Make the example recordings shipped in examples/: a simulated PUMA 560 with known
parameters (the modeled values of config/robots/puma560.yaml), viscous and Coulomb
friction, 2 ms sampling, 16-bit-per-turn encoder quantisation and torque noise.

    python examples/make_recordings.py

The torques come from Pinocchio's RNEA (independent of armid's regressor).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin

from armid.identify.pinocchio_bridge import to_pinocchio
from armid.identify.trajectories import random_fourier_trajectory
from armid.io.recordings import write_csv
from armid.io.robot_file import load_robot

HERE = Path(__file__).resolve().parent
ROBOT = HERE.parent / "config" / "robots" / "puma560.yaml"
VISCOUS = np.array([1.48, 0.82, 1.38, 0.071, 0.082, 0.037])  # N*m*s/rad (Corke's B, at the joint)
COULOMB = np.array([0.395, 0.126, 0.132, 0.0112, 0.00926, 0.00396]) * np.array([62.6, 107.8, 53.7, 76.0, 71.9, 76.7])


def simulate(seed: int, duration_s: float = 10.0, period_s: float = 0.002) -> dict[str, np.ndarray]:
    robot = load_robot(ROBOT)
    model = to_pinocchio(robot)
    data = model.createData()
    traj = random_fourier_trajectory(robot, harmonics=5, base_frequency_hz=0.1, fill=0.7, seed=seed)
    t = np.arange(0.0, duration_s, period_s)
    q, qd, qdd = traj.evaluate(t)
    tau = np.array([pin.rnea(model, data, q[k], qd[k], qdd[k]) for k in range(t.size)])
    tau += VISCOUS * qd + COULOMB * np.sign(qd)
    rng = np.random.default_rng(100 + seed)
    tau += rng.normal(size=tau.shape) * 0.005 * np.ptp(tau, axis=0)
    counts = 2.0 * np.pi / 2**16
    q_meas = np.round(q / counts) * counts
    qd_meas = qd  # the drive reports a clean velocity: noise on it would flip sign(qd) at reversals
    return {"t": t, "q": q_meas, "qd": qd_meas, "tau": tau}


def main() -> None:
    for name, seed in (("puma560_excitation.csv", 1), ("puma560_validation.csv", 2)):
        rec = simulate(seed)
        write_csv(HERE / name, rec["t"], {"q": rec["q"], "qd": rec["qd"], "tau": rec["tau"]})
        print(f"wrote {HERE / name}: {rec['t'].size} samples")


if __name__ == "__main__":
    main()

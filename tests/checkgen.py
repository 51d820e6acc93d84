"""A tool on the last link, undeclared: the data of ``armid check``'s tests.

It shares no code with armid: the arms, trajectories, torques and sensors are :mod:`blindgen`'s
(numpy, scipy, pinocchio, yaml only), the tool fixed as :mod:`fleetgen` fixes it. Each case is
a random serial arm (``family``: 6 joints in standard DH with joint torque sensors, or 6 joints
in modified DH with motor currents) with Coulomb and viscous friction on every joint, which its
robot file declares, and modeled inertials off by 20-30 % as a CAD model is. It writes::

    robot.yaml, ident.csv            the arm without a tool (to identify the model on)
    check_0.csv                      another trajectory, no tool
    check_<kg>.csv                   another trajectory each, a tool of that mass (0.5, 1, 2, 5 kg)
    truth.json                       the tool's mass and centre of mass in the last link's frame

    from checkgen import make_check_case
    case = make_check_case(3, "dh6", tmp_path / "c3")
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import blindgen as bg
import numpy as np
from fleetgen import _with_tool, random_arm_with_friction

MASSES_KG = (0.5, 1.0, 2.0, 5.0)
FAMILIES = {"dh6": ("dh", False), "mdh6": ("mdh", True)}  # convention, currents


@dataclass
class CheckCase:
    folder: Path
    robot: Path
    ident: Path
    checks: dict[float, Path]  # tool mass (0: none) -> recording
    offset_m: tuple[float, float, float]


def make_check_case(seed: int, family: str, folder: Path, duration_s: float = 20.0, rate_hz: float = 200.0,
                    masses: tuple[float, ...] = MASSES_KG) -> CheckCase:
    """One arm of ``family`` (:data:`FAMILIES`), its identification run and the check runs."""
    convention, currents = FAMILIES[family]
    rng = np.random.default_rng([seed, 0 if family == "dh6" else 1])
    folder.mkdir(parents=True, exist_ok=True)
    a = random_arm_with_friction(rng, 6, convention, duration_s, rate_hz)
    arm, f0, n = a.arm, a.f0, len(a.arm.links)
    effects = [bg.Effect("coulomb_friction", list(range(n)), {"fc": a.fc}), bg.Effect("viscous_friction", list(range(n)), {"fv": a.fv})]
    offset = (float(rng.uniform(-0.05, 0.05)), float(rng.uniform(-0.05, 0.05)), float(rng.uniform(0.02, 0.08)))
    declare = [{"effect": "coulomb_friction", "joint": j + 1} for j in range(n)] + [{"effect": "viscous_friction", "joint": j + 1} for j in range(n)]
    robot = folder / "robot.yaml"
    bg._write_robot(robot, f"check_{family}_{seed}", arm, a.modeled, a.peak, declare)

    def run(today: bg.Arm, name: str) -> Path:
        traj = bg.random_fourier(rng, arm, float(np.clip(f0 * rng.uniform(0.85, 1.15), 0.1, 0.3)))
        t = bg.stamps(rng, duration_s, rate_hz, 0.05)
        clean, _ = bg.recorded_torque(today, traj, t, effects)
        level = bg.NOISE_LEVELS["medium"]
        sensor = bg.Sensor(rate_hz, 0.05, "medium", True, currents, None, level["torque"] * np.abs(clean).max(axis=0), level["qd"],
                           level["counts"], level["q"])
        path = folder / f"{name}.csv"
        bg.record(rng, today, traj, t, effects, sensor, path, None)
        return path

    ident = run(arm, "ident")
    checks = {0.0: run(arm, "check_0")}
    for m in masses:
        checks[m] = run(_with_tool(arm, m, offset), f"check_{m:g}")
    (folder / "truth.json").write_text(json.dumps({"offset_m": offset, "masses_kg": list(masses), "family": family, "seed": seed}))
    return CheckCase(folder, robot, ident, checks, offset)

"""Shared fixtures: random robots (standard and modified DH, with a prismatic joint)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from armid.identify.robot import Inertial, Joint, JointLimits, JointType, Robot, dh_joint, inertia_entries, mdh_joint

ROOT = Path(__file__).resolve().parent.parent
ROBOTS = ROOT / "config" / "robots"
SHARED = ROOT.parent / "shared"


def random_robot(n: int, convention: str, prismatic_at: int | None, seed: int) -> Robot:
    """A random serial arm with physically valid random inertial values."""
    rng = np.random.default_rng(seed)
    make = dh_joint if convention == "dh" else mdh_joint
    joints = []
    for i in range(n):
        kind = JointType.PRISMATIC if i == prismatic_at else JointType.REVOLUTE
        alpha = float(rng.choice([0.0, np.pi / 2, -np.pi / 2, rng.uniform(-3, 3)]))
        pre, axis, post = make(kind, rng.normal(0, 0.3), alpha, rng.normal(0, 0.3), rng.uniform(-3, 3))
        a = rng.normal(size=(3, 3))
        inertia = a @ a.T * 0.1 + 0.05 * np.eye(3)
        inertial = Inertial(float(rng.uniform(0.5, 5)), tuple(rng.normal(0, 0.2, 3)), tuple(inertia_entries(inertia)))  # type: ignore[arg-type]
        limits = JointLimits((-2.0, 2.0), 2.0, None, 100.0)
        joints.append(Joint(f"j{i + 1}", kind, pre, axis, post, 1.0, limits, inertial))
    return Robot(f"random_{convention}_{seed}", np.array([0.3, -0.2, -9.81]), tuple(joints))


def random_motion(n_samples: int, n_joints: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.uniform(-2, 2, (n_samples, n_joints)), rng.normal(size=(n_samples, n_joints)), rng.normal(size=(n_samples, n_joints))


@pytest.fixture(params=[("dh", 5, 2, 11), ("mdh", 6, 3, 12), ("dh", 3, None, 13), ("mdh", 4, 0, 14)], ids=lambda p: f"{p[0]}-{p[1]}j")
def any_robot(request: pytest.FixtureRequest) -> Robot:
    convention, n, prismatic, seed = request.param
    return random_robot(n, convention, prismatic, seed)

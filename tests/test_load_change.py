"""A load on the last link read out of the base parameters' steps (identify/payload/load_change.py,
issue 62), against an independent construction: Pinocchio's own rigid-body sum (the payload
appended to the last joint's body) and its RNEA give the torques with and without the load;
the base parameters least squares fits to their difference are exactly ``P_N Delta phi``, and
the fit gives back the load's mass and centre. On an arm whose torques do not see the last
link's mass alone, the compact-load (point mass) fit does; steps no last-link load makes are
not named a load.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from armid.identify.identification import stacked_regressor, structural_base
from armid.identify.payload.load_change import fit_load, last_link_rows, load_parameters
from armid.identify.robot import Robot
from armid.io.robot_file import load_robot

pin = pytest.importorskip("pinocchio")

ROBOTS = Path(__file__).resolve().parent.parent / "config" / "robots"

MASS, COM = 1.3, np.array([0.03, -0.05, 0.08])
CUBE = MASS * 0.04**2 / 6.0 * np.eye(3)  # a 4 cm cube's inertia about its centre

# a 4-joint arm (tests/fleetgen.py's cell4_left's kinematics): a vertical first axis, then three
# axes on one line through the last link's origin; the torques see m4 only beside msz4 and Iyy4
COAXIAL = """
name: coaxial4
gravity: [0.0, 0.0, -9.81]
convention: mdh
joints:
  - {name: j1, a: 0.31, alpha: 0.0, d: 0.255, theta: 0.0, limits: {position: [-2.7, 2.7]},
     inertial: {mass: 9.4, com: [-0.03, -0.12, -0.03], inertia: [0.03, 0.0, 0.0, 0.03, 0.0, 0.03]}}
  - {name: j2, a: 0.0, alpha: 1.5707963267948966, d: 0.264, theta: 0.0, limits: {position: [-1.9, 1.9]},
     inertial: {mass: 9.4, com: [0.07, -0.015, 0.25], inertia: [0.07, 0.0, 0.0, 0.04, 0.0, 0.05]}}
  - {name: j3, a: 0.0, alpha: 0.0, d: 0.42, theta: 0.0, limits: {position: [-2.0, 2.0]},
     inertial: {mass: 3.6, com: [-0.026, -0.034, 0.36], inertia: [0.03, 0.0, 0.0, 0.025, 0.0, 0.04]}}
  - {name: j4, a: 0.0, alpha: 0.0, d: 0.42, theta: -2.98, limits: {position: [-2.0, 2.0]},
     inertial: {mass: 1.5, com: [0.02, 0.01, 0.1], inertia: [0.01, 0.0, 0.0, 0.01, 0.0, 0.008]}}
"""


def _torques(robot: Robot, payload: tuple[float, np.ndarray, np.ndarray] | None, q: np.ndarray, qd: np.ndarray,
             qdd: np.ndarray) -> np.ndarray:
    """Pinocchio's RNEA torques (n N,) of the robot's modeled arm, with ``payload`` (mass, centre
    and inertia about it in the last link's frame) added as a body on the last joint."""
    from armid.identify.pinocchio_bridge import to_pinocchio

    model = to_pinocchio(robot)
    if payload is not None:
        mass, com, inertia = payload
        post = robot.joints[-1].post  # the last link's frame in Pinocchio's joint frame
        rot = post[:3, :3]
        model.appendBodyToJoint(model.njoints - 1, pin.Inertia(mass, rot @ com + post[:3, 3], rot @ inertia @ rot.T), pin.SE3.Identity())
    data = model.createData()
    return np.concatenate([pin.rnea(model, data, a, b, c) for a, b, c in zip(q, qd, qdd)])


def _base_steps(robot: Robot, inertia: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P_N (p, 10), the base parameters' steps (p,) least squares fits to the torque the payload adds)."""
    base = structural_base(robot, [])
    rng = np.random.default_rng(62)
    q = rng.uniform(-1.5, 1.5, (120, robot.n_joints))
    qd, qdd = rng.normal(size=q.shape), rng.normal(size=q.shape)
    extra = _torques(robot, (MASS, COM, inertia), q, qd, qdd) - _torques(robot, None, q, qd, qdd)
    w = stacked_regressor(robot, [], q, qd, qdd)[:, base.independent]
    steps, *_ = np.linalg.lstsq(w, extra, rcond=None)
    assert np.abs(w @ steps - extra).max() < 1e-8 * np.abs(extra).max()  # the load is in the base parameters' span
    return last_link_rows(base, robot.n_joints), steps


def test_a_payload_moves_the_base_parameters_by_p_delta_phi_and_the_fit_gives_it_back() -> None:
    robot = load_robot(ROBOTS / "puma560.yaml")
    rows, steps = _base_steps(robot, CUBE)
    delta_phi = load_parameters(MASS, COM, CUBE)
    assert steps == pytest.approx(rows @ delta_phi, abs=1e-9)
    stds = np.full(steps.size, 1e-6)
    fit = fit_load(rows, steps, stds)
    assert fit.model == "rigid body" and fit.explains
    assert fit.mass == pytest.approx(MASS, abs=1e-6) and fit.com == pytest.approx(COM, abs=1e-6)
    # the steps less the load, and no step at all, are no load
    none = fit_load(rows, np.zeros_like(steps), stds)
    assert abs(none.mass) < 5 * none.mass_std and np.isnan(none.com).all() and "not well determined" in none.note


def test_on_an_arm_that_hides_the_last_mass_a_compact_load_is_fitted(tmp_path: Path) -> None:
    (tmp_path / "coaxial4.yaml").write_text(COAXIAL)
    robot = load_robot(tmp_path / "coaxial4.yaml")
    rows, steps = _base_steps(robot, np.zeros((3, 3)))
    assert np.linalg.matrix_rank(rows) < 10  # the steps alone leave part of Delta phi open
    stds = np.full(steps.size, 1e-6)
    point = fit_load(rows, steps, stds)
    assert point.model == "point mass" and point.explains and "leave the mass open" in point.note
    assert point.mass == pytest.approx(MASS, rel=1e-6) and point.com == pytest.approx(COM, abs=1e-6)
    # a 4 cm cube rather than a point: the mass still within 1 %
    _, cube_steps = _base_steps(robot, CUBE)
    cube = fit_load(rows, cube_steps, np.maximum(1e-3 * np.abs(cube_steps), 1e-6))
    assert cube.mass == pytest.approx(MASS, rel=0.01) and cube.com == pytest.approx(COM, abs=0.003)


def test_steps_no_last_link_load_makes_are_not_named_one() -> None:
    robot = load_robot(ROBOTS / "puma560.yaml")
    rows, steps = _base_steps(robot, CUBE)
    rng = np.random.default_rng(5)
    stds = np.full(steps.size, 1e-3)
    noisy = steps + rng.normal(0.0, 1e-3, steps.size)
    assert fit_load(rows, noisy, stds).explains
    # a base parameter without the last link's parameters stepped as well, flagged: not a load
    other = int(np.flatnonzero(np.abs(rows).max(axis=1) == 0)[0])
    both = noisy.copy()
    both[other] += 0.05
    changed = np.zeros(steps.size, bool)
    changed[other] = True
    assert not fit_load(rows, both, stds, changed).explains
    # the base parameters with the last link's parameters moved, but in proportions no body on it makes
    wrong = noisy.copy()
    moved = np.flatnonzero(np.abs(rows).max(axis=1) > 0)
    wrong[moved] += rng.normal(0.0, 0.05, moved.size)
    assert not fit_load(rows, wrong, stds).explains

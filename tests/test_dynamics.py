"""The model against independent references: Pinocchio's RNEA and regressor, closed form."""

from __future__ import annotations

import threading
import time

import numpy as np
import pinocchio as pin
import pytest
from conftest import ROBOTS, random_motion, random_robot

from armid.identify import dynamics as dyn
from armid.identify.kernels import threads as _threads
from armid.identify.pinocchio_bridge import KHOSLA_TO_PINOCCHIO_ORDER, parameter_map, to_pinocchio
from armid.identify.robot import Inertial, change_link_frame, inertial_from_parameters, link_parameters
from armid.io.robot_file import load_robot


def _pin_reference(robot, q, qd, qdd):  # type: ignore[no-untyped-def]
    model = to_pinocchio(robot)
    data = model.createData()
    tau = np.array([pin.rnea(model, data, q[k], qd[k], qdd[k]) for k in range(q.shape[0])])
    y = np.array([pin.computeJointTorqueRegressor(model, data, q[k], qd[k], qdd[k]) for k in range(q.shape[0])])
    return tau, y


def test_khosla_model_equals_classic_ne_and_pinocchio_rnea(any_robot):  # type: ignore[no-untyped-def]
    q, qd, qdd = random_motion(40, any_robot.n_joints, seed=1)
    tau_pin, _ = _pin_reference(any_robot, q, qd, qdd)
    phi = any_robot.modeled_parameters()
    scale = np.abs(tau_pin).max()
    assert np.abs(dyn.regressor(any_robot, q, qd, qdd) @ phi - tau_pin).max() <= 1e-9 * scale
    assert np.abs(dyn.inverse_dynamics(any_robot, q, qd, qdd) - tau_pin).max() <= 1e-9 * scale


def test_regressor_equals_pinocchio_regressor_after_parameter_map(any_robot):  # type: ignore[no-untyped-def]
    q, qd, qdd = random_motion(25, any_robot.n_joints, seed=2)
    _, y = _pin_reference(any_robot, q, qd, qdd)
    m = dyn.regressor(any_robot, q, qd, qdd)
    t = parameter_map(any_robot)
    assert np.abs(y @ t - m).max() <= 1e-9 * np.abs(m).max()


def test_fast_regressor_equals_literal_k_and_r_assembly(any_robot):  # type: ignore[no-untyped-def]
    q, qd, qdd = random_motion(30, any_robot.n_joints, seed=3)
    fast = dyn.regressor(any_robot, q, qd, qdd)
    literal = dyn.regressor_blocks(any_robot, q, qd, qdd)
    assert np.abs(fast - literal).max() <= 1e-12 * np.abs(literal).max()
    # block upper triangular (eq. 18 after eq. 17): joint j does not see links before it
    for j in range(any_robot.n_joints):
        assert np.all(fast[:, j, : 10 * j] == 0.0)


@pytest.mark.parametrize("n_joints, prismatic_at", [(6, 2), (7, 4)], ids=["6j-cache-line-rows", "7j-unaligned-rows"])
def test_regressor_into_every_kind_of_output_array(n_joints, prismatic_at):  # type: ignore[no-untyped-def]
    """The kernel writes 8 x 8 tiles (non-temporally where the rows are whole cache lines):
    every sample count around a tile, a block of lanes, a chunk and a call shared among
    threads (from ``SERIAL_BELOW`` samples, with a partial last chunk), into a fresh
    array, a view into a wider one (as identification uses it), one that starts mid cache
    line, and one of float32, against the literal K and R assembly; nothing outside is touched."""
    robot = random_robot(n_joints, "dh", prismatic_at, seed=21)
    ncol = 10 * n_joints
    for n in (1, 7, 8, 9, 127, 129, 1024 + 133, 4 * 1024 + 133):
        q, qd, qdd = random_motion(n, n_joints, seed=n)
        literal = dyn.regressor_blocks(robot, q, qd, qdd)
        tol = 1e-12 * np.abs(literal).max()
        assert np.abs(dyn.regressor(robot, q, qd, qdd) - literal).max() <= tol
        wide = np.full((n, n_joints, ncol + 7), np.nan)
        dyn.regressor(robot, q, qd, qdd, out=wide[:, :, :ncol])
        assert np.abs(wide[:, :, :ncol] - literal).max() <= tol and np.isnan(wide[:, :, ncol:]).all()
        for shift in (1, 3):
            flat = np.full(n * n_joints * ncol + 8, np.nan)
            shifted = flat[shift : shift + n * n_joints * ncol].reshape(n, n_joints, ncol)
            dyn.regressor(robot, q, qd, qdd, out=shifted)
            assert np.abs(shifted - literal).max() <= tol
            assert np.isnan(flat[:shift]).all() and np.isnan(flat[shift + shifted.size :]).all()
        single = np.empty((n, n_joints, ncol), np.float32)
        dyn.regressor(robot, q, qd, qdd, out=single)
        assert np.abs(single - literal).max() <= 1e-6 * np.abs(literal).max()


def test_independent_parts_are_each_done_once_across_the_threads(monkeypatch: pytest.MonkeyPatch) -> None:
    """``identify.kernels.threads.each_shared`` (the diagnosis's joints): every task once, on this
    thread and the pool's side by side (two threads, as on the 2-core machine, whatever this
    one has: the first two tasks each wait for the other, which one thread alone could never
    finish; which thread takes which is the scheduler's), each task's regressor the one
    computed alone (a task waits on the regressor's own pool: it must not wait on its own);
    a task's error is raised after every thread has stopped."""
    monkeypatch.setattr(_threads, "THREADS", 2)
    robot = random_robot(6, "dh", None, seed=3)
    motions = [random_motion(5000, 6, seed=k) for k in range(5)]
    alone = [dyn.regressor(robot, *m) for m in motions]
    done: dict[int, tuple[str, np.ndarray]] = {}
    both = threading.Barrier(2)

    def task(k: int) -> None:
        if k < 2:
            both.wait(timeout=30.0)
        done[k] = (threading.current_thread().name, dyn.regressor(robot, *motions[k]))

    _threads.each_shared(task, 5, "scoring")
    assert sorted(done) == list(range(5))
    assert all(np.array_equal(done[k][1], alone[k]) for k in range(5))
    first_two = {done[0][0], done[1][0]}
    assert threading.current_thread().name in first_two and any(n.startswith("armid-scoring") for n in first_two)
    stopped = threading.Event()

    def failing(k: int) -> None:
        if k == 1:
            raise ValueError("task 1")
        time.sleep(0.05)
        stopped.set()

    with pytest.raises(ValueError, match="task 1"):
        _threads.each_shared(failing, 3, "scoring")
    assert stopped.is_set()


def test_standard_dh_matrices_are_khoslas_letter_for_letter():  # type: ignore[no-untyped-def]
    robot = random_robot(4, "dh", None, seed=5)
    q, qd, qdd = random_motion(5, 4, seed=6)
    motions = dyn.forward_recursion(robot, q, qd, qdd)
    for i in range(1, 4):
        # Khosla Table 1: p_i = A_i^T P_i = [a_i, d_i sin(alpha_i), d_i cos(alpha_i)], constant
        p_i = np.einsum("nba,nb->na", motions[i].A, motions[i].P)
        assert np.allclose(p_i, p_i[0])
        assert np.allclose(-motions[i].rho, p_i)
        r = dyn.pseudo_rotation(motions[i], motions[i - 1].rho)
        p_prev = -motions[i - 1].rho
        expected = np.zeros_like(r)
        expected[:, :3, :3] = motions[i].A
        expected[:, 3:, 3:] = motions[i].A
        expected[:, 3:, :3] = np.cross(p_prev[:, None, :], motions[i].A.transpose(0, 2, 1)).transpose(0, 2, 1)
        assert np.allclose(r, expected)


def test_parameter_order_map_is_explicit():  # type: ignore[no-untyped-def]
    # Khosla: Ixx Ixy Ixz Iyy Iyz Izz; Pinocchio: Ixx Ixy Iyy Ixz Iyz Izz
    phi = np.arange(10.0)
    assert list(phi[KHOSLA_TO_PINOCCHIO_ORDER]) == [0, 1, 2, 3, 4, 5, 7, 6, 8, 9]
    inertial = Inertial(2.0, (0.1, -0.2, 0.3), (0.5, 0.01, -0.02, 0.4, 0.03, 0.3))
    p = link_parameters(inertial)
    ref = pin.Inertia(2.0, np.array([0.1, -0.2, 0.3]), np.array([[0.5, 0.01, -0.02], [0.01, 0.4, 0.03], [-0.02, 0.03, 0.3]]))
    assert np.allclose(p[KHOSLA_TO_PINOCCHIO_ORDER], ref.toDynamicParameters())
    back = inertial_from_parameters(p)
    assert np.allclose(back.com_m, inertial.com_m) and np.allclose(back.inertia_kgm2, inertial.inertia_kgm2)


def test_frame_change_matches_pinocchio_se3_action():  # type: ignore[no-untyped-def]
    inertia = pin.Inertia.Random()
    placement = pin.SE3.Random()
    p = inertia.toDynamicParameters()[np.argsort(KHOSLA_TO_PINOCCHIO_ORDER)]
    moved = change_link_frame(p, placement.rotation, placement.translation)
    assert np.allclose(moved[KHOSLA_TO_PINOCCHIO_ORDER], placement.act(inertia).toDynamicParameters())


def test_planar_two_link_closed_form():  # type: ignore[no-untyped-def]
    """Textbook 2R planar arm: M(q) qdd + C(q, qd) qd + G(q) with COM distances lc."""
    robot = load_robot(ROBOTS / "planar2.yaml")
    l1 = 0.5
    m1, m2 = 4.0, 2.0
    lc1, lc2 = 0.25, 0.2  # COM at -0.25 from the distal frame = 0.25 from the joint
    i1, i2 = 0.085, 0.027
    g = 9.81
    q, qd, qdd = random_motion(20, 2, seed=4)
    c2, s2 = np.cos(q[:, 1]), np.sin(q[:, 1])
    m11 = i1 + i2 + m1 * lc1**2 + m2 * (l1**2 + lc2**2 + 2 * l1 * lc2 * c2)
    m12 = i2 + m2 * (lc2**2 + l1 * lc2 * c2)
    m22 = i2 + m2 * lc2**2
    h = m2 * l1 * lc2 * s2
    g1 = (m1 * lc1 + m2 * l1) * g * np.cos(q[:, 0]) + m2 * lc2 * g * np.cos(q[:, 0] + q[:, 1])
    g2 = m2 * lc2 * g * np.cos(q[:, 0] + q[:, 1])
    tau1 = m11 * qdd[:, 0] + m12 * qdd[:, 1] - h * (2 * qd[:, 0] * qd[:, 1] + qd[:, 1] ** 2) + g1
    tau2 = m12 * qdd[:, 0] + m22 * qdd[:, 1] + h * qd[:, 0] ** 2 + g2
    tau = dyn.regressor(robot, q, qd, qdd) @ robot.modeled_parameters()
    assert np.allclose(tau, np.column_stack([tau1, tau2]), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("name", ["ur5", "kuka_lwr4"])
def test_urdf_robots_match_pinocchio_on_the_urdf_itself(name):  # type: ignore[no-untyped-def]
    _matches_pinocchio(load_robot(ROBOTS / f"{name}.yaml"), pin.buildModelFromUrdf(str(ROBOTS / f"{name}.urdf")), seed=7)


def _matches_pinocchio(robot, model, seed):  # type: ignore[no-untyped-def]
    """The robot's modeled torque (eq. 18) against ``pin.rnea`` on ``model`` at random states."""
    model.gravity.linear = robot.gravity
    data = model.createData()
    q, qd, qdd = random_motion(15, robot.n_joints, seed=seed)
    ref = np.array([pin.rnea(model, data, q[k], qd[k], qdd[k]) for k in range(15)])
    got = dyn.regressor(robot, q, qd, qdd) @ robot.modeled_parameters()
    assert np.abs(got - ref).max() <= 1e-9 * np.abs(ref).max()


@pytest.mark.parametrize("listed", [[0, 1, 2, 3, 4, 5], [0, 1, 2, 4, 5, 6]])
def test_urdf_joints_the_robot_file_does_not_list_are_held_at_zero(listed, tmp_path):  # type: ignore[no-untyped-def]
    """As Pinocchio's model of the URDF with those joints locked at zero: a gripper's or a last
    wrist joint's link merged into its parent's (silently), a joint left out mid-chain warned about."""
    import warnings

    names = [f"lwr_{i}_joint" for i in range(7)]
    (tmp_path / "kuka_lwr4.urdf").write_text((ROBOTS / "kuka_lwr4.urdf").read_text())
    joints = ", ".join(f"{{name: {names[i]}}}" for i in listed)
    (tmp_path / "r.yaml").write_text(f"name: part\nurdf: kuka_lwr4.urdf\ngravity: [0, 0, -9.81]\njoints: [{joints}]\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        robot = load_robot(tmp_path / "r.yaml")
    skipped = [n for i, n in enumerate(names) if i not in listed and i < max(listed)]
    said = [str(w.message) for w in caught if "not listed" in str(w.message)]
    assert (said and all(n in said[0] for n in skipped)) if skipped else not said, said
    full = pin.buildModelFromUrdf(str(ROBOTS / "kuka_lwr4.urdf"))
    model = pin.buildReducedModel(full, [full.getJointId(n) for i, n in enumerate(names) if i not in listed], pin.neutral(full))
    _matches_pinocchio(robot, model, seed=8)


def test_shape_errors_name_the_array():  # type: ignore[no-untyped-def]
    robot = random_robot(3, "dh", None, seed=1)
    with pytest.raises(ValueError, match="qd must be"):
        dyn.regressor(robot, np.zeros((4, 3)), np.zeros((4, 2)), np.zeros((4, 3)))


def test_the_regressor_kernels_sine_and_cosine_match_libm() -> None:
    """The kernel's own branch-free sincos (so that its lanes vectorise) against numpy's."""
    from armid.identify.kernels.regressor_lanes import _sincos

    rng = np.random.default_rng(5)
    x = np.concatenate([np.linspace(-20.0, 20.0, 40_001), rng.uniform(-1e5, 1e5, 20_000),
                        np.pi / 4 * np.arange(-16, 17), np.array([0.0, -0.0, 1e-300])])
    c, s = np.empty_like(x), np.empty_like(x)
    _sincos(x, c, s, x.size)
    assert np.abs(c - np.cos(x)).max() <= 4.5e-16 and np.abs(s - np.sin(x)).max() <= 4.5e-16


def test_simulated_sensors_report_position_and_velocity_at_one_instant() -> None:
    """Semi-implicit Euler is leapfrog: its positions lead its velocities by half a sub-step.
    The simulated sensors report the position at the velocity's instant, so that
    differentiated positions agree with the reported velocity (a constant acceleration:
    a rigid body about a vertical axis, the other joint braked)."""
    from dataclasses import replace

    from armid.sim_bus.physics import ArmPhysics, SimulationConfig

    robot = replace(load_robot(ROBOTS / "planar2.yaml"), gravity=np.array([0.0, 0.0, -9.81]))
    physics = ArmPhysics(robot, SimulationConfig(substeps=2), 0.002)
    steps = [physics.step(np.array([2.0, 0.0]), braked=np.array([False, True])) for _ in range(200)]
    q = np.array([m.position[0] for m in steps])
    v = np.array([m.velocity[0] for m in steps])
    true_q = np.array([m.true_position[0] for m in steps])
    central = (q[2:] - q[:-2]) / 0.004
    assert np.abs(central - v[1:-1]).max() < 1e-9 * np.abs(v).max()
    acc = steps[-1].true_acceleration[0]
    lead = (true_q[2:] - true_q[:-2]) / 0.004 - v[1:-1]  # the integrator's own positions: half a sub-step ahead
    assert np.allclose(lead, acc * 0.001 / 2, rtol=1e-6)

"""The blind generator checked against closed forms and the shared baseline's model building."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from blindgen import (
    EFFECTS,
    Arm,
    Fourier,
    Link,
    build_model,
    lowpass_first_order,
    make_case,
    noise_floor,
    random_arm,
    random_ptp,
    read_csv,
    recorded,
    recorded_torque,
    relative_error,
    rigid_torque,
)

ROOT = Path(__file__).resolve().parent.parent
BASELINE = ROOT.parent / "shared" / "tools" / "baseline.py"


def _baseline():
    spec = importlib.util.spec_from_file_location("baseline", BASELINE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _box(m: float, dims, rng) -> list[float]:
    r = pin.exp3(rng.normal(size=3))
    lx, ly, lz = dims
    i = r @ (m / 12 * np.diag([ly**2 + lz**2, lx**2 + lz**2, lx**2 + ly**2])) @ r.T
    return [i[0, 0], i[0, 1], i[0, 2], i[1, 1], i[1, 2], i[2, 2]]


def _planar(convention: str, seed: int) -> tuple[Arm, dict]:
    """A planar 2R arm in the vertical plane (gravity along -y of the base), COMs off the plane."""
    rng = np.random.default_rng(seed)
    a1, a2 = rng.uniform(0.2, 0.5, 2)
    m1, m2 = rng.uniform(1, 5, 2)
    lc1, lc2 = rng.uniform(0.05, 0.2, 2)
    w1, w2 = rng.uniform(-0.03, 0.03, 2)  # COM off the link line (y in the link frame)
    z1, z2 = rng.uniform(-0.05, 0.05, 2)  # and off the plane: no effect on the torques about z
    i1, i2 = _box(m1, rng.uniform(0.03, 0.3, 3), rng), _box(m2, rng.uniform(0.03, 0.3, 3), rng)
    lim = dict(q_limits=[-3.0, 3.0], v_limit=2.0, torque_constant=1.0)
    if convention == "dh":  # link frame i at the distal joint
        links = [Link(a1, 0.0, 0.0, 0.0, False, m1, [lc1 - a1, w1, z1], i1, **lim),
                 Link(a2, 0.0, 0.0, 0.0, False, m2, [lc2 - a2, w2, z2], i2, **lim)]
    else:  # link frame i at joint i; row 2 holds a1
        links = [Link(0.0, 0.0, 0.0, 0.0, False, m1, [lc1, w1, z1], i1, **lim),
                 Link(a1, 0.0, 0.0, 0.0, False, m2, [lc2, w2, z2], i2, **lim)]
    return Arm(convention, links, [0.0, -9.81, 0.0]), dict(a1=a1, m1=m1, m2=m2, lc1=lc1, lc2=lc2, w1=w1, w2=w2, izz1=i1[5], izz2=i2[5])


def _planar_closed_form(p: dict, q, qd, qdd) -> np.ndarray:
    """Planar 2R Lagrange equations with the COM at (lc, w) in each link's frame."""
    g = 9.81
    q1, q2 = q.T
    qd1, qd2 = qd.T
    a1, m1, m2 = p["a1"], p["m1"], p["m2"]
    r1sq, r2sq = p["lc1"] ** 2 + p["w1"] ** 2, p["lc2"] ** 2 + p["w2"] ** 2
    # a1 * (COM of link 2 from joint 2) projected: c = a1 (lc2 cos q2 - w2 sin q2), s = a1 (lc2 sin q2 + w2 cos q2)
    c = a1 * (p["lc2"] * np.cos(q2) - p["w2"] * np.sin(q2))
    s = a1 * (p["lc2"] * np.sin(q2) + p["w2"] * np.cos(q2))
    m11 = p["izz1"] + m1 * r1sq + p["izz2"] + m2 * (a1**2 + r2sq + 2 * c)
    m12 = p["izz2"] + m2 * (r2sq + c)
    m22 = p["izz2"] + m2 * r2sq
    h = m2 * s
    # potential: y of each COM times m g
    g1 = g * (m1 * (p["lc1"] * np.cos(q1) - p["w1"] * np.sin(q1)) + m2 * a1 * np.cos(q1)
              + m2 * (p["lc2"] * np.cos(q1 + q2) - p["w2"] * np.sin(q1 + q2)))
    g2 = g * m2 * (p["lc2"] * np.cos(q1 + q2) - p["w2"] * np.sin(q1 + q2))
    tau1 = m11 * qdd[:, 0] + m12 * qdd[:, 1] - h * (2 * qd1 * qd2 + qd2**2) + g1
    tau2 = m12 * qdd[:, 0] + m22 * qdd[:, 1] + h * qd1**2 + g2
    return np.column_stack([tau1, tau2])


@pytest.mark.parametrize("convention", ["dh", "mdh"])
def test_torque_equals_planar_2r_closed_form(convention):
    arm, p = _planar(convention, 3)
    rng = np.random.default_rng(4)
    f = Fourier(0.2, rng.normal(size=(2, 4)), rng.normal(size=(2, 4)), rng.normal(size=2))
    t = np.linspace(0, 5, 400)
    tau, (q, qd, qdd) = recorded_torque(arm, f, t, None)
    expected = _planar_closed_form(p, q, qd, qdd)
    assert np.abs(tau - expected).max() < 1e-9 * np.abs(expected).max()


def test_torque_equals_pendulum_with_offset_com():
    """One link swinging about z with gravity along +x: I qdd + m g lc sin q."""
    m, lc, izz = 2.0, 0.3, 0.05
    arm = Arm("dh", [Link(0.4, 0.0, 0.0, 0.0, False, m, [lc - 0.4, 0.0, 0.0], [0.01, 0, 0, 0.04, 0, izz], [-3, 3], 2.0, 1.0)],
              [9.81, 0.0, 0.0])  # gravity along +x of the base, perpendicular to the axis z
    q = np.linspace(-3, 3, 50)[:, None]
    qd, qdd = np.sin(q), np.cos(q)
    tau = rigid_torque(build_model(arm), q, qd, qdd)[:, 0]
    expected = (izz + m * lc**2) * qdd[:, 0] + m * 9.81 * lc * np.sin(q[:, 0])  # torque needed against g along +x
    assert np.allclose(tau, expected, rtol=1e-12, atol=1e-12)


def _dh_matrix(a, alpha, d, theta, convention):
    def rz(x):
        m = np.eye(4)
        m[:2, :2] = [[math.cos(x), -math.sin(x)], [math.sin(x), math.cos(x)]]
        return m

    def rx(x):
        m = np.eye(4)
        m[1:3, 1:3] = [[math.cos(x), -math.sin(x)], [math.sin(x), math.cos(x)]]
        return m

    def tz(x):
        m = np.eye(4)
        m[2, 3] = x
        return m

    def tx(x):
        m = np.eye(4)
        m[0, 3] = x
        return m

    return rz(theta) @ tz(d) @ tx(a) @ rx(alpha) if convention == "dh" else rx(alpha) @ tx(a) @ rz(theta) @ tz(d)


@pytest.mark.parametrize("convention,seed", [("dh", 1), ("mdh", 2), ("dh", 5), ("mdh", 6)])
def test_kinematics_match_matrix_products_and_baseline(convention, seed, tmp_path):
    """Link frames equal the product of DH/MDH matrices; baseline.py's model of robot.yaml gives the same torque."""
    case = make_case(seed, tmp_path, n_joints=5, convention=convention, rate_hz=100, noise="none", prismatic=True,
                     duration_s=2.0, valid_duration_s=2.0)
    truth = json.loads(case.truth_json.read_text())
    from blindgen import Link as L

    arm = Arm(convention, [L(**ln) for ln in truth["links"]])
    model = build_model(arm)
    data = model.createData()
    rng = np.random.default_rng(seed)
    q = rng.uniform(-1, 1, 5) * 0.1
    pin.forwardKinematics(model, data, q)
    t = np.eye(4)
    for i, ln in enumerate(arm.links):
        th = ln.theta + (0.0 if ln.prismatic else q[i])
        d = ln.d + (q[i] if ln.prismatic else 0.0)
        t = t @ _dh_matrix(ln.a, ln.alpha, d, th, convention)
        after = pin.SE3.Identity() if convention == "mdh" else pin.SE3(_dh_matrix(ln.a, ln.alpha, ln.d, ln.theta, "dh"))
        link_frame = data.oMi[i + 1] * after  # DH: the link frame is the body placement after the joint
        assert np.allclose(link_frame.homogeneous, t, atol=1e-12), i
        # the inertial values sit in that link frame: COM and inertia (about the COM) agree in the world
        com_world = t[:3, :3] @ np.array(ln.com) + t[:3, 3]
        inertia = model.inertias[i + 1]
        assert np.allclose(data.oMi[i + 1].act(inertia.lever), com_world, atol=1e-12)
        r = data.oMi[i + 1].rotation
        i_c = np.array(ln.inertia)[[0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(3, 3)
        assert np.allclose(r @ inertia.inertia @ r.T, t[:3, :3] @ i_c @ t[:3, :3].T, atol=1e-12)

    base = _baseline()
    bmodel, kt = base.load_robot(case.robot_yaml)
    assert np.allclose(kt, [ln.torque_constant for ln in arm.links])
    bdata = bmodel.createData()
    phi = np.concatenate([model.inertias[i + 1].toDynamicParameters() for i in range(5)])
    for _ in range(5):
        q, qd, qdd = rng.uniform(-1, 1, (3, 5)) * 0.1
        y = pin.computeJointTorqueRegressor(bmodel, bdata, q, qd, qdd)
        assert np.allclose(y @ phi, pin.rnea(model, data, q, qd, qdd), rtol=1e-10, atol=1e-10)


def test_robot_file_is_what_armid_loads(tmp_path):
    """The YAML follows the robot-file schema (armid's loader accepts it, modeled values 20-30 % off)."""
    from armid.io.robot_file import load_robot

    case = make_case(11, tmp_path, n_joints=6, noise="low", duration_s=2.0, valid_duration_s=2.0,
                     declare=[{"effect": "coulomb_friction", "joint": None}])
    robot = load_robot(case.robot_yaml)
    truth = json.loads(case.truth_json.read_text())
    assert len(robot.joints) == 6 and robot.effects[0].effect == "coulomb_friction"
    for ln, mo in zip(truth["links"], truth["modeled"]):
        assert 0.2 <= abs(mo["mass"] / ln["mass"] - 1) <= 0.3
        assert np.linalg.norm(np.subtract(mo["inertia"], ln["inertia"])) > 0.08 * np.linalg.norm(ln["inertia"])
        assert np.all(np.linalg.eigvalsh(np.array(mo["inertia"])[[0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(3, 3)) > 0)


def test_fourier_and_ptp_derivatives_are_analytic():
    rng = np.random.default_rng(0)
    arm, _ = random_arm(rng, 4, "dh", None)
    from blindgen import random_fourier

    t = np.linspace(0, 20, 200001)
    for traj in (random_fourier(rng, arm), random_ptp(rng, arm, 20.0)):
        q, qd, qdd = traj(t)
        h = t[1] - t[0]
        assert np.abs(np.gradient(q, h, axis=0) - qd)[1:-1].max() < 1e-5 * max(1, np.abs(qd).max())
        assert np.abs(np.gradient(qd, h, axis=0) - qdd)[1:-1].max() < 1e-2 * max(1, np.abs(qdd).max())
        lo = np.array([ln.q_limits[0] for ln in arm.links])
        hi = np.array([ln.q_limits[1] for ln in arm.links])
        assert np.all(q >= lo) and np.all(q <= hi)
        assert np.all(np.abs(qd) <= [ln.v_limit for ln in arm.links])


def test_recordings_at_jittered_stamps_and_currents(tmp_path):
    case = make_case(21, tmp_path, n_joints=3, rate_hz=200, noise="none", currents=True, jitter=0.15, duration_s=4.0, valid_duration_s=3.0)
    truth = json.loads(case.truth_json.read_text())
    v = read_csv(case.valid_csv)
    dt = np.diff(v["t"])
    assert np.all(dt > 0) and np.std(dt) > 0.05 * 0.005  # jittered, still increasing
    ex = truth["excitation"]["valid"]
    f = Fourier(ex["f0"], np.array(ex["a"]), np.array(ex["b"]), np.array(ex["q0"]))
    q, qd, _ = f(v["t"])
    assert np.allclose(np.column_stack([v[f"q{j + 1}"] for j in range(3)]), q, atol=1e-8)  # evaluated at the stamp written
    assert np.allclose(np.column_stack([v[f"qd{j + 1}"] for j in range(3)]), qd, atol=1e-8)
    assert "tau1" not in v and "i1" in v
    kt = np.array([ln["torque_constant"] for ln in truth["links"]])
    clean = recorded(read_csv(case.valid_clean_csv))
    assert np.allclose(recorded(v, kt), clean, rtol=1e-8)
    assert case.noise_floor == 0.0


def test_noise_floor_and_relative_error(tmp_path):
    case = make_case(5, tmp_path, n_joints=4, rate_hz=100, noise="high", velocity=False, duration_s=3.0, valid_duration_s=4.0)
    v = read_csv(case.valid_csv)
    assert "qd1" not in v
    floor = noise_floor(case.valid_csv, case.valid_clean_csv)
    assert floor == pytest.approx(case.noise_floor, rel=1e-6) and 0.005 < floor < 0.1
    clean = read_csv(case.valid_clean_csv)
    pred = tmp_path / "pred.csv"
    cols = ["t"] + [f"tau_hat{j + 1}" for j in range(4)]
    rows = np.column_stack([clean["t"]] + [clean[f"tau{j + 1}"] for j in range(4)])
    np.savetxt(pred, rows[::2], delimiter=",", header=",".join(cols), comments="", fmt="%.9g")
    err, covered = relative_error(case.valid_csv, pred)
    assert covered == pytest.approx(0.5, abs=0.01)
    assert err == pytest.approx(floor, rel=0.2)
    np.savetxt(pred, rows[::-1], delimiter=",", header=",".join(cols), comments="", fmt="%.9g")  # any row order
    err, covered = relative_error(case.valid_csv, pred)
    assert covered == 1.0 and err == pytest.approx(floor, rel=1e-6)  # the clean torque scores exactly the noise floor
    np.savetxt(pred, rows * [1.0, 1.1, 1.1, 1.1, 1.1], delimiter=",", header=",".join(cols), comments="", fmt="%.9g")
    err, covered = relative_error(case.valid_csv, pred)
    assert covered == 1.0 and err > 0.08


def test_deterministic_per_seed(tmp_path):
    kw = dict(noise=None, velocity=None, currents=None, jitter=None, duration_s=2.0, valid_duration_s=2.0)
    a, b, c = (make_case(s, tmp_path / k, **kw) for s, k in ((8, "a"), (8, "b"), (9, "c")))
    assert a.valid_csv.read_bytes() == b.valid_csv.read_bytes() and a.robot_yaml.read_text() == b.robot_yaml.read_text()
    assert a.valid_csv.read_bytes() != c.valid_csv.read_bytes()


LINEAR_SIZED = ["viscous_friction", "coulomb_friction", "smooth_coulomb", "stribeck_friction", "torque_offset",
                "rotor_inertia", "torque_gain", "spring", "load_coulomb", "friction_all"]


@pytest.mark.parametrize("effect", sorted(EFFECTS))
def test_effect_appears_as_specified(effect, tmp_path):
    """The clean recorded torque minus the rigid body is the effect's formula, on its joint only."""
    case = make_case(31, tmp_path, n_joints=4, rate_hz=100, noise="none", effect=effect, effect_joint=2, effect_size=0.2,
                     duration_s=6.0, valid_duration_s=6.0)
    truth = json.loads(case.truth_json.read_text())
    from blindgen import Link as L

    arm = Arm(truth["convention"], [L(**ln) for ln in truth["links"]])
    ex = truth["excitation"]["valid"]
    f = Fourier(ex["f0"], np.array(ex["a"]), np.array(ex["b"]), np.array(ex["q0"]))
    clean = read_csv(case.valid_clean_csv)
    t = clean["t"]
    tau = np.column_stack([clean[f"tau{j + 1}"] for j in range(4)])
    q, qd, qdd = f(t)
    rigid = rigid_torque(build_model(arm), q, qd, qdd)
    diff = tau - rigid
    p = truth["effect"]["params"]
    if EFFECTS[effect][1]:
        assert case.effect_joint is None and truth["effect"]["joints"] == [1, 2, 3, 4]
    else:
        assert case.effect_joint == 2
        others = [0, 2, 3]
        assert np.abs(diff[:, others]).max() < 1e-6 * np.abs(rigid).max()
    v, d = qd[:, 1], diff[:, 1]
    expected = {
        "viscous_friction": lambda: p["fv"][0] * v,
        "coulomb_friction": lambda: p["fc"][0] * np.sign(v),
        "smooth_coulomb": lambda: p["fc"][0] * np.tanh(v / p["v_s"][0]),
        "stribeck_friction": lambda: (p["fc"][0] + (p["fs"][0] - p["fc"][0]) * np.exp(-((v / p["vs"][0]) ** 2))) * np.sign(v),
        "torque_offset": lambda: np.full_like(v, p["offset"][0]),
        "rotor_inertia": lambda: p["ia"][0] * qdd[:, 1],
        "torque_gain": lambda: (p["gain"][0] - 1) * rigid[:, 1],
        "cogging": lambda: p["a_sin"][0] * np.sin(2 * np.pi * q[:, 1] / p["period_rad"][0]) + p["a_cos"][0] * np.cos(2 * np.pi * q[:, 1] / p["period_rad"][0]),
        "spring": lambda: p["k"][0] * (q[:, 1] - p["q0"][0]),
        "load_coulomb": lambda: (p["fc"][0] + p["c_load"][0] * np.abs(rigid[:, 1])) * np.sign(v),
        "friction_all": lambda: p["fc"][1] * np.sign(v) + p["fv"][1] * v + p["offset"][1],
    }
    if effect == "time_delay":
        assert 0 < p["delay_s"] <= 0.03
        lagged = rigid_torque(build_model(arm), *f(t - p["delay_s"]))
        assert np.allclose(tau, lagged, atol=1e-6 * np.abs(rigid).max())
        assert np.linalg.norm(tau - rigid) > 0.01 * np.linalg.norm(rigid)
    elif effect == "gravity_tilt":
        g = np.array([0, 0, -9.81])
        from blindgen import _rot

        tilted = rigid_torque(build_model(arm, _rot(p["axis"], p["angle_rad"]) @ g), q, qd, qdd)
        assert np.allclose(tau, tilted, atol=1e-6 * np.abs(rigid).max())
        assert 0 < abs(p["angle_rad"]) <= 0.2
    else:
        assert np.allclose(d, expected[effect](), atol=1e-6 * np.abs(rigid).max())
        assert np.abs(d).max() > 1e-3 * np.abs(rigid[:, 1]).max()


@pytest.mark.parametrize("effect", LINEAR_SIZED)
def test_effect_size_is_relative_to_the_joint_torque(effect, tmp_path):
    """On the identification run the effect's RMS is the requested fraction of the joint's rigid-body RMS."""
    case = make_case(41, tmp_path, n_joints=3, rate_hz=100, noise="none", effect=effect, effect_joint=3, effect_size=0.15,
                     duration_s=8.0, valid_duration_s=2.0)
    truth = json.loads(case.truth_json.read_text())
    from blindgen import Link as L

    arm = Arm(truth["convention"], [L(**ln) for ln in truth["links"]])
    ex = truth["excitation"]["ident"]
    f = Fourier(ex["f0"], np.array(ex["a"]), np.array(ex["b"]), np.array(ex["q0"]))
    clean = read_csv(tmp_path / "ident_clean.csv")
    q, qd, qdd = f(clean["t"])
    rigid = rigid_torque(build_model(arm), q, qd, qdd)[:, 2]
    rms = lambda x: np.sqrt(np.mean(x**2))  # noqa: E731
    assert rms(clean["tau3"] - rigid) / rms(rigid) == pytest.approx(0.15, rel=1e-6)


def test_lowpass_matches_first_order_frequency_response():
    """Steady state of a sine through the filter, at jittered stamps: gain 1/sqrt(1 + (w/wc)^2), phase -atan(w/wc)."""
    t = np.round(np.cumsum(np.full(20000, 1e-3) * (1 + 0.1 * np.sin(np.arange(20000)))), 6)
    w, wc = 2 * np.pi * 3.0, 2 * np.pi * 5.0
    y = lowpass_first_order(t, np.sin(w * t)[:, None], 5.0)[:, 0]
    gain, phase = 1 / np.sqrt(1 + (w / wc) ** 2), -np.arctan(w / wc)
    steady = t > 2.0
    # exact for a piecewise-linear input: the only error is the sine's linear interpolation, h^2 w^2 / 8
    assert np.abs(y[steady] - gain * np.sin(w * t[steady] + phase)).max() < np.diff(t).max() ** 2 * w**2 / 8


def test_bad_options_are_refused(tmp_path):
    with pytest.raises(ValueError, match="unknown effect"):
        make_case(1, tmp_path, effect="magic", duration_s=1.0, valid_duration_s=1.0)
    with pytest.raises(ValueError, match="unknown noise level"):
        make_case(1, tmp_path, noise="loud", duration_s=1.0, valid_duration_s=1.0)
    with pytest.raises(ValueError, match="convention"):
        make_case(1, tmp_path, convention="urdf", duration_s=1.0, valid_duration_s=1.0)
    with pytest.raises(ValueError, match="effect_snr needs torque noise"):
        make_case(1, tmp_path, noise="none", effect="cogging", effect_snr=2.0, duration_s=1.0, valid_duration_s=1.0)


def test_extra_effects_runs_and_current_quantisation(tmp_path):
    """Declared friction everywhere under an undeclared delay: the delay lags the friction too; K runs; currents in LSBs."""
    case = make_case(51, tmp_path, n_joints=3, rate_hz=100, noise="none", currents=True, current_lsb=1e-3, effect="time_delay",
                     effect_params={"delay_s": 0.02}, extra_effects=[{"effect": "friction_all", "size": 0.2}], n_ident=3,
                     ptp=True, duration_s=5.0, valid_duration_s=8.0,
                     declare=[{"effect": e, "joint": None} for e in ("coulomb_friction", "viscous_friction", "torque_offset")])
    truth = json.loads(case.truth_json.read_text())
    assert [p.name for p in case.ident_csvs] == ["ident1.csv", "ident2.csv", "ident3.csv"] and case.ident_csv == case.ident_csvs[0]
    assert len({p.read_bytes() for p in case.ident_csvs}) == 3
    from blindgen import Link as L
    from blindgen import PointToPoint

    arm = Arm(truth["convention"], [L(**ln) for ln in truth["links"]])
    kt = np.array([ln.torque_constant for ln in arm.links])
    fa = truth["extra_effects"][0]["params"]
    ex = truth["excitation"]["ptp"]
    traj = PointToPoint(np.array(ex["knots"]), np.array(ex["t_start"]), np.array(ex["t_move"]))
    rec = read_csv(case.ptp_csv)
    i = np.column_stack([rec[f"i{j + 1}"] for j in range(3)])
    assert np.allclose(i / 1e-3, np.round(i / 1e-3), atol=1e-6)
    t = rec["t"]
    q, qd, _ = traj(t)
    assert np.allclose(np.column_stack([rec[f"q{j + 1}"] for j in range(3)]), q, atol=1e-8)
    assert np.mean(np.all(qd == 0, axis=1)) > 0.1  # dwells
    ql, qdl, qddl = traj(t - 0.02)
    expected = rigid_torque(build_model(arm), ql, qdl, qddl) + np.array(fa["fc"]) * np.sign(qdl) + np.array(fa["fv"]) * qdl + np.array(fa["offset"])
    assert np.abs(i * kt - expected).max() <= 0.5e-3 * kt.max() + 1e-9
    assert case.effect_realized > 0.01 and case.ptp_noise_floor > 0  # quantisation is the only noise
    assert len(read_csv(case.ident_csvs[1])["t"]) == 500


def test_effect_snr_sets_the_size_from_the_noise(tmp_path):
    """effect_snr = ||effect torque||_F / expected ||torque noise||_F over the whole arm, identification run."""
    case = make_case(61, tmp_path, n_joints=4, rate_hz=100, noise="medium", effect="torque_offset", effect_joint=3, effect_snr=2.0,
                     duration_s=6.0, valid_duration_s=6.0)
    truth = json.loads(case.truth_json.read_text())
    offset = truth["effect"]["params"]["offset"][0]
    clean = read_csv(tmp_path / "ident_clean.csv")
    rigid = np.column_stack([clean[f"tau{j + 1}"] for j in range(4)]) - [0, 0, offset, 0]
    noise_std = 0.01 * np.abs(rigid).max(axis=0)  # "medium": 1 % of each joint's peak rigid-body torque
    assert abs(offset) == pytest.approx(2.0 * np.sqrt(np.sum(noise_std**2)), rel=2e-3)
    assert case.effect_visible == pytest.approx(2.0, rel=0.15)  # on the validation run, against the noise drawn


def test_blind_specs_cover_rates_noise_and_effects():
    from blindgen import blind_specs

    clean = blind_specs("clean", 20)
    assert len(clean) == 20 and {c["rate_hz"] for c in clean} == {100, 200, 500, 1000}
    assert {c["noise"] for c in clean} == {"low", "medium", "high"} and {c["velocity"] for c in clean} == {True, False}
    assert {c["currents"] for c in clean} == {True, False} and len({c["seed"] for c in clean}) == 20
    eff = blind_specs("effects", 5)
    assert len(eff) == 5 * len(EFFECTS) and {e["effect"] for e in eff} == set(EFFECTS)
    for name in EFFECTS:
        assert len({e["effect_snr"] for e in eff if e["effect"] == name}) == 5


def test_random_arms_and_excitations_stay_in_the_specified_ranges():
    from blindgen import random_fourier

    for seed in range(30):
        rng = np.random.default_rng(seed)
        n = 3 + seed % 5
        arm, boxes = random_arm(rng, n, "dh" if seed % 2 else "mdh", seed % 4 if seed % 3 == 0 else None)
        masses = [ln.mass for ln in arm.links]
        assert masses == sorted(masses, reverse=True) and 0.3 <= min(masses) and max(masses) <= 8.0
        for ln in arm.links:
            assert ln.a == 0.0 or 0.05 <= ln.a <= 0.5
            assert ln.d == 0.0 or 0.05 <= ln.d <= 0.5
            ev = np.linalg.eigvalsh(np.array(ln.inertia)[[0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(3, 3))
            assert ev[0] > 0 and ev[0] + ev[1] >= ev[2] * (1 - 1e-12)  # a real body: positive, triangle inequality
        f = random_fourier(rng, arm)
        assert 0.05 <= f.f0 <= 0.3 and 3 <= f.a.shape[1] <= 5
    assert sum(ln.alpha in (0.0, math.pi / 2, -math.pi / 2) for s in range(30)
               for ln in random_arm(np.random.default_rng(s), 6, "dh", None)[0].links) > 0.7 * 180


def test_distinct_fraction_finds_rigid_body_twins(tmp_path):
    """Rotor inertia on joint 1 is Izz1 (distinct 0); a declared offset absorbs an offset; a random joint avoids both."""
    kw = dict(n_joints=4, rate_hz=100, noise="low", duration_s=6.0, valid_duration_s=2.0, prismatic=False)
    on_1 = make_case(71, tmp_path / "a", effect="rotor_inertia", effect_joint=1, effect_size=0.2, **kw)
    assert on_1.effect_distinct < 1e-6
    on_3 = make_case(71, tmp_path / "b", effect="rotor_inertia", effect_joint=3, effect_size=0.2, **kw)
    assert on_3.effect_distinct > 0.1
    declared = make_case(71, tmp_path / "c", effect="torque_offset", effect_joint=2, effect_size=0.2,
                         declare=[{"effect": "torque_offset", "joint": 2}], **kw)
    assert declared.effect_distinct < 1e-6
    for seed in range(72, 76):
        drawn = make_case(seed, tmp_path / f"d{seed}", effect="rotor_inertia", **kw)
        assert drawn.effect_joint != 1 and drawn.effect_distinct >= 0.25


def test_oracle_reaches_the_noise_floor_and_the_effect_column_closes_the_gap(tmp_path):
    """Perfect kinematics + least squares: about the noise floor on clean data; the true effect's column takes it back there."""
    from blindgen import oracle_error

    kw = dict(n_joints=3, rate_hz=100, noise="medium", currents=True, duration_s=20.0, valid_duration_s=10.0)
    clean = make_case(81, tmp_path / "clean", **kw)
    o = oracle_error(clean)
    assert 0.99 * clean.noise_floor < o["before"] < 1.05 * clean.noise_floor and o["after"] is None
    eff = make_case(82, tmp_path / "eff", effect="coulomb_friction", effect_size=0.2, n_ident=2, **kw)
    o = oracle_error(eff)
    assert o["before"] > 2 * eff.noise_floor and o["after"] < 1.05 * eff.noise_floor


@pytest.mark.parametrize("kw", [dict(), dict(effect="cogging", n_ident=2, ptp=True, currents=True)])
def test_load_case_reads_back_what_make_case_returned(kw, tmp_path):
    from blindgen import load_case

    case = make_case(91, tmp_path, n_joints=3, rate_hz=100, duration_s=2.0, valid_duration_s=2.0, **kw)
    assert load_case(tmp_path) == case


def test_snr_size_is_capped_at_the_joint_torque(tmp_path):
    """A huge snr cannot make an effect larger than its joint's own rigid-body torque RMS."""
    case = make_case(62, tmp_path, n_joints=3, rate_hz=100, noise="low", effect="coulomb_friction", effect_joint=3, effect_snr=1e4,
                     duration_s=4.0, valid_duration_s=2.0)
    assert case.effect_size == 1.0 and case.effect_visible < 1e4 / 10

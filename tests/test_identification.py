"""End to end: simulated data with known parameters through ``armid identify``."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from conftest import ROBOTS, ROOT, SHARED

from armid.cli import main
from armid.identify.errors import RobotFileError
from armid.identify.pinocchio_bridge import to_pinocchio
from armid.identify.trajectories import random_fourier_trajectory
from armid.io.recordings import write_csv
from armid.io.robot_file import load_robot


def _simulate(robot_file, path, seed, noise=0.0, with_qdd=True, duration=8.0):  # type: ignore[no-untyped-def]
    """Torques from Pinocchio's RNEA on a Fourier trajectory, plus declared friction."""
    robot = load_robot(robot_file)
    model = to_pinocchio(robot)
    data = model.createData()
    traj = random_fourier_trajectory(robot, harmonics=5, base_frequency_hz=0.125, fill=0.7, seed=seed)
    t = np.arange(0.0, duration, 0.002)
    q, qd, qdd = traj.evaluate(t)
    tau = np.array([pin.rnea(model, data, q[k], qd[k], qdd[k]) for k in range(t.size)])
    rng = np.random.default_rng(seed + 50)
    tau += 0.5 * qd + 0.8 * np.sign(qd)  # viscous and Coulomb, as puma560.yaml declares
    tau += noise * rng.normal(size=tau.shape) * np.std(tau, axis=0)
    cols = {"q": q, "qd": qd}
    if with_qdd:
        cols["qdd"] = qdd
    cols["tau"] = tau
    write_csv(path, t, cols)


def test_noise_free_validation_error_below_1e6(tmp_path):  # type: ignore[no-untyped-def]
    robot = ROBOTS / "puma560.yaml"
    _simulate(robot, tmp_path / "a.csv", seed=3)
    _simulate(robot, tmp_path / "b.csv", seed=4)
    out = tmp_path / "r.json"
    pred = tmp_path / "pred.csv"
    code = main(["identify", str(tmp_path / "a.csv"), "--robot", str(robot), "--validate", str(tmp_path / "b.csv"), "--json", str(out), "--predictions", str(pred), "--report", str(tmp_path / "rep")])
    assert code == 0
    doc = json.loads(out.read_text())
    assert doc["validation"]["relative_error"] < 1e-6
    assert {"robot", "n_joints", "samples", "condition_number", "parameters", "base_parameters", "effects", "fit", "validation"} <= set(doc)
    # 36 inertial, 12 friction, and the rotor inertias of joints 3-6: ia1 joins Izz1's
    # combination (vertical first axis) and ia2 joins Izz2's (link 2's Izz never reaches row 1)
    assert len(doc["parameters"]) == 60 and len(doc["base_parameters"]) == 52
    fc = [e["parameters"]["fc"] for e in doc["effects"] if e["effect"] == "coulomb_friction"]
    assert np.allclose(fc, 0.8, atol=1e-6)
    header = pred.read_text().splitlines()[0]
    assert header == "t," + ",".join(f"tau_hat{j}" for j in range(1, 7))
    assert (tmp_path / "rep" / "report.md").exists() and (tmp_path / "rep" / "joint6.png").exists()
    for p in doc["parameters"]:
        assert (p["value"] is None) == (p["identifiability"] != "unique")


def test_predictions_at_the_stamps_are_kept_read_only_and_not_pickled(tmp_path):  # type: ignore[no-untyped-def]
    """A result computes its prediction at a list of segments' stamps once (the diagnosis's
    gates and report read the validation's again): the same arrays each time, read-only so
    that no caller can change what the next one reads, equal to a fresh result's, and left
    out of a pickle (they hold the segments)."""
    import pickle

    from armid.identify.identification import identify
    from armid.identify.preprocess import prepare
    from armid.io.recordings import read_recording

    robot = load_robot(ROBOTS / "puma560.yaml")
    _simulate(ROBOTS / "puma560.yaml", tmp_path / "a.csv", seed=3, noise=0.01)
    _simulate(ROBOTS / "puma560.yaml", tmp_path / "b.csv", seed=4, noise=0.01)
    ident, valid = (prepare(read_recording(tmp_path / f"{n}.csv", robot), robot) for n in ("a", "b"))
    result = identify(robot, [ident], [valid])
    segments = list(valid.segments)
    first, again = result.predict_stamps(segments), result.predict_stamps(list(valid.segments))
    assert all(a is b for a, b in zip(first, again)) and not any(a.flags.writeable for a in first)
    with pytest.raises(ValueError):
        first[2][0, 0] = 0.0
    fresh = pickle.loads(pickle.dumps(result))
    assert fresh._at_stamps == {}
    assert all(np.array_equal(a, b) for a, b in zip(fresh.predict_stamps(segments), first))


@pytest.mark.parametrize("seed", [5, 6])
def test_noisy_estimates_within_three_sigma(tmp_path, seed):  # type: ignore[no-untyped-def]
    robot_file = ROBOTS / "puma560.yaml"
    _simulate(robot_file, tmp_path / "a.csv", seed=seed, noise=0.02, with_qdd=False)
    out = tmp_path / "r.json"
    assert main(["identify", str(tmp_path / "a.csv"), "--robot", str(robot_file), "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    inertial = [b for b in doc["base_parameters"] if not b["expression"].startswith(("fv", "fc"))]
    z = np.array([(b["value"] - b["modeled"]) / b["std"] for b in inertial])
    assert len(z) == 40  # 36 rigid-body base parameters and the rotor inertias ia3..ia6 (0 in this data)
    assert np.all(np.abs(z) < 3.0 + 0.5), z  # 3 sigma; 36 draws may brush 3.0
    assert np.mean(np.abs(z) < 3.0) >= 0.94
    friction = {(e["effect"], e["joint"]): (e["parameters"], e["std"]) for e in doc["effects"]}
    for (name, _), (value, std) in friction.items():
        if name == "rotor_inertia":
            continue  # in the combinations above
        key = "fv" if name == "viscous_friction" else "fc"
        assert abs(value[key] - (0.5 if key == "fv" else 0.8)) < 3.5 * std[key]


@pytest.mark.parametrize(
    "text, field",
    [
        ("name: x\njoints: []\n", "joints"),
        ("name: x\njoints:\n  - {a: 0, alpha: 0, d: 0}\n", "joints[0].theta"),
        ("name: x\njoints:\n  - {a: 0, alpha: zero, d: 0, theta: 0}\n", "joints[0].alpha"),
        ("name: x\nconvention: craig\njoints:\n  - {a: 0, alpha: 0, d: 0, theta: 0}\n", "convention"),
        ("name: x\njoints:\n  - {a: 0, alpha: 0, d: 0, theta: 0, type: spherical}\n", "joints[0].type"),
        ("name: x\njoints:\n  - {a: 0, alpha: 0, d: 0, theta: 0, limits: {position: [1, -1]}}\n", "joints[0].limits.position"),
        ("name: x\njoints:\n  - {a: 0, alpha: 0, d: 0, theta: 0, inertial: {mass: 1, com: [0, 0]}}\n", "joints[0].inertial.inertia"),
        ("name: x\njoints:\n  - {a: 0, alpha: 0, d: 0, theta: 0}\neffects: [{effect: magic, joint: 1}]\n", "effects[0].effect"),
        ("name: x\njoints:\n  - {a: 0, alpha: 0, d: 0, theta: 0}\neffects: [{effect: coulomb_friction, joint: 4}]\n", "effects[0].joint"),
        ("name: x\njoints:\n  - {a: 0, alpha: 0, d: 0, theta: 0}\neffects: [{effect: cogging, joint: 1}]\n", "effects[0].period_rad"),
        ("name: x\njoints:\n  - {a: 0, alpha: 0, d: 0, theta: 0}\neffects: [{effect: cogging, joint: 1, period_rad: -1}]\n", "effects[0].period_rad"),
        ("name: x\njoints:\n  - {a: 0, alpha: 0, d: 0, theta: 0, torque_constant: 2, torque_constant_std: 5}\n", "joints[0].torque_constant_std"),
        ("name: x\njoints:\n  - {a: 0, alpha: 0, d: 0, theta: 0}\neffects: [{effect: rotor_inertia, joint: 1, modeled: -0.2}]\n", "effects[0].modeled"),
        ("name: x\njoints:\n  - {a: 0, alpha: 0, d: 0, theta: 0}\n  - {a: 0, alpha: 0, d: 0, theta: 0}\neffects: [{effect: rotor_inertia, joint: null, modeled: [0.2]}]\n",
         "effects[0].modeled"),
        ("name: x\njoints:\n  - {a: 0, alpha: 0, d: 0, theta: 0}\neffects: [{effect: cogging, joint: 1, period_rad: 1, modeled: 1}]\n", "effects[0].modeled"),
        ("name: x\njoints:\n  - {a: 0, alpha: 0, d: 0, theta: 0}\neffects: [{effect: spring, joint: 1, modeled: .nan}]\n", "effects[0].modeled"),
        ("name: x\njoints: [\n", "line"),
        ("name: x\nurdf: nothere.urdf\njoints: [{name: a}]\n", "urdf"),
    ],
)
def test_malformed_robot_file_names_file_and_field(tmp_path, text, field):  # type: ignore[no-untyped-def]
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(RobotFileError) as err:
        load_robot(path)
    assert str(err.value).startswith(f"{path}: {field}")


def test_a_modeled_value_reaches_its_joint_from_a_number_or_a_list(tmp_path):  # type: ignore[no-untyped-def]
    """``modeled`` on one joint may be written ``0.3`` or ``[0.3]`` (the file's check takes
    both), on ``joint: null`` one value per joint. The diagnosis's per-joint copy of the effects
    read a list by the joint's number: ``[0.3]`` on joint 2 stopped ``armid diagnose`` with an
    IndexError."""
    from armid.identify.diagnosis.refit import settled_robot
    from armid.identify.identification import declared_effects
    from armid.identify.single_link import modeled_effect_values

    path = tmp_path / "r.yaml"
    path.write_text("name: x\njoints:\n  - {a: 0, alpha: 0, d: 0, theta: 0}\n  - {a: 1, alpha: 0, d: 0, theta: 0}\neffects:\n"
                    "  - {effect: rotor_inertia, joint: 2, modeled: [0.3]}\n  - {effect: viscous_friction, joint: null, modeled: [0.1, 0.2]}\n")
    robot = load_robot(path)
    expected = {("rotor_inertia", 1): 0.3, ("viscous_friction", 0): 0.1, ("viscous_friction", 1): 0.2}
    got = dict(zip([(e.effect, e.joint) for e in declared_effects(robot)], modeled_effect_values(robot)))
    assert got == expected, got

    class Unsettled:  # an identification that chose no effect settings
        effects: list[object] = []

    settled = settled_robot(robot, Unsettled())  # type: ignore[arg-type]
    assert {(e.effect, e.joint): e.options["modeled"] for e in settled.effects} == {(k, j + 1): v for (k, j), v in expected.items()}

def test_a_torque_constant_is_known_to_5_percent_unless_the_file_says_and_a_sensor_exactly(tmp_path):  # type: ignore[no-untyped-def]
    path = tmp_path / "r.yaml"
    path.write_text("name: x\njoints:\n  - {a: 0, alpha: 0, d: 0, theta: 0, torque_constant: 2}\n"
                    "  - {a: 1, alpha: 0, d: 0, theta: 0, torque_constant: 2, torque_constant_std: 0.01}\n"
                    "  - {a: 1, alpha: 0, d: 0, theta: 0}\n")
    assert [j.torque_constant_std for j in load_robot(path).joints] == [0.05, 0.01, 0.0]


def test_unknown_urdf_joint_lists_the_real_ones(tmp_path):  # type: ignore[no-untyped-def]
    path = tmp_path / "r.yaml"
    path.write_text(f"name: x\nurdf: {ROBOTS / 'ur5.urdf'}\njoints: [{{name: shoulder_pan_joint}}, {{name: elbow}}]\n")
    with pytest.raises(RobotFileError, match=r"joints\[1\].name: no joint 'elbow'.*elbow_joint"):
        load_robot(path)


def test_cli_bad_input_exits_2_with_one_line(tmp_path):  # type: ignore[no-untyped-def]
    bad = tmp_path / "bad.csv"
    bad.write_text("t,q1\n0,1\n")
    proc = subprocess.run(
        [sys.executable, "-m", "armid.cli", "identify", str(bad), "--robot", str(ROBOTS / "planar2.yaml")],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "bad.csv" in lines[0] and "Traceback" not in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "armid.cli", "identify", "--robot"], capture_output=True, text=True)
    assert proc.returncode == 2


@pytest.mark.skipif(not (SHARED / "data" / "kuka_lwr4" / "measurements_1.npz").exists(), reason="shared KUKA data not beside the repository")
def test_kuka_lwr4_real_data_identifies_and_validates(tmp_path):  # type: ignore[no-untyped-def]
    data = SHARED / "data" / "kuka_lwr4"
    out = tmp_path / "k.json"
    code = main(["identify", str(data / "measurements_1.npz"), "--robot", str(ROBOTS / "kuka_lwr4.yaml"), "--validate", str(data / "measurements_2.npz"), "--json", str(out)])
    assert code == 0
    doc = json.loads(out.read_text())
    assert doc["n_joints"] == 7 and doc["samples"] > 4000
    # the identified model must beat the CAD model with friction reported for this data
    published_rms = [0.36, 1.55, 0.49, 0.98, 0.63, 0.49, 0.27]
    assert np.all(np.array(doc["validation"]["rms"]) < published_rms)
    # well excited: every base parameter identified, three sigmas inside its physical range (issue 62)
    base = doc["base_parameters"]
    assert all(b["identified"] for b in base) and max(3 * b["std"] / b["physical_range"] for b in base) < 0.1
    assert all(p["identified"] == (p["identifiability"] == "unique") for p in doc["parameters"])


def test_a_barely_excited_link_s_combinations_are_not_identified_by_these_data(tmp_path, capsys):  # type: ignore[no-untyped-def]
    """Issue 62: a combination whose three sigmas exceed its physical range (the arm's mass,
    mass x reach, mass x reach^2; a joint's torque over its speed for viscous friction) is
    printed and written as not identified by these data; its value and std are unchanged.
    The Dynamixel arm: link 5's run moves 0.06 rad for 3 s with 0.2 N*m of torque noise."""
    kw = {"robot_file": "dxl_arm6.yaml", "rig_file": "sim_dynamixel.yaml"}
    runs = [str(_single_joint_run(tmp_path / f"link{j + 1}.csv", j, 0.4, j, **kw,
                                  **({"amplitude": 0.06, "noise_nm": 0.2, "duration": 3.0} if j == 4 else {}))) for j in range(6)]
    out = tmp_path / "seq.json"
    assert main(["identify", *runs, "--robot", str(ROBOTS / "dxl_arm6.yaml"), "--single-link", "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    table = json.loads(out.read_text())["single_link"]["table"]
    weak = [row for row in table if not row["identified"]]
    assert [(row["link"], row["parameter"]) for row in weak] == [(5, "fv5")], weak
    [row] = weak
    assert 3 * row["std"] > row["physical_range"] and row["physical_range"] == pytest.approx(3.5 / 4.5)  # torque / speed limit
    assert f"link 5: fv5: not identified by these data (+-{3 * row['std']:.3g} at 3 sigma against a physical range of 0.778)" in printed
    assert "dxl_arm6: single-link sequence over links 6, 5, 4, 3, 2, 1: 23 combinations identified, 1 not identified by these data" in printed
    # the well-excited links stay identified
    assert all(row["identified"] for row in table if row["link"] != 5)


@pytest.mark.skipif(not (SHARED / "data" / "kuka_lwr4" / "measurements_1.npz").exists(), reason="shared KUKA data not beside the repository")
def test_a_urdf_inertia_with_a_negative_moment_is_a_warning(tmp_path, capsys):  # type: ignore[no-untyped-def]
    """CAD exports round products of inertia: a URDF's non-positive-semi-definite tensor warns
    (it is only the prior) instead of refusing the robot, and the physically consistent fit
    still runs. Written in the robot file itself, it is refused (test_fuzz)."""
    urdf = (ROBOTS / "kuka_lwr4.urdf").read_text()
    bad = '<inertia ixx="0.01845" ixy="0.02" ixz="0" iyy="0.00405" iyz="0" izz="0.01602"/>'
    urdf = urdf.replace('<inertia ixx="0.01845" ixy="0" ixz="0" iyy="0.00405" iyz="0" izz="0.01602"/>', bad, 1)
    assert bad in urdf
    (tmp_path / "kuka_lwr4.urdf").write_text(urdf)
    (tmp_path / "r.yaml").write_text((ROBOTS / "kuka_lwr4.yaml").read_text())
    whole = dict(np.load(SHARED / "data" / "kuka_lwr4" / "measurements_1.npz"))
    np.savez(tmp_path / "a.npz", **{k: v[:2500] for k, v in whole.items()})
    np.savez(tmp_path / "b.npz", **{k: v[2500:4000] for k, v in whole.items()})
    out = tmp_path / "f.json"
    assert main(["identify", str(tmp_path / "a.npz"), "--robot", str(tmp_path / "r.yaml"), "--validate", str(tmp_path / "b.npz"),
                 "--feasible", "--json", str(out)]) == 0
    err = capsys.readouterr().err
    assert re.search(r"joints\[0\] \(kuka_lwr4\.urdf\)\.inertia: not positive semi-definite.*used as the prior", err), err
    feasible = json.loads(out.read_text())["feasible"]
    assert feasible["status"] == "optimal" and feasible["feasible"]["consistent"] and feasible["feasible"]["validation"]["relative_error"] < 0.05


@pytest.mark.skipif(not (SHARED / "data" / "kuka_lwr4" / "measurements_1.npz").exists(), reason="shared KUKA data not beside the repository")
def test_a_torque_unlike_the_model_is_warned_about(tmp_path, capsys):  # type: ignore[no-untyped-def]
    """Parses, is plausible row by row, and identifies: a sensor's flipped sign or a missing
    torque constant shows only against the robot file's modeled torque. The KUKA's own
    recordings, whose light wrist joints 5 and 7 correlate -0.7 with their CAD model, are not
    warned about."""
    whole = {k: v[:2500] for k, v in np.load(SHARED / "data" / "kuka_lwr4" / "measurements_1.npz").items()}
    cases = {"plain.npz": (whole["torques"], None),
             "flipped.npz": (whole["torques"] * np.array([1, -1, 1, 1, 1, 1, 1]),
                             r"flipped\.npz: column tau2: joint 2's torque runs opposite to the robot file's modeled torque"),
             "amps.npz": (whole["torques"] * 0.05, r"amps\.npz: column tau2: joint 2 measures 0\.0[45]\d* times the robot file's modeled torque.*torque_constant"),
             "negated.npz": (-whole["torques"], r"negated\.npz: the torques of all joints together run opposite to the robot file's modeled torque")}
    for name, (tau, said) in cases.items():
        np.savez(tmp_path / name, **(whole | {"torques": tau}))
        assert main(["identify", str(tmp_path / name), "--robot", str(ROBOTS / "kuka_lwr4.yaml")]) == 0
        err = capsys.readouterr().err
        assert re.search(said, err) if said else "modeled torque" not in err, err


@pytest.mark.skipif(not (SHARED / "data" / "kuka_lwr4" / "measurements_1.npz").exists(), reason="shared KUKA data not beside the repository")
@pytest.mark.parametrize("kind", ["continuous", "limits 200 rad apart"])
def test_continuous_joints_and_their_wrapped_angles(kind, tmp_path):  # type: ignore[no-untyped-def]
    """A URDF's continuous joints (Pinocchio's cos/sin joints) are revolute joints without
    position limits, and a logger's (-pi, pi] wraps of their angle are undone, as for a joint
    whose limits are more than a turn apart (Kinova's +-100 rad): the KUKA's base joint turns
    about gravity, so its recording turned by 2.5 rad and wrapped must identify exactly as the
    recording itself."""
    data = SHARED / "data" / "kuka_lwr4"
    urdf = (ROBOTS / "kuka_lwr4.urdf").read_text()
    if kind == "continuous":
        urdf = urdf.replace('type="revolute"', 'type="continuous"')
    else:
        urdf = urdf.replace('lower="-2.96705972839" upper="2.96705972839"', 'lower="-100" upper="100"', 1)
    (tmp_path / "continuous.urdf").write_text(urdf)
    yaml = (ROBOTS / "kuka_lwr4.yaml").read_text().replace("urdf: kuka_lwr4.urdf", "urdf: continuous.urdf")
    assert "continuous.urdf" in yaml
    (tmp_path / "continuous.yaml").write_text(yaml)
    plain, continuous = load_robot(ROBOTS / "kuka_lwr4.yaml"), load_robot(tmp_path / "continuous.yaml")
    assert continuous.joints[0].limits.position == (None if kind == "continuous" else (-100.0, 100.0))
    for a, b in zip(plain.joints, continuous.joints):
        assert a.revolute and b.revolute and a.limits.position is not None
        np.testing.assert_allclose(b.axis, a.axis, atol=1e-12)
        np.testing.assert_allclose(b.pre, a.pre, atol=1e-12)
        assert b.inertial == a.inertial

    whole = dict(np.load(data / "measurements_1.npz"))
    for part, rows in (("ident", slice(0, 2500)), ("valid", slice(2500, 4000))):
        rec = {k: v[rows] for k, v in whole.items()}
        np.savez(tmp_path / f"plain_{part}.npz", **rec)
        turned = rec["positions"].copy()
        turned[:, 0] = np.angle(np.exp(1j * (turned[:, 0] + 2.5)))
        assert np.any(np.abs(np.diff(turned[:, 0])) > np.pi)  # the angle wraps
        np.savez(tmp_path / f"wrapped_{part}.npz", **(rec | {"positions": turned}))

    out = {}
    for name, robot in (("plain", ROBOTS / "kuka_lwr4.yaml"), ("wrapped", tmp_path / "continuous.yaml")):
        pred = tmp_path / f"{name}.csv"
        assert main(["identify", str(tmp_path / f"{name}_ident.npz"), "--robot", str(robot), "--validate", str(tmp_path / f"{name}_valid.npz"), "--predictions", str(pred), "--json", str(tmp_path / f"{name}.json")]) == 0
        out[name] = np.genfromtxt(pred, delimiter=",", names=True)
    assert out["wrapped"].shape == out["plain"].shape
    for field in out["plain"].dtype.names:
        np.testing.assert_allclose(out["wrapped"][field], out["plain"][field], rtol=1e-6, atol=1e-6 * np.abs(whole["torques"]).max())
    doc = json.loads((tmp_path / "wrapped.json").read_text())
    assert any("unwrapped" in note and "lwr_0_joint" in note for note in doc["preprocessing"])


def test_column_trials_give_the_least_squares_of_the_replaced_system() -> None:
    """A setting's try replaces a few columns of a joint's [W | y]; the rows ColumnTrials
    returns must give the same least-squares fit and residual as the replaced system itself,
    alone and stacked with another joint's rows sharing its parameters."""
    from armid.identify.estimation import ColumnTrials, JointFactors, solve_factors

    rng = np.random.default_rng(3)
    rows = rng.normal(size=(400, 9))
    other = rng.normal(size=(300, 9))
    trials = ColumnTrials(rows, [2, 5])
    for _ in range(3):
        new = rng.normal(size=(400, 2))
        replaced = rows.copy()
        replaced[:, [2, 5]] = new
        direct = solve_factors(JointFactors([np.linalg.qr(replaced, mode="r"), np.linalg.qr(other, mode="r")], np.array([400.0, 300.0])), "ols")
        tried = solve_factors(JointFactors([trials.rows(new), np.linalg.qr(other, mode="r")], np.array([400.0, 300.0])), "ols")
        np.testing.assert_allclose(tried.beta, direct.beta, rtol=1e-9, atol=1e-12)
        w, y = np.vstack([replaced, other])[:, :-1], np.vstack([replaced, other])[:, -1]
        np.testing.assert_allclose(tried.beta, np.linalg.lstsq(w, y, rcond=None)[0], rtol=1e-9, atol=1e-12)


def test_refined_setting_lands_between_grid_values_and_stays_inside_the_grid() -> None:
    """The search refines the best grid value towards the score's minimum (within about 8 %),
    keeps a sharp sign (0) when that is best, and never goes above the grid's largest value."""
    from armid.identify.identification import _refine

    grid = (0.0, 0.003, 0.01, 0.03, 0.1)
    for true in (0.0021, 0.02, 0.045, 0.07):
        tried: list[float] = []

        def score(v: float, true: float = true, tried: list[float] = tried) -> float:
            tried.append(v)
            return 1.0 + (np.log(max(v, 1e-6) / true)) ** 2

        chosen = _refine(grid, score)
        assert abs(np.log(chosen / true)) < np.log(1.09), (true, chosen)
        assert max(tried) <= 0.1
    assert _refine(grid, lambda v: v) == 0.0
    assert _refine(grid, lambda v: -v) == 0.1


def test_a_long_segment_goes_through_its_parallel_filter_in_blocks_with_the_same_equations() -> None:
    """A long 1 kHz log's full-rate regressor would not fit in memory whole: it is filtered in
    blocks with ``settling`` samples on either side, and must give the whole segment's
    equations (to rounding: the filter's response to a block's cut has died out)."""
    from armid.identify import equations
    from armid.identify import identification as ident
    from armid.identify.filtering import ParallelFilter
    from armid.identify.preprocess import Segment

    robot = load_robot(ROBOTS / "puma560.yaml")
    period = 0.001
    t = np.arange(40_000) * period
    rng = np.random.default_rng(3)
    w = 2 * np.pi * np.array([0.11, 0.23, 0.37])
    a = rng.normal(0.0, 0.4, (3, robot.n_joints))
    q = np.sin(np.outer(t, w)) @ a
    qd = (np.cos(np.outer(t, w)) * w) @ a
    qdd = -(np.sin(np.outer(t, w)) * w**2) @ a
    tau = rng.normal(0.0, 1.0, q.shape)
    seg = Segment("<long>", t, q, qd, qdd, tau, filter=ParallelFilter(period, cutoff_hz=3.0, decimation=30))
    effects = ident.declared_effects(robot)
    whole = equations.regression_system(robot, effects, [seg])
    n_cols = whole.shape[1]
    saved = equations.EQUATION_BYTES
    try:
        equations.EQUATION_BYTES = 8 * robot.n_joints * n_cols * 6_000  # blocks of 6,000 samples: seven of them
        blocked = equations.regression_system(robot, effects, [seg])
    finally:
        equations.EQUATION_BYTES = saved
    assert seg.parallel.settling < 6_000 < seg.n_samples // 6
    assert blocked.shape == whole.shape
    scale = np.abs(whole).max(axis=2, keepdims=True)
    assert np.all(np.abs(blocked - whole) <= 1e-10 * np.maximum(scale, 1e-300))


def test_every_torque_negated_is_warned_about_where_no_single_joint_shows_it(tmp_path, capsys):  # type: ignore[no-untyped-def]
    """The PUMA example's model lacks its large rotor inertias: no joint correlates beyond
    0.72 with it, so a flipped joint passes the per-joint check; every torque negated shows
    in the joints pooled (0.48 -> -0.48), and the example itself is not warned about."""
    lines = (ROOT / "examples" / "puma560_excitation.csv").read_text().splitlines()
    header = lines[0].split(",")
    taus = [i for i, h in enumerate(header) if h.startswith("tau")]
    negated = [",".join(str(-float(v)) if i in taus else v for i, v in enumerate(line.split(","))) for line in lines[1:]]
    (tmp_path / "negated.csv").write_text("\n".join([lines[0], *negated]) + "\n")
    for path, said in ((tmp_path / "negated.csv", True), (ROOT / "examples" / "puma560_excitation.csv", False)):
        assert main(["identify", str(path), "--robot", str(ROBOTS / "puma560.yaml")]) == 0
        err = capsys.readouterr().err
        assert ("the torques of all joints together run opposite" in err) == said, err


def _single_joint_run(path, joint, frequency_hz, seed, duration=8.0, robot_file="puma560.yaml", rig_file="sim.yaml",  # type: ignore[no-untyped-def]
                      amplitude=1.0, noise_nm=None):
    """Joint ``joint`` (0-based) alone moving (two sines, ``amplitude`` times 0.4 and 0.15 rad),
    the others held at the simulated rig's start pose; torques from Pinocchio's RNEA plus the
    declared friction, 1 % noise (or white noise of ``noise_nm`` N*m)."""
    from armid.io.rig_file import load_rig

    robot = load_robot(ROBOTS / robot_file)
    model = to_pinocchio(robot)
    data = model.createData()
    q0 = np.asarray(load_rig(ROOT / "config" / "rigs" / rig_file).simulation["initial_position"], float)
    t = np.arange(0.0, duration, 0.002)
    w1, w2 = 2 * np.pi * frequency_hz, 2 * np.pi * 2.3 * frequency_hz
    n = robot.n_joints
    q, qd, qdd = np.tile(q0, (t.size, 1)), np.zeros((t.size, n)), np.zeros((t.size, n))
    q[:, joint] += amplitude * (0.4 * np.sin(w1 * t) + 0.15 * np.sin(w2 * t))
    qd[:, joint] = amplitude * (0.4 * w1 * np.cos(w1 * t) + 0.15 * w2 * np.cos(w2 * t))
    qdd[:, joint] = amplitude * (-0.4 * w1**2 * np.sin(w1 * t) - 0.15 * w2**2 * np.sin(w2 * t))
    tau = np.array([pin.rnea(model, data, q[k], qd[k], qdd[k]) for k in range(t.size)]) + 0.5 * qd + 0.8 * np.sign(qd)
    rng = np.random.default_rng(seed)
    tau += (0.01 * rng.normal(size=tau.shape) * np.maximum(np.std(tau, axis=0), 1e-3) if noise_nm is None
            else noise_nm * rng.normal(size=tau.shape))
    write_csv(path, t, {"q": q, "qd": qd, "qdd": qdd, "tau": tau})
    return path


def test_khoslas_single_link_sequence_from_the_users_recordings(tmp_path):  # type: ignore[no-untyped-def]
    """Issue 33: ``armid identify --single-link``: six recordings, each moving one joint (data
    from Pinocchio's RNEA, not armid's regressor), identified last link first; a held-out run
    of joint 2 at another frequency is predicted at the noise level; a run moving two joints is
    refused by name."""
    runs = [str(_single_joint_run(tmp_path / f"link{j + 1}.csv", j, 0.4, j)) for j in range(6)]
    validation = str(_single_joint_run(tmp_path / "val2.csv", 1, 0.27, 99))
    out, predictions = tmp_path / "seq.json", tmp_path / "pred.csv"
    assert main(["identify", *runs, "--robot", str(ROBOTS / "puma560.yaml"), "--single-link", "--validate", validation,
                 "--json", str(out), "--predictions", str(predictions)]) == 0
    doc = json.loads(out.read_text())
    assert doc["single_link"]["order"] == [6, 5, 4, 3, 2, 1]
    assert all(row["std"] > 0 for row in doc["single_link"]["table"])
    # every link well excited: every combination identified, well inside its physical range
    assert all(row["identified"] and 3 * row["std"] < 0.01 * row["physical_range"] for row in doc["single_link"]["table"])
    [v] = doc["validation"]
    assert v["joint"] == 2 and v["relative_error"] < 0.03, v  # 1 % noise on the torque
    header = predictions.read_text().splitlines()[0].split(",")
    assert header == ["t"] + [f"tau_hat{j}" for j in range(1, 7)]
    both = np.loadtxt(runs[0], delimiter=",", skiprows=1)
    both[:, 2] = both[:, 1]  # joint 2 moves with joint 1
    header_line = Path(runs[0]).read_text().splitlines()[0]
    np.savetxt(tmp_path / "two.csv", both, delimiter=",", header=header_line, comments="")
    assert main(["identify", str(tmp_path / "two.csv"), "--robot", str(ROBOTS / "puma560.yaml"), "--single-link"]) == 2


def test_the_lag_window_covariance_matches_the_exact_one_where_batch_means_fall_short() -> None:
    """Least squares on smooth columns with MA(1) noise (white current noise, torques averaged
    with their neighbour as a held current is re-timed): the exact covariance of the estimate
    is ``B A^T Sigma A B``. Over 400 draws the lag-window sandwich (single-link steps) must
    average to it within 3 %; batch means of 8 samples, cut at block edges and blind to what
    the fit took out of the residual, average about 10 % short (they did on the demo's steps)."""
    from armid.identify.estimation import batch_means_covariance, lag_window_covariance

    rng = np.random.default_rng(11)
    n, p = 1500, 5
    t = np.linspace(0.0, 4.0, n)
    a = np.column_stack([np.sin(2 * np.pi * f * t + ph) for f, ph in zip((0.5, 1.0, 1.5, 2.5), (0.3, 1.1, 2.0, 0.7))]
                        + [np.sign(np.sin(2 * np.pi * 0.5 * t))])
    bread = np.linalg.inv(a.T @ a)
    sigma = np.zeros((n, n))  # e_t = (w_t + w_{t+1}) / 2, w white with unit variance
    idx = np.arange(n)
    sigma[idx, idx] = 0.5
    sigma[idx[:-1], idx[:-1] + 1] = sigma[idx[:-1] + 1, idx[:-1]] = 0.25
    exact = np.diag(bread @ a.T @ sigma @ a @ bread)
    lag_window, batch = np.zeros(p), np.zeros(p)
    draws = 400
    for _ in range(draws):
        w = rng.normal(size=n + 1)
        e = 0.5 * (w[:-1] + w[1:])
        beta = bread @ a.T @ e
        r = e - a @ beta
        lag_window += np.diag(lag_window_covariance(bread, a, r, 4)) / draws
        batch += np.diag(batch_means_covariance(bread, a * r[:, None], 8)) / draws
    assert np.all(np.abs(lag_window / exact - 1) < 0.03), lag_window / exact
    assert np.all(batch / exact < 0.96), batch / exact  # what the single-link steps used before


def test_the_lag_window_covariance_is_never_zero_where_the_residual_correlations_sum_below_zero() -> None:
    """A twice-differentiated quantised position leaves residuals correlated -0.3 and -0.6 at
    lags 1 and 2 where torques are nearly noise-free (the simulated KUKA): a flat window's meat
    is then negative definite, and clipped, it made every standard deviation of the step 0.
    The Bartlett window (Newey-West) is used there: positive, and not below the exact variance."""
    from armid.identify.estimation import bartlett_meat, lag_window_covariance

    rng = np.random.default_rng(5)
    n = 1500
    t = np.linspace(0.0, 4.0, n)
    a = np.column_stack([np.sin(2 * np.pi * 0.5 * t + 0.3), np.cos(2 * np.pi * 1.5 * t), np.ones(n)])
    bread = np.linalg.inv(a.T @ a)
    w = rng.normal(size=n + 3)
    e = w[3:] - w[2:-1] - w[1:-2] + w[:-3]  # correlated -0.25 and -0.5 at lags 1 and 2, summing to zero at 3
    r = e - a @ (bread @ a.T @ e)
    sigma = sum(g * (np.eye(n, k=k) + np.eye(n, k=-k)) for g, k in ((-1.0, 1), (-2.0, 2), (1.0, 3))) + 4.0 * np.eye(n)
    exact = np.diag(bread @ a.T @ sigma @ a @ bread)
    got = np.diag(lag_window_covariance(bread, a, r, 2))
    assert np.all(got > exact), (got, exact)
    scores = a * r[:, None]
    brute = sum((1 - abs(k) / 3) * scores[max(0, -k): n - max(0, k)].T @ scores[max(0, k): n - max(0, -k)] for k in range(-2, 3))
    assert np.allclose(bartlett_meat(scores, 2), brute, rtol=1e-12, atol=0.0)

def test_fits_that_reuse_earlier_fits_equations_build_the_same_system() -> None:
    """Within ``reused_equations`` (the diagnosis's dozen fits of one recording), a fit takes
    each joint's filtered rigid-body rows, effect columns and torque from the fits before it
    and computes only what changed: a finding's columns on one joint, a drive gain or delay on
    one joint's torque, a load-dependent friction's load. Each system must be the one built
    from nothing, to the bit, with and without a low-pass."""
    from armid.identify import equations
    from armid.identify import identification as ident
    from armid.identify.effects import linear_effect, load_friction
    from armid.identify.filtering import ParallelFilter
    from armid.identify.preprocess import Segment

    robot = load_robot(ROBOTS / "puma560.yaml")
    rng = np.random.default_rng(4)
    t = np.arange(3_000) * 0.002
    w = 2 * np.pi * np.array([0.3, 0.7, 1.1])
    a = rng.normal(0.0, 0.5, (3, robot.n_joints))
    q, qd, qdd = np.sin(np.outer(t, w)) @ a, (np.cos(np.outer(t, w)) * w) @ a, -(np.sin(np.outer(t, w)) * w**2) @ a
    tau = rng.normal(0.0, 1.0, q.shape)
    declared = ident.declared_effects(robot)
    load = load_friction(robot, 2, rng.normal(size=robot.n_parameters), smoothing=0.01)
    fits = [(declared, None, None), (declared + [linear_effect("spring", 3)], None, None),
            (declared + [linear_effect("spring", 3)], np.array([1, 1, 1, 0.8, 1, 1.0]), None),
            (declared + [load], None, np.array([0, 0.004, 0, 0, 0, 0.0])), (declared + [load, linear_effect("viscous_friction", 1)], None, None),
            (declared, None, None)]
    for filt in (ParallelFilter(0.002, cutoff_hz=4.0, decimation=5), ParallelFilter(0.002, cutoff_hz=None, decimation=2)):
        segs = [Segment("<a>", t[:1700], q[:1700], qd[:1700], qdd[:1700], tau[:1700], filter=filt),
                Segment("<b>", t[1700:], q[1700:], qd[1700:], qdd[1700:], tau[1700:], filter=filt)]
        with equations.reused_equations():
            kept = [equations.regression_system(robot, e, segs, scale, delay) for e, scale, delay in fits]
        for (e, scale, delay), system in zip(fits, kept):
            assert np.array_equal(system, equations.regression_system(robot, e, segs, scale, delay))

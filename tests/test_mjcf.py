"""``--mjcf``: the physically consistent identified model as MJCF (armid/mjcf_export.py).

References that share no code with the writer: MuJoCo itself (``mujoco.mj_inverse`` on the
file it compiles) against Pinocchio's RNEA on the ``--urdf`` of the same run (its own URDF
parser), and on a robot's chain built by Pinocchio (``to_pinocchio``) where no URDF is read.
Friction and rotor inertia are compared as the terms of the dynamics they are: MuJoCo's
passive and armature forces against ``fv qd`` and ``ia qdd``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pinocchio as pin
import pytest
from conftest import ROBOTS, SHARED

from armid.identify.effects import linear_effect
from armid.identify.errors import IdentificationError
from armid.identify.pinocchio_bridge import to_pinocchio
from armid.io.robot_file import load_robot
from armid.mjcf_export import quaternion, write_mjcf

ROOT = Path(__file__).resolve().parent.parent
KUKA = SHARED / "data" / "kuka_lwr4"
STATES = 200


def _armid(*argv: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "armid.cli", *argv], capture_output=True, text=True, cwd=cwd, timeout=600)


def _rigid(path: Path) -> mujoco.MjModel:
    """The MJCF's model with friction and armature set to 0: its rigid body alone."""
    m = mujoco.MjModel.from_xml_path(str(path))
    m.dof_damping[:] = 0.0
    m.dof_frictionloss[:] = 0.0
    m.dof_armature[:] = 0.0
    m.jnt_stiffness[:] = 0.0
    return m


def _states(m: mujoco.MjModel, seed: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Random (q, qd, qdd) with q inside each joint's range (outside it MuJoCo's limit would push)."""
    rng = np.random.default_rng(seed)
    lo = np.where(m.jnt_limited, m.jnt_range[:, 0], -np.pi)
    hi = np.where(m.jnt_limited, m.jnt_range[:, 1], np.pi)
    return [(rng.uniform(lo, hi), rng.uniform(-2, 2, m.nv), rng.uniform(-5, 5, m.nv)) for _ in range(STATES)]


def _inverse(m: mujoco.MjModel, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:], d.qacc[:] = q, qd, qdd
    mujoco.mj_inverse(m, d)
    return d.qfrc_inverse.copy()


def _max_difference(m: mujoco.MjModel, model: pin.Model, seed: int) -> float:
    data = model.createData()
    return max(float(np.max(np.abs(_inverse(m, q, qd, qdd) - pin.rnea(model, data, q, qd, qdd)))) for q, qd, qdd in _states(m, seed))


def _feasible_effects(doc: dict) -> dict[tuple[str, int], float]:  # type: ignore[type-arg]
    return {(e["effect"], e["joint"]): e["value"] for e in doc["feasible"]["effects"]}


@pytest.fixture(scope="module")
def kuka(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, subprocess.CompletedProcess[str]]:
    """The README tour's identification of the KUKA with ``--urdf`` and ``--mjcf``."""
    if not (KUKA / "measurements_1.npz").exists():
        pytest.skip("shared KUKA data not present")
    out = tmp_path_factory.mktemp("kuka")
    done = _armid("identify", str(KUKA / "measurements_1.npz"), "--robot", str(ROBOTS / "kuka_lwr4.yaml"), "--json", "id.json",
                  "--urdf", "kuka.urdf", "--mjcf", "kuka.xml", cwd=out)
    assert done.returncode == 0, done.stderr
    return out, done


def test_kuka_mjcf_inverse_dynamics_is_pinocchio_rnea_on_the_urdf(kuka: tuple[Path, subprocess.CompletedProcess[str]]) -> None:
    out, _ = kuka
    robot = load_robot(ROBOTS / "kuka_lwr4.yaml")
    m = _rigid(out / "kuka.xml")
    assert m.nv == 7 and np.array_equal(m.opt.gravity, robot.gravity)
    model = pin.buildModelFromUrdf(str(out / "kuka.urdf"))
    model.gravity = pin.Motion(np.asarray(robot.gravity, float), np.zeros(3))
    worst = _max_difference(m, model, seed=64)
    print(f"KUKA LWR4+: MuJoCo mj_inverse on the MJCF against Pinocchio's RNEA on the URDF, {STATES} states: max |diff| {worst:.3g} N*m")
    assert worst < 1e-6


def test_kuka_mjcf_friction_is_the_declared_friction(kuka: tuple[Path, subprocess.CompletedProcess[str]]) -> None:
    """Viscous and Coulomb friction on every joint (the robot file declares both): damping and
    frictionloss positive, the feasible estimate's values; no rotor inertia declared, no
    armature; the torque offset has no MuJoCo term and the file and the output say so."""
    out, done = kuka
    doc = json.loads((out / "id.json").read_text())
    values = _feasible_effects(doc)
    m = mujoco.MjModel.from_xml_path(str(out / "kuka.xml"))
    damping = np.array([values[("viscous_friction", j)] for j in range(1, 8)])
    coulomb = np.array([values[("coulomb_friction", j)] for j in range(1, 8)])
    assert np.all(m.dof_damping > 0) and np.all(m.dof_frictionloss > 0)
    assert np.allclose(m.dof_damping, damping, rtol=1e-15, atol=0) and np.allclose(m.dof_frictionloss, coulomb, rtol=1e-15, atol=0)
    assert np.all(m.dof_armature == 0)
    said = "torque offset on joints 1, 2, 3, 4, 5, 6, 7"
    last = done.stdout.splitlines()[-1]
    assert last.endswith(f"URDF written to kuka.urdf; MJCF written to kuka.xml (no MuJoCo term, left out: {said})"), last
    text = (out / "kuka.xml").read_text()
    assert f"No MuJoCo equivalent, left out: {said}." in text and "Coulomb friction as frictionloss" in text
    # damping is MuJoCo's viscous term: with it alone the inverse dynamics gain fv * qd
    m = _rigid(out / "kuka.xml")
    q, qd, qdd = _states(m, seed=1)[0]
    rigid = _inverse(m, q, qd, qdd)
    m.dof_damping[:] = damping
    assert np.allclose(_inverse(m, q, qd, qdd) - rigid, damping * qd, rtol=1e-12, atol=1e-12)


def test_check_writes_the_model_checked(kuka: tuple[Path, subprocess.CompletedProcess[str]]) -> None:
    """``armid check --mjcf`` where the model holds (recording 2 repeats recording 1): nothing
    changed, so the file is the identification's, byte for byte; the URDF too."""
    out, _ = kuka
    done = _armid("check", str(KUKA / "measurements_2.npz"), "--robot", str(ROBOTS / "kuka_lwr4.yaml"), "--model", "id.json",
                  "--mjcf", "checked.xml", "--urdf", "checked.urdf", cwd=out)
    assert done.returncode == 0, done.stderr
    assert "the model holds" in done.stdout
    assert done.stdout.splitlines()[-1].startswith("kuka_lwr4: the model of id.json: URDF written to checked.urdf; MJCF written to checked.xml")
    assert (out / "checked.xml").read_text() == (out / "kuka.xml").read_text()
    assert (out / "checked.urdf").read_text() == (out / "kuka.urdf").read_text()


def test_check_writes_the_load_it_finds(tmp_path: Path) -> None:
    """An undeclared 1 kg tool (tests/checkgen.py, which shares no code with armid): ``armid
    check --mjcf`` writes the model with the load it names on the last link. Reference: Pinocchio's
    RNEA on the identification's URDF with the named load appended to that link's frame by
    Pinocchio (mass, centre and inertia as the check's JSON gives them)."""
    from checkgen import make_check_case

    case = make_check_case(0, "dh6", tmp_path / "case", masses=(1.0,))
    done = _armid("identify", str(case.ident), "--robot", str(case.robot), "--feasible", "--json", "model.json", "--urdf", "model.urdf",
                  cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    done = _armid("check", str(case.checks[1.0]), "--robot", str(case.robot), "--model", "model.json", "--json", "check.json",
                  "--mjcf", "tool.xml", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    load = next(f for f in json.loads((tmp_path / "check.json").read_text())["found"] if f["effect"] == "payload")["parameters"]
    assert abs(load["m"] - 1.0) < 0.05
    assert f"with the load of {load['m']:.3f} kg found on link 6" in done.stdout.splitlines()[-1]
    robot = load_robot(case.robot)
    model = pin.buildModelFromUrdf(str(tmp_path / "model.urdf"))
    model.gravity = pin.Motion(np.asarray(robot.gravity, float), np.zeros(3))
    link = model.frames[model.getFrameId("link6")]
    inertia = np.array([[load["Ixx"], load["Ixy"], load["Ixz"]], [load["Ixy"], load["Iyy"], load["Iyz"]],
                        [load["Ixz"], load["Iyz"], load["Izz"]]])
    model.appendBodyToJoint(link.parentJoint, pin.Inertia(load["m"], np.array([load["cx"], load["cy"], load["cz"]]), inertia),
                            link.placement)
    worst = _max_difference(_rigid(tmp_path / "tool.xml"), model, seed=7)
    print(f"check with a 1 kg tool: max |diff| {worst:.3g} N*m")
    assert worst < 1e-6


def test_check_without_the_feasible_parameters_is_one_line(kuka: tuple[Path, subprocess.CompletedProcess[str]]) -> None:
    out, _ = kuka
    doc = json.loads((out / "id.json").read_text())
    del doc["feasible"]
    (out / "plain.json").write_text(json.dumps(doc))
    done = _armid("check", str(KUKA / "measurements_2.npz"), "--robot", str(ROBOTS / "kuka_lwr4.yaml"), "--model", "plain.json",
                  "--mjcf", "plain.xml", cwd=out)
    assert done.returncode == 2 and len(done.stderr.splitlines()) == 1, done.stderr
    assert "plain.json" in done.stderr and "--feasible" in done.stderr and not (out / "plain.xml").exists()


def test_diagnose_writes_the_model_with_its_findings(kuka: tuple[Path, subprocess.CompletedProcess[str]]) -> None:
    """``armid diagnose --mjcf`` (the README tour, KUKA 1 -> 2): the final model's rigid body as
    its URDF's; the cogging it finds on joint 6 has no MuJoCo term and is named."""
    out, _ = kuka
    done = _armid("diagnose", str(KUKA / "measurements_1.npz"), "--robot", str(ROBOTS / "kuka_lwr4.yaml"), "--validate",
                  str(KUKA / "measurements_2.npz"), "--urdf", "diagnosed.urdf", "--mjcf", "diagnosed.xml", cwd=out)
    assert done.returncode == 0, done.stderr
    assert "residual is periodic in position: cogging" in done.stdout
    assert done.stdout.splitlines()[-1].endswith("MJCF written to diagnosed.xml (no MuJoCo term, left out: torque offset on joints "
                                                 "1, 2, 3, 4, 5, 6, 7; cogging on joint 6)")
    robot = load_robot(ROBOTS / "kuka_lwr4.yaml")
    model = pin.buildModelFromUrdf(str(out / "diagnosed.urdf"))
    model.gravity = pin.Motion(np.asarray(robot.gravity, float), np.zeros(3))
    worst = _max_difference(_rigid(out / "diagnosed.xml"), model, seed=65)
    print(f"KUKA LWR4+ diagnosed: max |diff| {worst:.3g} N*m")
    assert worst < 1e-6


def test_puma_dh_mjcf_with_rotor_inertia(tmp_path: Path) -> None:
    """Standard DH (the PUMA 560, link frames off the joint axes) through the command line: the
    rigid body equals Pinocchio's RNEA on the DH URDF; rotor inertia is armature and viscous
    friction damping, each the same term as armid's ``ia qdd`` and ``fv qd``."""
    done = _armid("identify", str(ROOT / "examples" / "puma560_excitation.csv"), "--robot", str(ROBOTS / "puma560.yaml"),
                  "--json", "id.json", "--urdf", "puma.urdf", "--mjcf", "puma.xml", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "MJCF written to puma.xml" in done.stdout and "left out" not in done.stdout
    robot = load_robot(ROBOTS / "puma560.yaml")
    model = pin.buildModelFromUrdf(str(tmp_path / "puma.urdf"))
    model.gravity = pin.Motion(np.asarray(robot.gravity, float), np.zeros(3))
    m = _rigid(tmp_path / "puma.xml")
    worst = _max_difference(m, model, seed=560)
    print(f"PUMA 560 (DH): max |diff| {worst:.3g} N*m")
    assert worst < 1e-6
    values = _feasible_effects(json.loads((tmp_path / "id.json").read_text()))
    ia = np.array([values[("rotor_inertia", j)] for j in range(1, 7)])
    fv = np.array([values[("viscous_friction", j)] for j in range(1, 7)])
    full = mujoco.MjModel.from_xml_path(str(tmp_path / "puma.xml"))
    assert np.all(full.dof_armature > 0) and np.all(full.dof_damping > 0) and np.all(full.dof_frictionloss > 0)
    full.dof_frictionloss[:] = 0.0
    data = model.createData()
    for q, qd, qdd in _states(full, seed=6)[:20]:
        assert np.allclose(_inverse(full, q, qd, qdd), pin.rnea(model, data, q, qd, qdd) + ia * qdd + fv * qd, rtol=0, atol=1e-9)


def test_scara_mdh_prismatic_and_what_mujoco_lacks(tmp_path: Path) -> None:
    """Modified DH with a prismatic quill (scara_mdh), written from its modeled values with
    effects of every kind: the slide joint, MuJoCo's inverse dynamics against Pinocchio's RNEA
    on the chain built from the robot (no URDF read), the spring as stiffness, and the effects
    MuJoCo has no term for named in the file and in the return."""
    robot = load_robot(ROBOTS / "scara_mdh.yaml")
    effects = [linear_effect("viscous_friction", 2), linear_effect("coulomb_friction", 2, velocity=0.01),
               linear_effect("rotor_inertia", 0), linear_effect("spring", 1), linear_effect("torque_offset", 3),
               linear_effect("stribeck_friction", 2, velocity=0.05), linear_effect("cogging", 0, period_rad=0.5)]
    values = [40.0, 12.0, 0.3, 7.5, 0.2, 3.0, 0.1, 0.05]
    phi = np.concatenate([robot.modeled_parameters(), values])
    path, left_out = write_mjcf(tmp_path / "scara.xml", robot, phi, effects)
    assert left_out == ["torque offset on joint 4", "stribeck friction on joint 3", "cogging on joint 1"]
    text = path.read_text()
    assert "left out: torque offset on joint 4; stribeck friction on joint 3; cogging on joint 1." in text
    assert "fc tanh(qd / v) on joints (v, rad/s or m/s) 3 (0.01)" in text
    full = mujoco.MjModel.from_xml_path(str(path))
    assert list(full.jnt_type) == [mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE,
                                   mujoco.mjtJoint.mjJNT_HINGE]
    assert full.dof_damping[2] == 40.0 and full.dof_frictionloss[2] == 12.0 and full.dof_armature[0] == 0.3
    assert full.jnt_stiffness[1] == 7.5 and full.nu == 4 and np.allclose(full.actuator_ctrlrange[2], [-300.0, 300.0])
    model = to_pinocchio(robot, robot.modeled_parameters())
    worst = _max_difference(_rigid(path), model, seed=3)
    print(f"SCARA (MDH, prismatic): max |diff| {worst:.3g}")
    assert worst < 1e-6
    # the spring is MuJoCo's stiffness: the inverse dynamics gain ks * q on its joint
    m = _rigid(path)
    q, qd, qdd = _states(m, seed=4)[0]
    rigid = _inverse(m, q, qd, qdd)
    m.jnt_stiffness[1] = 7.5
    assert np.allclose(_inverse(m, q, qd, qdd) - rigid, [0.0, 7.5 * q[1], 0.0, 0.0], rtol=0, atol=1e-12)


def test_a_body_mujoco_refuses_is_one_error_and_no_file(tmp_path: Path) -> None:
    robot = load_robot(ROBOTS / "scara_mdh.yaml")
    phi = robot.modeled_parameters()
    phi[30:40] = 0.0  # the last link without mass or inertia: MuJoCo does not simulate it
    with pytest.raises(IdentificationError, match="MuJoCo does not load the identified model"):
        write_mjcf(tmp_path / "bad.xml", robot, phi)
    assert not (tmp_path / "bad.xml").exists()


@pytest.mark.parametrize("command, argv", [
    ("identify", ["data.csv", "--robot", str(ROBOTS / "puma560.yaml")]),
    ("diagnose", ["data.csv", "--robot", str(ROBOTS / "puma560.yaml"), "--validate", "data.csv"]),
    ("check", ["data.csv", "--robot", str(ROBOTS / "puma560.yaml"), "--model", "id.json"]),
])
@pytest.mark.parametrize("out, said", [("a_file/puma.xml", "a_file: Not a directory"), (".", ".: Is a directory")])
def test_mjcf_to_an_unwritable_path_is_one_line(tmp_path: Path, command: str, argv: list[str], out: str, said: str) -> None:
    """Refused before any work: the data named here do not even exist."""
    (tmp_path / "a_file").write_text("")
    done = _armid(command, *argv, "--mjcf", out, cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines() == [f"armid {command}: error: {said}"]


def test_mjcf_to_a_path_that_fails_on_writing_is_one_line(tmp_path: Path) -> None:
    """A folder no file can be made in though its permissions allow it (``/proc``, for root): refused
    by the check or by the write itself, in one line either way."""
    done = _armid("identify", str(ROOT / "examples" / "puma560_excitation.csv"), "--robot", str(ROBOTS / "puma560.yaml"),
                  "--mjcf", "/proc/armid/puma.xml", cwd=tmp_path)
    assert done.returncode == 2, done.stderr
    assert len(done.stderr.splitlines()) == 1 and "/proc/armid" in done.stderr and "Traceback" not in done.stderr, done.stderr


@pytest.mark.parametrize("seed", range(5))
def test_quaternion_is_mujocos(seed: int) -> None:
    """The body orientation: MuJoCo's own conversion of the same matrix."""
    rng = np.random.default_rng(seed)
    r, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    r *= np.sign(np.linalg.det(r))
    expected = np.zeros(4)
    mujoco.mju_mat2Quat(expected, r.flatten())
    assert np.allclose(quaternion(r), expected * np.sign(expected[0]), atol=1e-12)

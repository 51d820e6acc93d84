"""rosbag2 bags in (issue 64): a bag identifies as the CSV/NPZ of the same data does.

The bags are written by ``rosbags`` (:mod:`bagwriter`), in sqlite3 and MCAP storage, with the
joints in another order than the robot file's (reversed for the KUKA, alphabetical for the UR5,
as UR's driver publishes them): equality to the CSV proves they are matched by name. The UR5's
effort is motor current (its robot file says ``effort: current``): its torques come from
Pinocchio's RNEA on the URDF with viscous and Coulomb friction, divided by each joint's torque
constant, so that nothing of armid made them. Bad bags are in ``test_fuzz.py``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from bagwriter import Message, arm_messages, storage_file, write_bag

from armid.cli import main
from armid.io.recordings import read_recording, recording_kind
from armid.io.robot_file import load_robot

ROOT = Path(__file__).resolve().parent.parent
ROBOTS = ROOT / "config" / "robots"
KUKA = next((p / "shared" / "data" / "kuka_lwr4" for p in ROOT.parents if (p / "shared" / "data" / "kuka_lwr4").is_dir()), None)
needs_kuka = pytest.mark.skipif(KUKA is None, reason="the shared KUKA LWR4+ recordings are not beside the repository")
KUKA_JOINTS = [f"lwr_{j}_joint" for j in range(7)]
UR5_JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]
STORAGES = ("sqlite3", "mcap")


def seconds(t_ns: np.ndarray) -> np.ndarray:
    """A ROS 2 stamp in seconds (``sec + 1e-9 * nanosec``): the times a bag holds."""
    t_ns = np.asarray(t_ns, np.int64)
    return (t_ns // 10**9).astype(float) + 1e-9 * (t_ns % 10**9).astype(float)


def write_csv(path: Path, t: np.ndarray, columns: dict[str, np.ndarray]) -> Path:
    """A CSV written here (not by armid), every value as the shortest text that reads back exactly."""
    header = ["t"] + [f"{p}{j + 1}" for p, a in columns.items() for j in range(a.shape[1])]
    rows = np.column_stack([t, *columns.values()])
    path.write_text(",".join(header) + "\n" + "".join(",".join(repr(float(v)) for v in row) + "\n" for row in rows))
    return path


def kuka_data() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    assert KUKA is not None
    with np.load(KUKA / "measurements_1.npz") as a:
        t_ns = np.round(a["times"] * 1e9).astype(np.int64)
        return t_ns, a["positions"], a["velocities"], a["torques"]


@pytest.fixture(scope="module")
def kuka(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """measurements_1 as a bag of each storage (joints reversed), and as a CSV and an NPZ of the
    same numbers (the stamps as the bag holds them, no accelerations: a JointState has none)."""
    folder = tmp_path_factory.mktemp("kuka")
    t_ns, q, qd, tau = kuka_data()
    messages = arm_messages(t_ns, KUKA_JOINTS, q, qd, tau, order=list(range(7))[::-1])
    out = {s: write_bag(folder / f"bag_{s}", s, messages) for s in STORAGES}
    out["csv"] = write_csv(folder / "m1.csv", seconds(t_ns), {"q": q, "qd": qd, "tau": tau})
    np.savez(folder / "m1.npz", times=seconds(t_ns), positions=q, velocities=qd, torques=tau)
    out["npz"] = folder / "m1.npz"
    return out


def identify_json(data: Path, robot: Path | str, out: Path, capsys: pytest.CaptureFixture[str], *extra: str) -> dict[str, Any]:
    code = main(["identify", str(data), "--robot", str(robot), "--json", str(out), *extra])
    err = capsys.readouterr().err
    assert code == 0, err
    return json.loads(out.read_text())


def parameter_difference(a: dict[str, Any], b: dict[str, Any]) -> float:
    """Largest absolute difference of the two identifications' base parameters (value and std)
    and fit error; their expressions must be the same."""
    assert [x["expression"] for x in a["base_parameters"]] == [x["expression"] for x in b["base_parameters"]]
    pairs = [(x[k], y[k]) for x, y in zip(a["base_parameters"], b["base_parameters"]) for k in ("value", "std")]
    pairs.append((a["fit"]["relative_error"], b["fit"]["relative_error"]))
    return max(abs(float(x) - float(y)) for x, y in pairs)


@needs_kuka
@pytest.mark.parametrize("storage", STORAGES)
def test_a_kuka_bag_reads_as_its_csv(storage: str, kuka: dict[str, Path]) -> None:
    """The folder and its storage file alone read to the very arrays of the CSV, joints by name."""
    robot = load_robot(ROBOTS / "kuka_lwr4.yaml")
    csv = read_recording(kuka["csv"], robot)
    for path in (kuka[storage], storage_file(kuka[storage])):
        assert recording_kind(path) == "bag"
        rec = read_recording(path, robot)
        for name in ("t", "q", "qd", "tau"):
            assert np.array_equal(getattr(rec, name), getattr(csv, name)), name
        assert rec.torque_from_current is False and not rec.torque_held
        assert any("joints matched by name" in n for n in rec.notes)


@needs_kuka
@pytest.mark.slow
@pytest.mark.parametrize("storage", STORAGES)
def test_a_kuka_bag_identifies_as_its_csv_and_npz(storage: str, kuka: dict[str, Path], tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """What must hold: ``armid identify BAG_DIR`` gives the CSV's and the NPZ's result to 1e-9."""
    robot = ROBOTS / "kuka_lwr4.yaml"
    bag = identify_json(kuka[storage], robot, tmp_path / "bag.json", capsys)
    diff = {other: parameter_difference(bag, identify_json(kuka[other], robot, tmp_path / f"{other}.json", capsys)) for other in ("csv", "npz")}
    with capsys.disabled():
        print(f"kuka {storage} bag: max abs difference against the csv {diff['csv']:.3g}, against the npz {diff['npz']:.3g}")
    assert max(diff.values()) <= 1e-9


# -- a UR5 whose driver publishes motor current ---------------------------------------------

def ur5_current_case(folder: Path, seed: int = 0, rate_hz: float = 250.0, duration_s: float = 20.0) -> dict[str, Any]:
    """A simulated UR5 run: a 5-harmonic Fourier trajectory, torque by Pinocchio's RNEA on the
    URDF plus viscous and Coulomb friction, current = torque / torque constant plus noise;
    a robot file that says ``effort: current``."""
    import pinocchio as pin
    import yaml

    rng = np.random.default_rng(seed)
    doc = yaml.safe_load((ROBOTS / "ur5.yaml").read_text())
    kt = np.array([j["torque_constant"] for j in doc["joints"]])
    doc["urdf"] = str(ROBOTS / doc["urdf"])
    doc["effort"] = "current"
    robot = folder / "ur5_current.yaml"
    robot.write_text(yaml.safe_dump(doc))
    model = pin.buildModelFromUrdf(str(ROBOTS / "ur5.urdf"))
    data = model.createData()
    assert [model.names[i] for i in range(1, model.njoints)] == UR5_JOINTS
    n, w = 6, 2 * np.pi * 0.1
    t_ns = 1_700_000_000 * 10**9 + np.round(np.arange(int(duration_s * rate_hz)) * 1e9 / rate_hz).astype(np.int64)
    t = (t_ns - t_ns[0]) * 1e-9
    harmonics = np.arange(1, 6)
    a, b = rng.uniform(-1, 1, (2, n, 5)) * 0.35 / harmonics
    q0 = np.array([0.0, -1.2, 1.2, -1.5, -1.5, 0.0])
    ang = w * np.outer(t, harmonics)  # (samples, harmonics)
    q = q0 + (np.sin(ang) @ a.T) / w - (np.cos(ang) @ b.T) / w
    qd = np.cos(ang) @ a.T + np.sin(ang) @ b.T
    qdd = w * (-(np.sin(ang) * harmonics) @ a.T + (np.cos(ang) * harmonics) @ b.T)
    fv, fc = rng.uniform(2.0, 6.0, n), rng.uniform(1.0, 4.0, n)
    tau = np.array([pin.rnea(model, data, q[k], qd[k], qdd[k]) for k in range(t.size)]) + fv * qd + fc * np.sign(qd)
    current = tau / kt + rng.normal(0.0, 0.01, tau.shape)
    return {"robot": robot, "t_ns": t_ns, "q": q, "qd": qd, "current": current, "kt": kt}


@pytest.fixture(scope="module")
def ur5(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    folder = tmp_path_factory.mktemp("ur5")
    case = ur5_current_case(folder)
    alphabetical = sorted(range(6), key=lambda j: UR5_JOINTS[j])
    messages = arm_messages(case["t_ns"], UR5_JOINTS, case["q"], case["qd"], case["current"], alphabetical)
    case.update({s: write_bag(folder / f"bag_{s}", s, messages) for s in STORAGES})
    case["csv"] = write_csv(folder / "ur5.csv", seconds(case["t_ns"]), {"q": case["q"], "qd": case["qd"], "i": case["current"]})
    return case


def test_a_ur5_bag_of_currents_reads_as_its_csv_of_currents(ur5: dict[str, Any]) -> None:
    """Alphabetical joints matched by name; the current made a torque by the robot file's torque
    constants, as the CSV's current columns are; a robot file without ``effort: current`` reads
    the same numbers as torques."""
    robot = load_robot(ur5["robot"])
    assert robot.effort == "current"
    csv = read_recording(ur5["csv"], robot)
    for storage in STORAGES:
        rec = read_recording(ur5[storage], robot)
        for name in ("t", "q", "qd", "tau"):
            assert np.array_equal(getattr(rec, name), getattr(csv, name)), name
        assert np.array_equal(rec.tau, ur5["current"] * ur5["kt"])
        assert rec.torque_from_current is True
        assert any("effort read as motor current" in n for n in rec.notes)
    as_torque = read_recording(ur5["mcap"], load_robot(ROBOTS / "ur5.yaml"))
    assert np.array_equal(as_torque.tau, ur5["current"]) and as_torque.torque_from_current is False


@pytest.mark.slow
@pytest.mark.parametrize("storage", STORAGES)
def test_a_ur5_bag_of_currents_identifies_as_its_csv(storage: str, ur5: dict[str, Any], tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """What must hold: the UR5 bag with current as effort identifies as its CSV to 1e-9, and the
    fit is the arm's (a current not made a torque would leave most of the torque unexplained)."""
    bag = identify_json(ur5[storage], ur5["robot"], tmp_path / "bag.json", capsys)
    diff = parameter_difference(bag, identify_json(ur5["csv"], ur5["robot"], tmp_path / "csv.json", capsys))
    print(f"ur5 {storage} bag against csv: max abs difference {diff:.3g}, fit error {bag['fit']['relative_error']:.4g}")
    assert diff <= 1e-9
    assert bag["fit"]["relative_error"] < 0.05


# -- what reading repairs, and says ---------------------------------------------------------

def puma_messages(rows: int = 400) -> tuple[np.ndarray, list[Message]]:
    """The shipped PUMA 560 example's first rows as messages (joints reversed), 2 ms apart."""
    data = np.loadtxt(ROOT / "examples" / "puma560_excitation.csv", delimiter=",", skiprows=1, max_rows=rows)
    t_ns = 1_600_000_000 * 10**9 + np.arange(rows, dtype=np.int64) * 2_000_000
    return t_ns, arm_messages(t_ns, [f"j{j + 1}" for j in range(6)], data[:, 1:7], data[:, 7:13], data[:, 13:19], order=list(range(6))[::-1])


@pytest.mark.parametrize("storage", STORAGES)
def test_extra_joints_a_gripper_publisher_and_repeats_are_said_and_left_out(storage: str, tmp_path: Path) -> None:
    """A gripper joint in every message (ignored, named), a second publisher of the gripper alone
    interleaved (left out, counted), a message repeated (kept once): the arm's arrays as in a
    clean bag, and each repair said."""
    robot = load_robot(ROBOTS / "puma560.yaml")
    _, clean = puma_messages()
    messy: list[Message] = []
    for k, m in enumerate(clean):
        messy.append(Message(m.stamp_ns, [*m.names, "gripper_joint"], [*m.position, 0.01], [*m.velocity, 0.0], [*m.effort, 0.5]))
        if k % 3 == 0:
            messy.append(Message(m.stamp_ns + 1000, ["finger_joint"], [0.02], [0.0], [1.0]))
        if k == 100:
            messy.append(messy[-2] if k % 3 == 0 else messy[-1])
    ref = read_recording(write_bag(tmp_path / "clean", storage, clean), robot)
    rec = read_recording(write_bag(tmp_path / "messy", storage, messy), robot)
    for name in ("t", "q", "qd", "tau"):
        assert np.array_equal(getattr(rec, name), getattr(ref, name)), name
    said = "\n".join(rec.notes)
    assert "gripper_joint on /joint_states are not in puma560's robot file: ignored" in said
    assert "134 message(s) of another publisher on /joint_states left out (joints finger_joint)" in said
    assert "1 message(s) repeated with their stamp and values: kept once" in said


def test_zero_header_stamps_fall_back_to_the_receive_time_and_say_so(tmp_path: Path) -> None:
    robot = load_robot(ROBOTS / "puma560.yaml")
    t_ns, messages = puma_messages()
    for m in messages:
        m.received_ns, m.stamp_ns = m.stamp_ns + 1500, 0
    rec = read_recording(write_bag(tmp_path / "bag", "mcap", messages), robot)
    assert np.array_equal(rec.t, seconds(t_ns + 1500))
    assert any("every header stamp on /joint_states is zero: timed by the bag's receive time" in n for n in rec.notes)


def test_header_stamps_not_receive_times_give_the_time(tmp_path: Path) -> None:
    """A bag received 3 ms late with jitter: the times are the header stamps."""
    robot = load_robot(ROBOTS / "puma560.yaml")
    t_ns, messages = puma_messages()
    jitter = np.random.default_rng(1).integers(0, 1_000_000, len(messages))
    for m, j in zip(messages, jitter):
        m.received_ns = m.stamp_ns + 3_000_000 + int(j)
    rec = read_recording(write_bag(tmp_path / "bag", "sqlite3", messages), robot)
    assert np.array_equal(rec.t, seconds(t_ns))


def test_another_topic_is_read_with_topic(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    robot = load_robot(ROBOTS / "puma560.yaml")
    _, messages = puma_messages()
    for m in messages:
        m.topic = "/arm/joint_states"
    bag = write_bag(tmp_path / "bag", "mcap", messages)
    assert read_recording(bag, robot, "/arm/joint_states").n_samples == len(messages)
    code = main(["identify", str(bag), "--robot", "puma560", "--topic", "/joint_states"])
    err = capsys.readouterr().err
    assert code == 2 and "topic /joint_states: not in the bag (it holds /arm/joint_states (sensor_msgs/msg/JointState)" in err


def test_armid_s_own_mcap_and_a_bag_s_mcap_take_their_own_readers(tmp_path: Path) -> None:
    from test_fuzz import write_mcap

    from armid.schema import Sample
    from armid.schema.joint_state import JointStateRecord

    q = np.linspace(0, 1, 60)[:, None] * np.ones(6)
    own = write_mcap(tmp_path / "own.mcap", [JointStateRecord(k, Sample(k, 0.002 * k, np.ones(6, bool), q[k], np.ones(6), np.ones(6, bool),
                                                                         np.ones(6), np.ones(6), np.full(6, 0x27), np.ones(6)))
                                             for k in range(60)])
    assert read_recording(own, load_robot(ROBOTS / "puma560.yaml")).n_samples == 60
    _, messages = puma_messages()
    bag = write_bag(tmp_path / "bag", "mcap", messages)
    assert recording_kind(own) == "mcap"
    assert recording_kind(storage_file(bag)) == "bag" and recording_kind(bag) == "bag"
    assert recording_kind(tmp_path / "x.csv") == "csv" and recording_kind(tmp_path / "x.npz") == "npz"


def test_a_fleet_finds_a_bag_folder_as_one_recording(tmp_path: Path) -> None:
    from armid.fleet.discover import find_arms

    arm = tmp_path / "root" / "puma"
    arm.mkdir(parents=True)
    (arm / "robot.yaml").write_text((ROBOTS / "puma560.yaml").read_text())
    _, messages = puma_messages()
    write_bag(arm / "day1", "sqlite3", messages)
    write_bag(arm / "day2", "mcap", messages)
    single = write_bag(tmp_path / "single", "sqlite3", messages)
    storage_file(single).rename(arm / "day3.db3")
    arms, _ = find_arms(tmp_path / "root")
    assert arms[0].recordings == ("puma/day1", "puma/day2", "puma/day3.db3")


@needs_kuka
@pytest.mark.slow
def test_estimate_replays_a_bag_as_its_csv(kuka: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    robot = str(ROBOTS / "kuka_lwr4.yaml")
    identify_json(kuka["csv"], robot, tmp_path / "ident.json", capsys)
    out = {}
    for name in ("csv", "mcap"):
        code = main(["estimate", "--robot", robot, "--params", str(tmp_path / "ident.json"), "--replay", str(kuka[name]),
                     "--out", str(tmp_path / f"{name}.jsonl")])
        assert code == 0, capsys.readouterr().err
        out[name] = (tmp_path / f"{name}.jsonl").read_text()
    assert out["csv"] and out["csv"] == out["mcap"]


def test_a_velocity_nan_throughout_is_left_for_the_positions_and_said(tmp_path: Path) -> None:
    """Some drivers publish NaN for a velocity they do not measure: velocity from the positions."""
    robot = load_robot(ROBOTS / "puma560.yaml")
    _, messages = puma_messages()
    for m in messages:
        m.velocity = np.where(np.arange(6) == 2, np.nan, m.velocity)
    rec = read_recording(write_bag(tmp_path / "bag", "mcap", messages), robot)
    assert rec.qd is None
    assert any("velocity is NaN in every message for joint(s) j4: velocity from the positions throughout" in n for n in rec.notes)


@pytest.mark.parametrize("storage", STORAGES)
@pytest.mark.parametrize("compression", ["file", "message"])
def test_a_compressed_bag_reads_as_its_plain_twin(storage: str, compression: str, tmp_path: Path) -> None:
    """zstd by file (``.db3.zstd``, ``.mcap.zstd``) or by message: read through the bag's folder."""
    robot = load_robot(ROBOTS / "puma560.yaml")
    _, messages = puma_messages()
    plain = read_recording(write_bag(tmp_path / "plain", storage, messages), robot)
    rec = read_recording(write_bag(tmp_path / "zstd", storage, messages, compression), robot)
    for name in ("t", "q", "qd", "tau"):
        assert np.array_equal(getattr(rec, name), getattr(plain, name)), name

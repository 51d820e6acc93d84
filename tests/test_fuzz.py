"""Bad input never crashes and never passes silently (issue 18).

Every case is made from a shipped example (the PUMA 560 recording, its robot description,
the simulated rig, a Fourier trajectory for it) by breaking one thing, and run through
``armid.cli.main`` in this process. Each must exit 2 with exactly one ``error:`` line, the
last line on stderr, naming what is wrong, and no traceback. A few run end to end in a
subprocess. Each group also runs its unbroken original, so that a case fails for its one
change and not for something else.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from cli_runs import run

from armid.cli import load_trajectory, strict_json
from armid.io.ros2_cdr import ros2_messages
from armid.schema import Sample
from armid.schema.joint_state import EXTRA_TOPIC, EXTRA_TYPE, JOINT_STATE_TYPE, JOINT_STATES_TOPIC, ROS2_MSGDEFS, JointStateRecord

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "puma560_excitation.csv"
PUMA = ROOT / "config" / "robots" / "puma560.yaml"
PUBLISHED_LINK3_INERTIA = [0.066, 0.0, 0.0, 0.086, 0.0, 0.0125]  # Armstrong et al. (1986): 0.066 + 0.0125 < 0.086
UR5 = ROOT / "config" / "robots" / "ur5.yaml"
RIG = ROOT / "config" / "rigs" / "sim.yaml"
LAB = ROOT / "config" / "zenoh" / "lab.json5"
ROWS = 600  # of the example: enough for every check, quick to read

HEADER = EXAMPLE.read_text().splitlines()[0].split(",")
DATA = np.loadtxt(EXAMPLE, delimiter=",", skiprows=1, max_rows=ROWS)
T, Q, QD, TAU = DATA[:, 0], DATA[:, 1:7], DATA[:, 7:13], DATA[:, 13:19]
KT = np.array([j["torque_constant"] for j in yaml.safe_load(PUMA.read_text())["joints"]])
RIG_DOC = yaml.safe_load(RIG.read_text())
Q0 = RIG_DOC["simulation"]["initial_position"]
TRAJECTORY = {"fourier": {"q0": Q0, "a": [[0.05, 0.02]] * 6, "b": [[0.0, 0.01]] * 6, "base_frequency_hz": 0.2}}


def assert_clean_error(code: int, err: str, expect: str) -> None:
    """Exit 2, stderr one ``error:`` line matching ``expect`` and nothing else, no traceback."""
    assert "Traceback" not in err, err
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert code == 2, f"exit {code}, stderr:\n{err}"
    assert len(lines) == 1 and ": error: " in lines[0], err
    assert re.search(expect, lines[0]), f"{lines[0]!r} does not say {expect!r}"


# -- recordings --------------------------------------------------------------------------

def _csv(path: Path, header: list[str], rows: Any) -> Path:
    lines = [",".join(header)] + [",".join(f"{v:.10g}" if isinstance(v, float) else str(v) for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def _recording(path: Path, t: Any = None, q: Any = None, qd: Any = None, tau: Any = None) -> Path:
    cols = [T if t is None else t, Q if q is None else q, QD if qd is None else qd, TAU if tau is None else tau]
    data = np.column_stack([np.asarray(c, float).reshape(ROWS, -1) for c in cols])
    return _csv(path, HEADER, data.tolist())


def _drop_column(path: Path, name: str) -> Path:
    keep = [k for k, h in enumerate(HEADER) if h != name]
    return _csv(path, [HEADER[k] for k in keep], DATA[:, keep].tolist())


def _npz(path: Path, **arrays: Any) -> Path:
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    return path


CSV_CASES: dict[str, tuple[Callable[[Path], Path], str]] = {
    "time in milliseconds": (lambda p: _recording(p, t=T * 1e3), r"column t: .*milliseconds"),
    "time in microseconds": (lambda p: _recording(p, t=T * 1e6), r"column t: .*microseconds"),
    "time in nanoseconds": (lambda p: _recording(p, t=T * 1e9), r"column t: .*nanoseconds"),
    "all-zero torque": (lambda p: _recording(p, tau=np.zeros_like(TAU)), r"tau1\.\.tau6: every torque is zero"),
    "constant torque": (lambda p: _recording(p, tau=np.full_like(TAU, 3.0)), r"torque is constant on every joint"),
    "positions in degrees": (lambda p: _recording(p, q=np.degrees(Q)), r"columns q, qd: the positions q look like degrees"),
    "velocities in degrees/s": (lambda p: _recording(p, qd=np.degrees(QD)), r"columns q, qd: the velocities qd look like degrees/s"),
    "positions in degrees, no velocity": (lambda p: _csv(p, HEADER[:7] + HEADER[13:], np.column_stack([T, np.degrees(Q), TAU]).tolist()),
                                          r"column q\d: the positions look like degrees.*against its limits"),
    "one moving joint's torque dead": (lambda p: _recording(p, tau=np.column_stack([TAU[:, :5], np.zeros(ROWS)])),
                                       r"column tau6: the torque is constant \(0\) while joint 6 moves"),
    "time reversed": (lambda p: _recording(p, t=T[::-1]), r"column t: time runs backwards"),
    "time frozen": (lambda p: _recording(p, t=np.zeros(ROWS)), r"column t: time never advances"),
    "no joint moves": (lambda p: _recording(p, q=np.tile(Q[0], (ROWS, 1)), qd=np.zeros_like(QD)), r"no joint moves.*not excited"),
    "empty file": (lambda p: (p.write_text(""), p)[1], r"empty file"),
    "header only": (lambda p: (p.write_text(",".join(HEADER) + "\n"), p)[1], r"no data rows"),
    "no time column": (lambda p: _csv(p, ["time"] + HEADER[1:], DATA.tolist()), r"line 1: no time column 't'"),
    "a position column missing": (lambda p: _drop_column(p, "q3"), r"line 1: column\(s\) q3 missing"),
    "no torque columns": (lambda p: _csv(p, HEADER[:13], DATA[:, :13].tolist()), r"neither torque columns"),
    "duplicate column": (lambda p: _csv(p, HEADER[:-1] + ["tau5"], DATA.tolist()), r"duplicate column\(s\) tau5"),
    "a seventh joint": (lambda p: _csv(p, HEADER + ["q7"], np.column_stack([DATA, DATA[:, 1]]).tolist()), r"column q7 but puma560 has 6"),
    "binary garbage": (lambda p: (p.write_bytes(bytes(range(256)) * 40), p)[1], r"not a text CSV"),
    "torque in mN*m": (lambda p: _recording(p, tau=TAU * 1e3), r"usable rows of .*torque beyond 5x .*is the torque in N\*m"),
    "every cell garbage": (lambda p: _csv(p, HEADER, [["x"] * len(HEADER)] * ROWS), r"usable rows"),
    "every row short": (lambda p: _csv(p, HEADER, DATA[:, :-2].tolist()), r"usable rows"),
    "infinite torque": (lambda p: _recording(p, tau=np.full_like(TAU, np.inf)), r"usable rows"),
    "no such file": (lambda p: p.with_name("missing.csv"), r"missing\.csv: no such file"),
    "npz not an archive": (lambda p: (p.with_suffix(".npz").write_bytes(b"PK\x03\x04 not a zip"), p.with_suffix(".npz"))[1],
                           r"not a readable \.npz"),
    "npz without torques": (lambda p: _npz(p.with_suffix(".npz"), times=T, positions=Q), r"archive has no 'torques'"),
    "npz wrong shape": (lambda p: _npz(p.with_suffix(".npz"), times=T, positions=Q[:, :5], torques=TAU), r"'positions' has shape"),
    "npz of Python objects": (lambda p: _npz(p.with_suffix(".npz"), times=np.array([object()] * ROWS, dtype=object), positions=Q,
                                             torques=TAU), r"'times' is not an array of numbers"),
    "npz time in milliseconds": (lambda p: _npz(p.with_suffix(".npz"), times=T * 1e3, positions=Q, velocities=QD, torques=TAU),
                                 r"milliseconds"),
}


@pytest.mark.parametrize("command", ["identify", "diagnose"])
@pytest.mark.parametrize("case", list(CSV_CASES))
def test_bad_recording(case: str, command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    make, expect = CSV_CASES[case]
    bad = make(tmp_path / "bad.csv")
    good = _recording(tmp_path / "good.csv")
    argv = [command, str(bad), "--robot", str(PUMA), "--validate", str(good)]
    assert_clean_error(*run(argv, capsys), expect)


def test_positions_beyond_the_limits_are_warned_about(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Joint 2 counted from a zero a turn away: beyond its limits all the time, but not degrees."""
    q = Q - np.array([0, 2 * np.pi, 0, 0, 0, 0])
    code, err = run(["identify", str(_recording(tmp_path / "offset.csv", q=q)), "--robot", str(PUMA), "--lowpass", "off"], capsys)
    assert code == 0 and re.search(r"offset\.csv: column q2: joint 2 is beyond its limits .* the controller's zero", err), err


def test_bad_validation_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    good = _recording(tmp_path / "good.csv")
    bad = _recording(tmp_path / "ms.csv", t=T * 1e3)
    assert_clean_error(*run(["identify", str(good), "--robot", str(PUMA), "--validate", str(bad)], capsys), r"ms\.csv: .*milliseconds")


def test_the_unbroken_recording_identifies(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "ident.json"
    argv = ["identify", str(_recording(tmp_path / "good.csv")), "--robot", str(PUMA), "--json", str(out), "--lowpass", "off"]
    code, err = run(argv, capsys)
    assert code == 0 and "Traceback" not in err and ": error: " not in err and "modeled torque" not in err, err
    json.loads(out.read_text(), parse_constant=_refuse_constant)
    # the shipped PUMA 560 is a rigid body (its robot file says which published values it changed)
    assert "inertial" not in err and "rigid body" not in err, err
    # the published values of link 3 break the triangle inequality: said once, on one line
    published = _robot(tmp_path / "published.yaml", _joint(2, "inertial.inertia", PUBLISHED_LINK3_INERTIA))
    code, err = run([*argv[:3], str(published), *argv[4:]], capsys)
    said = [line for line in err.splitlines() if "joints[2].inertial.inertia: principal moments" in line]
    assert code == 0 and len(said) == 1 and said[0].startswith("armid identify: warning: ") and "triangle inequality" in said[0], err


# -- MCAP --------------------------------------------------------------------------------

def _records(change: Callable[[list[JointStateRecord]], None] | None = None) -> list[JointStateRecord]:
    """The example's rows as ``armid record`` acquires them (the driver's torque, its currents)."""
    out = []
    for k in range(ROWS):
        current = TAU[k] / KT
        out.append(JointStateRecord(k, Sample(k, float(T[k]), np.ones(6, bool), Q[k].copy(), QD[k].copy(), np.ones(6, bool), current,
                                              current.copy(), np.full(6, 0x27), TAU[k].copy())))
    if change is not None:
        change(out)
    return out


def write_mcap(path: Path, records: list[JointStateRecord], metadata: dict[str, str] | None = None,
               replace: dict[tuple[str, int], bytes] | None = None) -> Path:
    """A ROS 2 recording as ``daq.recorder`` lays it out (its two CDR channels, summary, footer),
    in uncompressed 32 KiB chunks so that a case can break bytes in them; ``replace``: the bytes
    of (topic, sequence)'s message instead of the record's."""
    from mcap.writer import CompressionType, Writer

    names = [f"j{j + 1}" for j in range(records[0].sample.position.size)]
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=32 * 1024, compression=CompressionType.NONE)
        w.start(profile="ros2", library="armid-test")
        channels = {topic: w.register_channel(topic, "cdr", w.register_schema(kind, "ros2msg", ROS2_MSGDEFS[kind].encode()))
                    for topic, kind in ((JOINT_STATES_TOPIC, JOINT_STATE_TYPE), (EXTRA_TOPIC, EXTRA_TYPE))}
        w.add_metadata("armid.run", {"robot": "puma560"} if metadata is None else metadata)
        for r in records:
            ns = int(round(r.sample.time_s * 1e9))
            for topic, data in zip(channels, ros2_messages(r, names)):
                w.add_message(channels[topic], ns, (replace or {}).get((topic, r.sequence), data), ns, r.sequence)
        w.finish()
    return path


def _mcap_with(path: Path, change: Callable[[list[JointStateRecord]], None], metadata: dict[str, str] | None = None) -> Path:
    return write_mcap(path, _records(change), metadata)


def _set(k: int, field: str, value: Any) -> Callable[[list[JointStateRecord]], None]:
    def change(records: list[JointStateRecord]) -> None:
        setattr(records[k].sample, field, value)
    return change


def _seven_joints(records: list[JointStateRecord]) -> None:
    for r in records:
        for field in ("valid", "position", "velocity", "velocity_fresh", "commanded_current", "measured_current", "status", "torque"):
            v = getattr(r.sample, field)
            setattr(r.sample, field, np.concatenate([v, v[:1]]))


def _stamped_two_seconds_apart(records: list[JointStateRecord]) -> None:
    for r in records:
        r.sample.time_s = 2.0 * r.sequence  # the example's 2 ms cycles stamped as if milliseconds were seconds


def _zero_torque(records: list[JointStateRecord]) -> None:
    for r in records:
        r.sample.torque = np.zeros(6)


_DELETE = object()


def _every_chunk_flipped(path: Path) -> Path:
    from mcap.reader import make_reader

    write_mcap(path, _records())
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    data = bytearray(path.read_bytes())
    for chunk in summary.chunk_indexes:
        pos = chunk.chunk_start_offset + chunk.chunk_length // 2
        data[pos : pos + 4] = bytes(b ^ 0xFF for b in data[pos : pos + 4])
    path.write_bytes(bytes(data))
    return path


def _json_layout(path: Path) -> Path:
    """A file in the layout armid wrote before its ROS 2 recordings: one JSON message a cycle on ``/joint_state``."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="armid")
        channel = w.register_channel("/joint_state", "json", w.register_schema("armid.JointState", "jsonschema", b"{}"))
        for k in range(10):
            w.add_message(channel, 2_000_000 * k, json.dumps({"sequence": k, "position": Q[k].tolist()}).encode(), 2_000_000 * k, k)
        w.finish()
    return path


MCAP_CASES: dict[str, tuple[Callable[[Path], Path], str]] = {
    "position too short": (lambda p: _mcap_with(p, _set(200, "position", Q[200][:5])),
                           r"/joint_states \(sequence 200\): 'position' has 5 values, the recording's other messages 6"),
    "statusword too long": (lambda p: _mcap_with(p, _set(5, "status", np.full(7, 0x27))),
                            r"/armid/joint_state_extra \(sequence 5\): 'statusword' has 7 values, .* 6"),
    "message not its type": (lambda p: write_mcap(p, _records(), replace={(EXTRA_TOPIC, 10): b"\x00\x01\x00\x00garbage"}),
                             r"/armid/joint_state_extra message 10 \(in the chunk at byte \d+\): not a armid_msgs/msg/JointStateExtra in CDR"),
    "the JSON layout of old": (_json_layout, r"bad\.mcap: an MCAP in the JSON layout \(channel /joint_state\).*no longer read"),
    "recorded on another robot": (lambda p: _mcap_with(p, lambda m: None, {"robot": "ur5"}),
                                  r"recorded on robot 'ur5'.* describes 'puma560'"),
    "seven joints recorded": (lambda p: _mcap_with(p, _seven_joints), r"7 joints recorded, robot puma560 has 6"),
    "not an MCAP file": (lambda p: (p.write_bytes(b"hello, this is not MCAP" * 100), p)[1], r"not an MCAP file"),
    "magic only": (lambda p: (p.write_bytes(b"\x89MCAP0\r\n"), p)[1], r"no joint_state record"),
    "every chunk corrupt": (_every_chunk_flipped, r"no joint_state record could be read: a chunk that fails its CRC"),
    "time stamps in milliseconds": (lambda p: _mcap_with(p, _stamped_two_seconds_apart), r"milliseconds"),
    "zero torque": (lambda p: _mcap_with(p, _zero_torque), r"every torque is zero"),
}


@pytest.mark.parametrize("case", list(MCAP_CASES))
def test_bad_mcap(case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    make, expect = MCAP_CASES[case]
    bad = make(tmp_path / "bad.mcap")
    assert_clean_error(*run(["identify", str(bad), "--robot", str(PUMA)], capsys), expect)


def _read_as_identify_does(path: Path) -> Any:
    """What ``armid identify`` does before preprocessing: read, then the plausibility checks."""
    from armid.identify.plausibility import check_recording
    from armid.io.recordings import read_recording
    from armid.io.robot_file import load_robot

    rec = read_recording(path, load_robot(PUMA))
    assert check_recording(rec.t, rec.q, rec.qd, rec.tau, rec.source) == []
    return rec


def test_the_unbroken_mcap_reads_whole() -> None:
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        rec = _read_as_identify_does(_mcap_with(Path(folder) / "good.mcap", lambda m: None))
    assert rec.n_samples == ROWS and np.allclose(rec.tau, TAU) and not any("lost" in n for n in rec.notes)


def test_mcap_time_going_backwards_is_read_and_said(tmp_path: Path) -> None:
    """A clock step back on the bench: the records stamped before an earlier one are left out, and said so."""
    def step_back(records: list[JointStateRecord]) -> None:
        for r in records[300:]:
            r.sample.time_s = float(T[r.sequence] - 0.05)
    rec = _read_as_identify_does(_mcap_with(tmp_path / "step.mcap", step_back))
    assert any(re.search(r"time goes backwards at sequence 300 .*left out 25 records", n) for n in rec.notes), rec.notes
    assert rec.n_samples == ROWS - 25 and np.all(np.diff(rec.t) > 0)


def test_an_mcap_that_names_no_robot_is_read_and_said(tmp_path: Path) -> None:
    """Metadata stripped (another tool's copy): the recording cannot be checked against
    --robot; it is read as that robot, and the notes say so. One that names another robot is refused."""
    rec = _read_as_identify_does(_mcap_with(tmp_path / "bare.mcap", lambda m: None, metadata={}))
    assert any("its metadata names no robot" in n and "puma560" in n for n in rec.notes), rec.notes
    assert not any("names no robot" in n for n in _read_as_identify_does(_mcap_with(tmp_path / "named.mcap", lambda m: None)).notes)
    from armid.identify.errors import RecordingError
    from armid.io.recordings import read_recording
    from armid.io.robot_file import load_robot

    with pytest.raises(RecordingError, match="recorded on robot .ur5."):
        read_recording(_mcap_with(tmp_path / "other.mcap", lambda m: None, metadata={"robot": "ur5"}), load_robot(PUMA))


# -- rosbag2 bags (written by rosbags: tests/bagwriter.py) ------------------------------

BAG_T0_NS = 1_600_000_000 * 10**9  # the example's 2 ms stamps from an epoch second (a zero stamp means "not stamped")
PUMA_NAMES = [f"j{j + 1}" for j in range(6)]


def _bag_messages(order: list[int] | None = None, t_shift_ns: int = 0) -> list[Any]:
    """The example's rows as JointState messages, joints in ``order`` (reversed unless given)."""
    from bagwriter import arm_messages

    t_ns = BAG_T0_NS + t_shift_ns + np.round(T * 1e9).astype(np.int64)
    return arm_messages(t_ns, PUMA_NAMES, Q, QD, TAU, list(range(6))[::-1] if order is None else order)


def _bag(path: Path, storage: str, change: Callable[[list[Any]], list[Any] | None] | None = None) -> Path:
    from bagwriter import write_bag

    messages = _bag_messages()
    if change is not None:
        messages = change(messages) or messages
    return write_bag(path, storage, messages)


def _cut(path: Path, storage: str) -> Path:
    from bagwriter import storage_file

    f = storage_file(_bag(path, storage))
    f.write_bytes(f.read_bytes()[: f.stat().st_size * 9 // 10])
    return path


def _each(field: str, value: Callable[[Any], Any]) -> Callable[[list[Any]], None]:
    def change(messages: list[Any]) -> None:
        for m in messages:
            setattr(m, field, value(m))
    return change


def _two_publishers(messages: list[Any]) -> list[Any]:
    """A second publisher of the same joints interleaved (received 1 us after the first), its stamps 1 s behind."""
    behind = _bag_messages(t_shift_ns=-10**9)
    for m, b in zip(messages, behind):
        b.received_ns = m.stamp_ns + 1000
    return [m for pair in zip(messages, behind) for m in pair]


def _two_orders(messages: list[Any]) -> list[Any]:
    other = _bag_messages(order=list(range(6)), t_shift_ns=1000)
    return [m for pair in zip(messages, other) for m in pair]


def _split(messages: list[Any]) -> list[Any]:
    """The arm's joints in two messages a cycle (3 and 3), as two controllers might publish them."""
    from bagwriter import Message

    out = []
    for m in messages:
        for part in (slice(0, 3), slice(3, 6)):
            out.append(Message(m.stamp_ns, m.names[part], m.position[part], m.velocity[part], m.effort[part]))
    return out


def _same_stamp_other_values(messages: list[Any]) -> list[Any]:
    from bagwriter import Message

    m = messages[50]
    return [*messages[:51], Message(m.stamp_ns, m.names, m.position + 0.1, m.velocity, m.effort), *messages[51:]]


def _garbage_message(messages: list[Any]) -> None:
    messages[10].raw = b"\x00\x01\x00\x00not a joint state"


def _wrong_type(messages: list[Any]) -> list[Any]:
    from bagwriter import Message

    return [Message(m.stamp_ns, [], [], msgtype="std_msgs/msg/String", extra={"data": "hello"}) for m in messages]


def _short_position(messages: list[Any]) -> None:
    messages[20].position = messages[20].position[:5]


def _no_folder_metadata(path: Path, storage: str) -> Path:
    _bag(path, storage)
    (path / "metadata.yaml").unlink()
    return path


BAG_CASES: dict[str, tuple[Callable[[Path, str], Path], str]] = {
    "truncated": (_cut, r"the bag cannot be read, cut short or damaged\?"),
    "wrong message type": (lambda p, s: _bag(p, s, _wrong_type), r"carries std_msgs/msg/String, not sensor_msgs/msg/JointState"),
    "topic absent": (lambda p, s: _bag(p, s, _each("topic", lambda m: "/other")),
                     r"not in the bag \(it holds /other \(sensor_msgs/msg/JointState\); --topic chooses another\)"),
    "joint missing": (lambda p, s: _bag(p, s, lambda ms: [type(m)(m.stamp_ns, m.names[1:], m.position[1:], m.velocity[1:], m.effort[1:])
                                                          for m in ms]), r"joint\(s\) j6 of .*puma560\.yaml missing \(the messages name j5, j4"),
    "effort empty": (lambda p, s: _bag(p, s, _each("effort", lambda m: [])), r"effort is empty in every message \(600 messages\)"),
    "effort NaN": (lambda p, s: _bag(p, s, _each("effort", lambda m: np.where(np.arange(6) == 3, np.nan, m.effort))),
                   r"effort is NaN in every message for joint\(s\) j3"),
    "position NaN": (lambda p, s: _bag(p, s, _each("position", lambda m: np.where(np.arange(6) == 0, np.nan, m.position))),
                     r"position is NaN in every message for joint\(s\) j6"),
    "second publisher, stamps go back": (lambda p, s: _bag(p, s, _two_publishers), r"header stamps go back 600 time\(s\) \(first at message 2"),
    "two publishers of every joint": (lambda p, s: _bag(p, s, _two_orders), r"two publishers name every joint of puma560"),
    "joints split across messages": (lambda p, s: _bag(p, s, _split), r"the joints of puma560 are split across messages"),
    "one stamp, two values": (lambda p, s: _bag(p, s, _same_stamp_other_values), r"messages 51 and 52 are both stamped .* with different values"),
    "not JointState CDR": (lambda p, s: _bag(p, s, _garbage_message), r"message 11: not a sensor_msgs/msg/JointState in CDR"),
    "position short": (lambda p, s: _bag(p, s, _short_position), r"message 21: 'position' has 5 values for 6 joint names"),
    "folder without metadata.yaml": (_no_folder_metadata, r"a folder without metadata\.yaml: not a rosbag2 bag"),
}


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
@pytest.mark.parametrize("case", list(BAG_CASES))
def test_bad_bag(case: str, storage: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Exit 2, one line naming the bag, the topic and the problem."""
    make, expect = BAG_CASES[case]
    bad = make(tmp_path / "bad", storage)
    where = r"bad: " if case == "folder without metadata.yaml" else r"bad: topic /joint_states: "
    assert_clean_error(*run(["identify", str(bad), "--robot", str(PUMA)], capsys), where + expect)


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_a_bag_s_storage_file_cut_short_is_named(storage: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from bagwriter import storage_file

    f = storage_file(_cut(tmp_path / "bad", storage))
    assert_clean_error(*run(["identify", str(f), "--robot", str(PUMA)], capsys), rf"{f.name}: topic /joint_states: the bag cannot be read")


def test_the_unbroken_bag_and_its_unstamped_twin_identify(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The bags the cases break identify; a bag without header stamps too, on its receive time, said."""
    assert run(["identify", str(_bag(tmp_path / "good", "mcap")), "--robot", str(PUMA)], capsys)[0] == 0

    def unstamped(messages: list[Any]) -> None:
        for m in messages:
            m.received_ns, m.stamp_ns = m.stamp_ns, 0

    code, err = run(["identify", str(_bag(tmp_path / "unstamped", "sqlite3", unstamped)), "--robot", str(PUMA)], capsys)
    assert code == 0 and "every header stamp on /joint_states is zero: timed by the bag's receive time" in err


# -- robot descriptions ------------------------------------------------------------------

def _robot(path: Path, change: Callable[[dict[str, Any]], None]) -> Path:
    doc = yaml.safe_load(PUMA.read_text())
    change(doc)
    path.write_text(yaml.safe_dump(doc))
    return path


def _joint(k: int, key: str, value: Any) -> Callable[[dict[str, Any]], None]:
    def change(doc: dict[str, Any]) -> None:
        target = doc["joints"][k]
        *path, leaf = key.split(".")
        for part in path:
            target = target[part]
        if value is _DELETE:
            del target[leaf]
        else:
            target[leaf] = value
    return change


def _ur5(path: Path, joint_type: str) -> Path:
    doc = yaml.safe_load(UR5.read_text())
    doc["urdf"] = str(UR5.parent / doc["urdf"])
    doc["joints"][1]["type"] = joint_type
    path.write_text(yaml.safe_dump(doc))
    return path


def _ur5_urdf_nan(path: Path) -> Path:
    """The UR5 with ``nan`` in its shoulder link's inertial origin (the URDF parser reads it as a number)."""
    urdf = (UR5.parent / "ur5.urdf").read_text()
    at = urdf.index('<link name="shoulder_link">')
    tail = urdf[at:].replace('<origin xyz="0 0 0"', '<origin xyz="nan 0 0"', 1)
    (path.parent / "nan.urdf").write_text(urdf[:at] + tail)
    doc = yaml.safe_load(UR5.read_text())
    doc["urdf"] = "nan.urdf"
    path.write_text(yaml.safe_dump(doc))
    return path


ROBOT_CASES: dict[str, tuple[Callable[[Path], Path], str]] = {
    "nested 5000 deep": (lambda p: (p.write_text("[" * 5000 + "]" * 5000), p)[1], r"nested too deeply"),
    "mapping nested 5000 deep": (lambda p: (p.write_text("a: " + "{b: " * 5000 + "1" + "}" * 5000), p)[1], r"nested too deeply"),
    "not YAML": (lambda p: (p.write_text("name: [puma\njoints: {"), p)[1], r"not valid YAML"),
    "a list, not a mapping": (lambda p: (p.write_text("- a\n- b\n"), p)[1], r"must be a mapping"),
    "empty": (lambda p: (p.write_text(""), p)[1], r"must be a mapping"),
    "unknown field": (lambda p: _robot(p, lambda d: d.update(colour="red")), r"colour: unknown field"),
    "no joints": (lambda p: _robot(p, lambda d: d.update(joints=[])), r"joints: must be a non-empty list"),
    "gravity of two": (lambda p: _robot(p, lambda d: d.update(gravity=[0, -9.81])), r"gravity: must be a list of 3"),
    "negative principal moment": (lambda p: _robot(p, _joint(1, "inertial.inertia", [-0.13, 0, 0, 0.524, 0, 0.539])),
                                  r"joints\[1\]\.inertial\.inertia: not positive semi-definite"),
    "indefinite inertia": (lambda p: _robot(p, _joint(3, "inertial.inertia", [0.1, 0.5, 0, 0.1, 0, 0.1])),
                           r"joints\[3\]\.inertial\.inertia: not positive semi-definite"),
    "negative mass": (lambda p: _robot(p, _joint(2, "inertial.mass", -4.8)), r"joints\[2\]\.inertial\.mass: must not be negative"),
    "inertial unknown field": (lambda p: _robot(p, _joint(1, "inertial.about", "origin")), r"joints\[1\]\.inertial\.about: unknown field"),
    "inertia of five": (lambda p: _robot(p, _joint(2, "inertial.inertia", [0.1] * 5)), r"inertia: must be a list of 6"),
    "position limits reversed": (lambda p: _robot(p, _joint(1, "limits.position", [1.0, -1.0])), r"lower 1.0 must be below"),
    "negative velocity limit": (lambda p: _robot(p, _joint(1, "limits.velocity", -1.5)), r"velocity: must be positive"),
    "zero torque constant": (lambda p: _robot(p, _joint(0, "torque_constant", 0)), r"torque_constant: must be positive"),
    "effort neither torque nor current": (lambda p: _robot(p, lambda d: d.update(effort="voltage")),
                                          r"effort: must be one of torque, current .*got 'voltage'"),
    "effort current without torque constants": (lambda p: (p.write_text(UR5.read_text().replace("torque_constant: 13.3}", "type: revolute}")
                                                                        .replace("urdf: ur5.urdf", f"urdf: {UR5.parent / 'ur5.urdf'}")
                                                                        + "effort: current\n"), p)[1],
                                                r"effort: current needs each joint's torque_constant .*none for shoulder_pan_joint, shoulder_lift_joint$"),
    "unknown effect": (lambda p: _robot(p, lambda d: d.update(effects=[{"effect": "magic"}])), r"unknown effect 'magic'"),
    "effect on joint 9": (lambda p: _robot(p, lambda d: d.update(effects=[{"effect": "viscous_friction", "joint": 9}])),
                          r"must be a joint number 1\.\.6"),
    "URDF missing": (lambda p: _robot(p, lambda d: d.update(urdf="nope.urdf")), r"urdf: no such file"),
    "URDF joint type contradicted": (lambda p: _ur5(p, "prismatic"), r"joints\[1\]\.type: prismatic here, but ur5\.urdf makes "
                                                                      r"'shoulder_lift_joint' revolute"),
    "URDF joint type unknown": (lambda p: _ur5(p, "helical"), r"joints\[1\]\.type: must be revolute or prismatic"),
    "URDF inertial origin NaN": (_ur5_urdf_nan, r"urdf: .*nan\.urdf: the URDF parser left part of it out \(Error: Unable to parse component \[nan\]"),
}
for _k in range(6):  # every kinematic number of every joint, broken three ways
    for _key in ("a", "alpha", "d", "theta"):
        ROBOT_CASES[f"joints[{_k}].{_key} a word"] = (lambda p, k=_k, key=_key: _robot(p, _joint(k, key, "zero")),
                                                      rf"joints\[{_k}\]\.{_key}: must be a number, got 'zero'")
        ROBOT_CASES[f"joints[{_k}].{_key} infinite"] = (lambda p, k=_k, key=_key: _robot(p, _joint(k, key, float("inf"))),
                                                        rf"joints\[{_k}\]\.{_key}: must be finite")
        ROBOT_CASES[f"joints[{_k}].{_key} missing"] = (lambda p, k=_k, key=_key: _robot(p, _joint(k, key, _DELETE)),
                                                       rf"joints\[{_k}\]\.{_key}: missing")


@pytest.mark.parametrize("case", list(ROBOT_CASES))
def test_bad_robot(case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    make, expect = ROBOT_CASES[case]
    bad = make(tmp_path / "robot.yaml")
    assert_clean_error(*run(["identify", str(EXAMPLE), "--robot", str(bad)], capsys), expect)


@pytest.mark.parametrize("name, text, said", [
    ("arm.urdf.xacro", '<robot xmlns:xacro="http://www.ros.org/wiki/xacro" name="a"><xacro:arm prefix=""/></robot>\n',
     r"arm\.urdf\.xacro: not a loadable URDF \(a xacro file: expand it first.*\(Error: No link elements found"),
    ("cut.urdf", '<robot name="a"><link name="b"><inertial><mass value="1"/>\n', r"cut\.urdf: not a loadable URDF"),
])
def test_an_unreadable_urdf_is_one_line_whatever_its_parser_prints(name: str, text: str, said: str, tmp_path: Path) -> None:
    """urdfdom (C++) writes its complaint to file descriptor 2 itself; armid holds it and quotes it."""
    (tmp_path / name).write_text(text)
    (tmp_path / "r.yaml").write_text(f"name: a\nurdf: {name}\njoints: [{{name: j1}}]\n")
    proc = subprocess.run([sys.executable, "-m", "armid.cli", "identify", str(EXAMPLE), "--robot", str(tmp_path / "r.yaml")],
                          capture_output=True, text=True)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and re.search(said, lines[0]), proc.stderr


def test_urdf_robot_repeating_its_urdf_is_accepted(tmp_path: Path) -> None:
    from armid.io.robot_file import load_robot

    same = load_robot(_ur5(tmp_path / "same.yaml", "revolute"))
    assert [j.type.value for j in same.joints] == ["revolute"] * 6


def test_robot_argument_takes_a_shipped_name_a_robot_file_or_a_urdf(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Issue 36: every ``--robot`` takes a shipped robot's name, a robot file or a URDF (a robot
    of the URDF alone: its movable joints in order, torque constant 1); an unknown name is one
    error line that lists the shipped robots."""
    from armid.cli import load_robot_argument
    from armid.io.robot_file import load_robot

    assert load_robot_argument("ur5").name == "ur5"
    from_urdf = load_robot_argument(str(UR5.parent / "ur5.urdf"))
    from_file = load_robot(UR5)
    assert [j.name for j in from_urdf.joints] == [j.name for j in from_file.joints]
    assert all(j.torque_constant == 1.0 for j in from_urdf.joints) and from_urdf.effects == ()
    q = np.random.default_rng(0).uniform(-1, 1, (5, 6))
    from armid.identify.dynamics import regressor
    np.testing.assert_allclose(regressor(from_urdf, q, q, q), regressor(from_file, q, q, q), atol=1e-12)  # the same kinematics
    code, err = run(["identify", str(EXAMPLE), "--robot", "puma"], capsys)
    assert_clean_error(code, err, r"puma: no such file, nor a shipped robot \(shipped: .*puma560.*\)")


def test_triangle_violating_inertia_is_a_warning(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from armid.identify.errors import ImplausibleDataWarning
    from armid.io.robot_file import load_robot

    published = _robot(tmp_path / "published.yaml", _joint(2, "inertial.inertia", PUBLISHED_LINK3_INERTIA))
    with pytest.warns(ImplausibleDataWarning, match=r"joints\[2\]\.inertial\.inertia: .* break the triangle inequality"):
        load_robot(published)  # the published PUMA 560 value of link 3 (Armstrong et al. 1986)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_robot(PUMA)  # the shipped one is a rigid body
    flat = _robot(tmp_path / "flat.yaml", _joint(4, "inertial.inertia", [0.01, 0, 0, 0.01, 0, 0.5]))
    with pytest.warns(ImplausibleDataWarning, match=r"joints\[4\]\.inertial\.inertia: .*0.01 \+ 0.01 < 0.5"):
        load_robot(flat)
    # held while the inputs are read: bad input still ends in its one error line alone
    code, err = run(["identify", str(_recording(tmp_path / "ms.csv", t=T * 1e3)), "--robot", str(flat)], capsys)
    assert_clean_error(code, err, r"milliseconds")


# -- rigs --------------------------------------------------------------------------------

def _rig(path: Path, change: Callable[[dict[str, Any]], None]) -> Path:
    doc = yaml.safe_load(RIG.read_text())
    doc["robot"] = str(PUMA)
    change(doc)
    path.write_text(yaml.safe_dump(doc))
    return path


def _sim(key: str, value: Any) -> Callable[[dict[str, Any]], None]:
    return lambda d: d["simulation"].update({key: value})


RIG_CASES: dict[str, tuple[Callable[[Path], Path], str]] = {
    "unknown CAN interface": (lambda p: _rig(p, lambda d: d["bus"].update(interface="nosuchcan")),
                              r"bus\.interface: unknown CAN interface 'nosuchcan'"),
    "no bus": (lambda p: _rig(p, lambda d: d.pop("bus")), r"bus\.interface: missing"),
    "bus without interface": (lambda p: _rig(p, lambda d: d["bus"].pop("interface")), r"bus\.interface: missing"),
    "substeps 0": (lambda p: _rig(p, _sim("substeps", 0)), r"simulation\.substeps: must be in 1\.\.1000, got 0"),
    "substeps a word": (lambda p: _rig(p, _sim("substeps", "two")), r"simulation\.substeps: must be an integer"),
    "initial position beyond a limit": (lambda p: _rig(p, _sim("initial_position", [0, 5.0, -0.7854, 0, 0, 0])),
                                        r"simulation\.initial_position\[1\]: 5 is beyond joint 2's position limits"),
    "initial position of five": (lambda p: _rig(p, _sim("initial_position", [0.0] * 5)), r"initial_position: must be a list of 6"),
    "negative current noise": (lambda p: _rig(p, _sim("current_noise_a", -0.1)), r"current_noise_a: must not be negative"),
    "unknown simulation setting": (lambda p: _rig(p, _sim("wind", 3)), r"simulation\.wind: unknown setting"),
    "effect on joint 8": (lambda p: _rig(p, _sim("effects", [{"joint": 8, "viscous": 1.0}])), r"effects\[0\]\.joint: must be 1\.\.6"),
    "simulation a list": (lambda p: _rig(p, lambda d: d.update(simulation=[1, 2])), r"simulation: must be a mapping"),
    "channel a list": (lambda p: _rig(p, lambda d: d["bus"].update(channel=[1])), r"bus\.channel: must be a name or a number"),
    "name a list": (lambda p: _rig(p, lambda d: d.update(name=["a"])), r"name: must be a string"),
    "period negative": (lambda p: _rig(p, lambda d: d.update(period_s=-0.002)), r"period_s: must be positive"),
    "a drive missing": (lambda p: _rig(p, lambda d: d["drives"].pop()), r"drives: must list one drive per joint \(6\)"),
    "node id twice": (lambda p: _rig(p, lambda d: d["drives"][1].update(node_id=1)), r"drives\[1\]\.node_id: node id 1 is used twice"),
    "robot missing": (lambda p: _rig(p, lambda d: d.update(robot="nope.yaml")), r"nope\.yaml: no such file"),
    "robot not a path": (lambda p: _rig(p, lambda d: d.update(robot=[1, 2])), r"robot: must be the path"),
    "nested 1500 deep": (lambda p: (p.write_text("[" * 1500 + "]" * 1500), p)[1], r"nested too deeply"),
    "no such rig": (lambda p: p.with_name("nope.yaml"), r"nope\.yaml: no such file"),
}


def _rig_argv(command: str, rig: Path, out: Path) -> list[str]:
    if command == "record":
        return ["record", "--rig", str(rig), "--out", str(out), "--duration", "0.5", "--no-zenoh"]
    if command == "excite":
        return ["excite", "--rig", str(rig), "--out", str(out), "--dry-run"]
    return ["sim", "--rig", str(rig), "--duration", "0.5"]


@pytest.mark.parametrize("command", ["record", "excite", "sim"])
@pytest.mark.parametrize("case", list(RIG_CASES))
def test_bad_rig(case: str, command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    make, expect = RIG_CASES[case]
    bad = make(tmp_path / "rig.yaml")
    assert_clean_error(*run(_rig_argv(command, bad, tmp_path / "out"), capsys), expect)
    assert not (tmp_path / "out").exists()  # refused before anything was written


@pytest.mark.parametrize("command", ["record", "excite", "sim"])
def test_unknown_interface_override(command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = _rig_argv(command, _rig(tmp_path / "rig.yaml", lambda d: None), tmp_path / "out") + ["--interface", "nosuchcan"]
    assert_clean_error(*run(argv, capsys), r"--interface\)?: unknown CAN interface 'nosuchcan'")


def test_unbroken_rig_loads(tmp_path: Path) -> None:
    from armid.io.rig_file import load_rig
    assert load_rig(_rig(tmp_path / "rig.yaml", lambda d: None)).n_joints == 6


# -- trajectories (armid excite --trajectory) --------------------------------------------

def _trajectory(path: Path, change: Callable[[dict[str, Any]], Any]) -> Path:
    doc = json.loads(json.dumps(TRAJECTORY))
    doc = change(doc) or doc
    path.write_text(json.dumps(doc))
    return path


def _fourier(key: str, value: Any) -> Callable[[dict[str, Any]], None]:
    def change(doc: dict[str, Any]) -> None:
        if value is _DELETE:
            del doc["fourier"][key]
        else:
            doc["fourier"][key] = value
    return change


TRAJECTORY_CASES: dict[str, tuple[Callable[[Path], Path], str]] = {
    "bad syntax": (lambda p: (p.write_text('{"fourier": {"q0": [0, '), p)[1], r"line 1 column \d+: not valid JSON"),
    "q0 missing": (lambda p: _trajectory(p, _fourier("q0", _DELETE)), r"fourier\.q0: missing"),
    "base frequency missing": (lambda p: _trajectory(p, _fourier("base_frequency_hz", _DELETE)), r"base_frequency_hz: missing"),
    "five joints": (lambda p: _trajectory(p, _fourier("q0", Q0[:5])), r"fourier\.q0: 5 joints, the rig's robot has 6"),
    "coefficients for five joints": (lambda p: _trajectory(p, _fourier("a", [[0.1, 0.0]] * 5)), r"fourier\.a: shape \(5, 2\)"),
    "a and b differ": (lambda p: _trajectory(p, _fourier("b", [[0.0]] * 6)), r"fourier\.b: shape \(6, 1\) differs"),
    "ragged coefficients": (lambda p: _trajectory(p, _fourier("a", [[0.1, 0.0]] * 5 + [[0.1]])), r"fourier\.a: must be"),
    "base frequency 0": (lambda p: _trajectory(p, _fourier("base_frequency_hz", 0)), r"base_frequency_hz: must lie in \(0, "),
    "base frequency negative": (lambda p: _trajectory(p, _fourier("base_frequency_hz", -0.2)), r"base_frequency_hz: must lie in"),
    "base frequency beyond Nyquist": (lambda p: _trajectory(p, _fourier("base_frequency_hz", 1e6)), r"base_frequency_hz: must lie in"),
    "base frequency a word": (lambda p: _trajectory(p, _fourier("base_frequency_hz", "fast")), r"must be a finite number"),
    "base frequency NaN": (lambda p: (p.write_text(json.dumps(TRAJECTORY).replace("0.2}", "NaN}")), p)[1], r"must be a finite number"),
    "coefficient NaN": (lambda p: (p.write_text(json.dumps(TRAJECTORY).replace("0.05", "NaN", 1)), p)[1], r"finite numbers only"),
    "a list": (lambda p: (p.write_text("[1, 2, 3]"), p)[1], r"must be a JSON object"),
    "two designs": (lambda p: _trajectory(p, lambda d: {"link6": d, "whole": d}), r"holds 2 designs \(link6, whole\)"),
    "moving joint 7": (lambda p: _trajectory(p, lambda d: d.update(moving_joints=[7])), r"moving_joints: must be a list of distinct"),
    "nested 5000 deep": (lambda p: (p.write_text("[" * 5000 + "]" * 5000), p)[1], r"nested too deeply"),
    "no such file": (lambda p: p.with_name("nope.json"), r"nope\.json: no such file"),
}


@pytest.mark.parametrize("case", list(TRAJECTORY_CASES))
def test_bad_trajectory(case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    make, expect = TRAJECTORY_CASES[case]
    bad = make(tmp_path / "trajectory.json")
    argv = ["excite", "--rig", str(RIG), "--trajectory", str(bad), "--dry-run", "--out", str(tmp_path / "out")]
    assert_clean_error(*run(argv, capsys), expect)


def test_unbroken_trajectory_plans_and_writes_strict_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The unbroken file through ``armid excite --dry-run``: checked against every limit, and its
    design (no condition number for a given trajectory) written with null, not NaN."""
    out = tmp_path / "out"
    argv = ["excite", "--rig", str(RIG), "--trajectory", str(_trajectory(tmp_path / "t.json", lambda d: None)), "--dry-run",
            "--out", str(out)]
    code, err = run(argv, capsys)
    assert code == 0 and "checked against every limit" in err, err
    design = json.loads((out / "designs.json").read_text(), parse_constant=_refuse_constant)["t"]
    assert design["condition_number"] is None and design["fourier"]["base_frequency_hz"] == 0.2


def test_unbroken_trajectory_loads(tmp_path: Path) -> None:
    traj, moving = load_trajectory(_trajectory(tmp_path / "t.json", lambda d: None), 6, 0.002)
    assert traj.base_frequency_hz == 0.2 and moving == tuple(range(6))
    one = _trajectory(tmp_path / "one.json", lambda d: {"whole": {**d, "moving_joints": [2, 3]}})
    assert load_trajectory(one, 6, 0.002)[1] == (1, 2)


# -- options -----------------------------------------------------------------------------

OPTION_CASES: dict[str, tuple[list[str], str]] = {
    "lowpass negative": (["identify", str(EXAMPLE), "--robot", str(PUMA), "--lowpass", "-5"], r"--lowpass: must be a positive cutoff"),
    "lowpass zero": (["diagnose", str(EXAMPLE), "--robot", str(PUMA), "--validate", str(EXAMPLE), "--lowpass", "0"],
                     r"--lowpass: must be a positive"),
    "lowpass beyond Nyquist": (["identify", str(EXAMPLE), "--robot", str(PUMA), "--lowpass", "1e9"],
                               r"--lowpass: 1e\+09 Hz is not below the Nyquist frequency .* \(250 Hz"),
    "lowpass NaN": (["identify", str(EXAMPLE), "--robot", str(PUMA), "--lowpass", "nan"], r"--lowpass: must be finite"),
    "lowpass a word": (["identify", str(EXAMPLE), "--robot", str(PUMA), "--lowpass", "soft"], r"--lowpass: 'soft' is not a number"),
    "gap factor 0": (["identify", str(EXAMPLE), "--robot", str(PUMA), "--max-gap-factor", "0"], r"--max-gap-factor: must be at least 2"),
    "sim duration negative": (["sim", "--rig", str(RIG), "--duration", "-5"], r"--duration: must be positive, got -5"),
    "sim duration 0": (["sim", "--rig", str(RIG), "--duration", "0"], r"--duration: must be positive"),
    "sim duration infinite": (["sim", "--rig", str(RIG), "--duration", "inf"], r"--duration: must be finite"),
    "sim seed negative": (["sim", "--rig", str(RIG), "--seed", "-1"], r"--seed: must be 0 or more"),
    "record duration negative": (["record", "--rig", str(RIG), "--out", "x", "--duration", "-1"], r"--duration: must be positive"),
    "watch duration negative": (["watch", "--robot", "puma560", "--duration", "-1"], r"--duration: must be positive"),
    "excite periods 0": (["excite", "--rig", str(RIG), "--dry-run", "--periods", "0"], r"--periods: must be at least 1"),
    "excite periods a fraction": (["excite", "--rig", str(RIG), "--dry-run", "--periods", "1.5"], r"--periods: '1.5' is not a whole"),
    "excite frequency 0": (["excite", "--rig", str(RIG), "--dry-run", "--frequency", "0"], r"--frequency: must be positive"),
    "excite frequency negative": (["excite", "--rig", str(RIG), "--dry-run", "--frequency", "-0.5"], r"--frequency: must be positive"),
    "excite frequency beyond Nyquist": (["excite", "--rig", str(RIG), "--dry-run", "--frequency", "1e9"],
                                        r"--frequency: 1e\+09 Hz is not below the 250 Hz Nyquist"),
    "excite tracking limit negative": (["excite", "--rig", str(RIG), "--dry-run", "--tracking-limit", "-0.2"],
                                       r"--tracking-limit: must be positive"),
    "excite seed negative": (["excite", "--rig", str(RIG), "--dry-run", "--seed", "-3"], r"--seed: must be 0 or more"),
    "excite link 9": (["excite", "--rig", str(RIG), "--dry-run", "--link", "9"], r"--link: joint 9 does not exist"),
    "excite link a word": (["excite", "--rig", str(RIG), "--dry-run", "--link", "elbow"], r"--link: 'elbow' is not a joint number"),
    "demo seed negative": (["demo", "--seed", "-1"], r"--seed: must be 0 or more"),
    "identify without data": (["identify", "--robot", str(PUMA)], r"the following arguments are required: data"),
    "identify without robot": (["identify", str(EXAMPLE)], r"the following arguments are required: --robot"),
    "unknown weighting": (["identify", str(EXAMPLE), "--robot", str(PUMA), "--weighting", "best"], r"--weighting: invalid choice"),
    "unknown command": (["calibrate"], r"invalid choice: 'calibrate'"),
    "lab Zenoh file without its certificates": (["watch", "--robot", "puma560", "--duration", "0.1", "--zenoh-config", str(LAB)],
                                                r"lab\.json5: transport\.link\.tls\.\w+: no such file /etc/armid/tls/"),
    "Zenoh file missing": (["watch", "--robot", "puma560", "--zenoh-config", "nope.json5"], r"nope\.json5: no such file"),
    "Zenoh endpoint garbage": (["watch", "--robot", "puma560", "--duration", "0.1", "--zenoh-connect", "nonsense"],
                               r"--zenoh-listen/--zenoh-connect: Endpoints must be of the form"),
}


@pytest.mark.parametrize("case", list(OPTION_CASES))
def test_bad_option(case: str, capsys: pytest.CaptureFixture[str]) -> None:
    argv, expect = OPTION_CASES[case]
    assert_clean_error(*run(argv, capsys), expect)


def test_garbage_zenoh_configuration(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "zenoh.json5"
    bad.write_text("{ mode: peer, listen: {{{ }")
    code, err = run(["watch", "--robot", "puma560", "--duration", "0.1", "--zenoh-config", str(bad)], capsys)
    assert_clean_error(code, err, r"zenoh\.json5: not a usable Zenoh configuration")


def test_lowpass_words_pass_the_option_check() -> None:
    """'off' and 'auto' reach the command as given ('off' also runs end to end above)."""
    from armid.cli import build_parser

    for word in ("off", "auto", "AUTO"):
        args = build_parser().parse_args(["identify", str(EXAMPLE), "--robot", str(PUMA), "--lowpass", word])
        assert args.lowpass == word.lower()
    assert build_parser().parse_args(["identify", str(EXAMPLE), "--robot", str(PUMA), "--lowpass", "20"]).lowpass == 20.0


# -- JSON --------------------------------------------------------------------------------

def _refuse_constant(name: str) -> None:
    raise ValueError(f"bare {name} in JSON")


def test_json_writers_never_write_bare_nan() -> None:
    doc = {"a": float("nan"), "b": [np.float64("inf"), 1.5, np.int64(3)], "c": {"d": np.array([np.nan, 2.0])}, "e": "NaN"}
    text = strict_json(doc)
    assert json.loads(text, parse_constant=_refuse_constant) == {"a": None, "b": [None, 1.5, 3], "c": {"d": [None, 2.0]}, "e": "NaN"}


# -- end to end --------------------------------------------------------------------------

def _cli(argv: list[str], debug: bool = False) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("ARMID_DEBUG", None)
    if debug:
        env["ARMID_DEBUG"] = "1"
    return subprocess.run([sys.executable, "-m", "armid.cli", *argv], capture_output=True, text=True, env=env, timeout=120, cwd=ROOT)


def test_end_to_end_one_line_and_debug_traceback(tmp_path: Path) -> None:
    ms = _recording(tmp_path / "ms.csv", t=T * 1e3)
    deep = tmp_path / "deep.yaml"
    deep.write_text("[" * 5000 + "]" * 5000)
    traj = TRAJECTORY_CASES["base frequency negative"][0](tmp_path / "t.json")
    for argv, expect in ((["identify", str(ms), "--robot", str(PUMA)], r"milliseconds"),
                         (["identify", str(EXAMPLE), "--robot", str(deep)], r"nested too deeply"),
                         (["excite", "--rig", str(RIG), "--trajectory", str(traj), "--dry-run", "--out", str(tmp_path / "o")],
                          r"base_frequency_hz: must lie in"),
                         (["sim", "--rig", str(RIG), "--duration", "-5"], r"--duration: must be positive")):
        proc = _cli(argv)
        assert_clean_error(proc.returncode, proc.stderr, expect)
    debug = _cli(["identify", str(ms), "--robot", str(PUMA)], debug=True)
    assert debug.returncode == 2 and "Traceback" in debug.stderr and debug.stderr.strip().splitlines()[-1].startswith("armid identify: error:")


# -- the plausibility API (identify/plausibility.py) -----------------------------------------

def test_plausibility_api_warns_on_what_may_be_right_and_refuses_garbage() -> None:
    from armid.identify.errors import RecordingError
    from armid.identify.plausibility import check_recording, velocity_ratio

    assert check_recording(T, Q, QD, TAU, "ex.csv") == []
    assert velocity_ratio(T, Q, QD) == pytest.approx(1.0, abs=0.01)
    assert velocity_ratio(T * 1e3, Q, QD) == pytest.approx(1e-3, rel=0.01)
    still = Q.copy()
    still[:, 5] = Q[0, 5]
    held = TAU.copy()
    held[:, 5] = 0.25
    said = check_recording(T, still, None, held, "ex.csv")  # a joint that stays still, its torque held: may be right
    assert said == ["ex.csv: column tau6: the torque is constant (0.25) over the whole recording"]
    odd = check_recording(T, Q, QD * 3.0, TAU, "ex.csv")  # neither a time unit nor degrees: said, not refused
    assert len(odd) == 1 and re.search(r"columns qd: dq/dt is 0.33\d times the velocity columns", odd[0]), odd
    with pytest.raises(RecordingError, match=r"^ex\.csv: column t: the time stamps look like milliseconds"):
        check_recording(T * 1e3, Q, QD, TAU, "ex.csv")
    with pytest.raises(RecordingError, match=r"^ex\.csv: column tau6: the torque is constant \(0.25\) while joint 6 moves"):
        check_recording(T, Q, QD, held, "ex.csv")


def test_the_units_check_reads_motion_not_an_encoders_jitter() -> None:
    """Issue 33: an arm that holds still (its positions jitter by one encoder count, qd = 0),
    or moves one joint while the others hold, is no evidence of wrong time units; the same
    motion with t in milliseconds still is."""
    from armid.identify.errors import RecordingError
    from armid.identify.plausibility import check_recording, velocity_ratio

    rng = np.random.default_rng(3)
    t = np.arange(5000) * 0.001  # 1 kHz
    count = 2 * np.pi / (4096 * 100)
    rest = np.array([0.1, 0.7, -0.7, 0.2, 0.3, -0.1])
    jitter = rest + count * rng.integers(-1, 2, (t.size, 6))
    tau = np.tile([1.0, 20.0, 5.0, 0.5, 0.3, 0.1], (t.size, 1)) + 0.01 * rng.standard_normal((t.size, 6))
    drift = 1e-4 * rng.standard_normal((t.size, 6))  # a drive's velocity reading at rest: noise, not 0
    assert velocity_ratio(t, jitter, drift) is None
    assert not [w for w in check_recording(t, jitter, drift, tau, "still.csv") if "dq/dt" in w]
    one = jitter.copy()  # joint 2 moves slowly (0.05 rad/s rms), the others hold with their jitter
    one[:, 1] = np.round((0.7 + 0.05 * np.sin(1.3 * t) / 1.3) / count) * count
    qd = drift.copy()
    qd[:, 1] = 0.05 * np.cos(1.3 * t)
    assert velocity_ratio(t, one, qd) == pytest.approx(1.0, abs=0.05)
    assert not [w for w in check_recording(t, one, qd, tau, "one.csv") if "dq/dt" in w]
    with pytest.raises(RecordingError, match=r"^one\.csv: column t: the time stamps look like milliseconds"):
        check_recording(t * 1e3, one, qd, tau, "one.csv")


def test_the_units_check_reads_no_motion_across_a_gap() -> None:
    """Issue 33: a recording with stretches of records missing (the estimator service's copy
    of a run it fell behind on keeps a fifth of it in short stretches) has the right units; the
    velocities at a gap's two ends say nothing of the travel across it. Read across its gaps,
    this one came out at 0.4 and was warned of."""
    from armid.identify.plausibility import check_recording, velocity_ratio

    t = np.arange(20000) * 0.002  # 500 Hz, 40 s
    w = np.array([0.6, 0.9, 1.3, 1.7, 2.3, 2.9])
    q = np.sin(np.outer(t, w)) / w
    qd = np.cos(np.outer(t, w))
    tau = 5.0 * qd
    kept = (np.arange(t.size) % 625) < 125  # 125 of every 625 records: gaps of 1 s
    assert velocity_ratio(t[kept], q[kept], qd[kept]) == pytest.approx(1.0, abs=0.01)
    assert not [w for w in check_recording(t[kept], q[kept], qd[kept], tau[kept], "kept.mcap") if "dq/dt" in w]
    assert velocity_ratio(t[kept] * 1e3, q[kept], qd[kept]) == pytest.approx(1e-3, rel=0.01)


def test_the_scale_check_leaves_a_joint_whose_modeled_torque_is_near_zero() -> None:
    """Issue 33: a held wrist whose modeled torque barely varies (a light CAD wrist) measures
    many times it: no unit can be read from that; a large joint in mN*m still is said."""
    from armid.identify.plausibility import check_against_model

    rng = np.random.default_rng(4)
    s = np.sin(np.linspace(0, 20, 4000))
    modeled = np.column_stack([30.0 * s, 10.0 * s, 0.02 * s])
    measured = modeled * [1.0, 1.0, 16.7] + 0.01 * rng.standard_normal(modeled.shape)
    assert check_against_model(measured, modeled, "wrist.csv") == []
    measured[:, 1] *= 1000.0  # joint 2 in mN*m
    said = check_against_model(measured, modeled, "wrist.csv")
    assert len(said) == 1 and said[0].startswith("wrist.csv: column tau2: joint 2 measures 1e+03 times"), said


def test_the_sign_check_leaves_a_joint_whose_modeled_torque_is_near_zero() -> None:
    """Issue 33: a blind case's light wrist (modeled torque 0.2 % of the base's, 0.02 N*m)
    correlated -0.99 with the model through a CAD first moment of the other sign, and was warned
    of as a flipped sensor; a joint whose modeled torque is a tenth of the base's, flipped,
    still is said."""
    from armid.identify.plausibility import check_against_model

    rng = np.random.default_rng(5)
    s = np.sin(np.linspace(0, 20, 4000))
    modeled = np.column_stack([30.0 * s, 3.0 * s, 0.066 * s])
    measured = modeled * [1.0, 1.0, -1.0] + 0.001 * rng.standard_normal(modeled.shape)
    assert check_against_model(measured, modeled, "wrist.csv") == []
    measured[:, 1] *= -1.0  # joint 2's sensor flipped
    said = check_against_model(measured, modeled, "wrist.csv")
    assert len(said) == 1 and said[0].startswith("wrist.csv: column tau2: joint 2's torque runs opposite"), said


def test_the_scale_check_leaves_a_held_joint() -> None:
    """Issue 33: in a single-link experiment a held joint's varying torque is its servo holding
    it against the moving link's pull, through a rotor inertia the rigid body lacks (the demo's
    joint 3, held while joint 4 moved, measured 12 times its modeled torque): no unit can be
    read from that. The same joint moving, many times its modeled torque, still is said."""
    from armid.identify.plausibility import check_against_model, moving_joints

    t = np.linspace(0, 20, 4000)
    q = np.column_stack([np.zeros_like(t), 0.5 * np.sin(t), 0.003 * np.sin(3 * t)])  # joint 3 held within 3 mrad
    modeled = np.column_stack([np.zeros_like(t), 3.0 * np.sin(t), 0.5 * np.sin(3 * t)])
    measured = modeled * [1.0, 1.0, 12.1]
    assert list(moving_joints(q)) == [False, True, False]
    assert check_against_model(measured, modeled, "link4.csv", moving_joints(q)) == []
    said = check_against_model(measured, modeled, "link4.csv", [True, True, True])
    assert len(said) == 1 and said[0].startswith("link4.csv: column tau3: joint 3 measures 12.1 times"), said


@pytest.mark.parametrize("path", sorted((ROOT / "config" / "robots").glob("*.yaml")) + sorted((ROOT / "config" / "robots").glob("*.urdf"))
                         + sorted((ROOT / "config" / "rigs").glob("*.yaml")), ids=lambda p: p.name)
def test_shipped_robots_and_rigs_load_without_a_warning(path: Path) -> None:
    """Issue 36: `armid demo` prints no warning on a quiet run, and no shipped file is the reason
    a lab's command warns: every robot is a rigid body (the PUMA's published link 3 is not, and
    its robot file says what it changed)."""
    from armid.cli import load_robot_argument
    from armid.io.rig_file import load_rig

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_rig(path) if path.parent.name == "rigs" else load_robot_argument(str(path))

"""The bad-input campaign's cases of issue 66, each fixed at its cause: exit 2 with one line
naming the input and the problem, or accepted with a note that is true; never an internal error.

Each case breaks one thing of a shipped example (the PUMA 560 recording and its robot file,
the simulated rig) and runs the command as a user would (``armid.cli.main`` in this process,
or the service and the payload estimator on a real Zenoh session on loopback, multicast
scouting off; ``armid record`` on the simulated arm over a real virtual CAN bus)."""

from __future__ import annotations

import os
import re
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from cli_runs import record_with, run

from armid.cli import main
from armid.io.ros2_cdr import ros2_messages
from armid.schema import Sample
from armid.schema.joint_state import EXTRA_TOPIC, EXTRA_TYPE, JOINT_STATE_TYPE, JOINT_STATES_TOPIC, ROS2_MSGDEFS, JointStateRecord

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "puma560_excitation.csv"
PUMA = ROOT / "config" / "robots" / "puma560.yaml"
RIG = ROOT / "config" / "rigs" / "sim.yaml"
ROWS = 600
HEADER = EXAMPLE.read_text().splitlines()[0].split(",")
DATA = np.loadtxt(EXAMPLE, delimiter=",", skiprows=1, max_rows=ROWS)
T, Q, QD, TAU = DATA[:, 0], DATA[:, 1:7], DATA[:, 7:13], DATA[:, 13:19]
KT = np.array([j["torque_constant"] for j in yaml.safe_load(PUMA.read_text())["joints"]])


def assert_clean_error(code: int, err: str, expect: str) -> None:
    """Exit 2, one ``error:`` line (the last on stderr) matching ``expect``, no traceback, no internal error."""
    assert "Traceback" not in err and "internal error" not in err, err
    assert code == 2, f"exit {code}, stderr:\n{err}"
    last = err.strip().splitlines()[-1]
    assert ": error: " in last and re.search(expect, last), f"{last!r} does not say {expect!r}"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _records(first: int = 0, change: Callable[[list[JointStateRecord]], None] | None = None) -> list[JointStateRecord]:
    """The example's rows as ``armid record`` acquires them, numbered from ``first``."""
    out = []
    for k in range(ROWS):
        current = TAU[k] / KT
        out.append(JointStateRecord(first + k, Sample(k, float(T[k]), np.ones(6, bool), Q[k].copy(), QD[k].copy(), np.ones(6, bool), current,
                                                      current.copy(), np.full(6, 0x27), TAU[k].copy())))
    if change is not None:
        change(out)
    return out


def write_mcap(path: Path, records: list[JointStateRecord], topics: tuple[str, ...] = (JOINT_STATES_TOPIC, EXTRA_TOPIC)) -> Path:
    """A ROS 2 recording as ``daq.recorder`` lays it out, in uncompressed 32 KiB chunks (a case
    can break bytes in them); ``topics``: the channels written."""
    from mcap.writer import CompressionType, Writer

    kinds = {JOINT_STATES_TOPIC: JOINT_STATE_TYPE, EXTRA_TOPIC: EXTRA_TYPE}
    names = [f"j{j + 1}" for j in range(6)]
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=32 * 1024, compression=CompressionType.NONE)
        w.start(profile="ros2", library="armid-test")
        channels = {t: w.register_channel(t, "cdr", w.register_schema(kinds[t], "ros2msg", ROS2_MSGDEFS[kinds[t]].encode())) for t in topics}
        w.add_metadata("armid.run", {"robot": "puma560"})
        for r in records:
            ns = int(round(r.sample.time_s * 1e9))
            for topic, data in zip((JOINT_STATES_TOPIC, EXTRA_TOPIC), ros2_messages(r, names)):
                if topic in channels:
                    w.add_message(channels[topic], ns, data, ns, r.sequence)
        w.finish()
    return path


def _chunks(path: Path) -> list[Any]:
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    return sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)


@pytest.fixture(scope="module")
def ident(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ident") / "ident.json"
    assert main(["identify", str(EXAMPLE), "--robot", str(PUMA), "--json", str(out), "--lowpass", "off"]) == 0
    return out


# -- the service drops unusable records as identify does ---------------------------------------

def _with_nan_velocity(records: list[JointStateRecord]) -> None:
    """The drives' velocity carried every other cycle (a PDO plan's), NaN in ten records flagged fresh and valid."""
    for r in records:
        if r.sequence % 2:
            r.sample.velocity_fresh[:] = False
    for r in records[300:310]:
        r.sample.velocity[:] = np.nan
        r.sample.velocity_fresh[:] = True


def test_ten_nan_records_are_left_out_by_identify_and_by_the_service_alike(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The service answered "not identified: ValueError: `y` must contain only finite values"
    (the drives' velocity interpolated through NaN); now one judgement of a usable record
    (:meth:`JointStates.unusable`) serves both: the ten records are left out and said."""
    import zenoh

    from armid.daq.experiment_stream import CollectedExperiment
    from armid.daq.stream import session_config
    from armid.io.robot_file import load_robot
    from armid.schema.joint_states import JointStates
    from armid.serve import EstimatorService

    records = _records(0, _with_nan_velocity)
    code, err = run(["identify", str(write_mcap(tmp_path / "nan.mcap", records)), "--robot", str(PUMA)], capsys)
    assert code == 0 and "left out 10 unusable records (10 velocity not finite)" in err, err
    said: list[str] = []
    session = zenoh.open(session_config(listen=[f"tcp/127.0.0.1:{_free_port()}"]))
    service = EstimatorService(session, load_robot(PUMA), tmp_path / "serve", log=said.append)
    try:
        states = JointStates.concat([JointStates.unpack(JointStates.of_sample(r.sequence, r.sample).pack()) for r in records])
        experiment = {"kind": "whole_arm", "metadata": {"period_s": 0.002}}
        service.process(CollectedExperiment("nan", {"experiment": experiment}, {"completed": True, "experiment": experiment},
                                            states, 0, [[0, ROWS - 1]]))
    finally:
        service.close()
        session.close()
    assert "note" not in service.experiments[-1] and "nan" in service.whole_fits, service.experiments[-1]
    assert "nan: left out 10 unusable records (10 velocity not finite)" in said, said


# -- MCAP ----------------------------------------------------------------------------------------

def test_a_chunk_without_a_crc_is_read_and_said_unverified(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A digit flipped in a chunk whose CRC is 0 ("not computed") was fitted without a word."""
    path = write_mcap(tmp_path / "nocrc.mcap", _records())
    chunk = _chunks(path)[1]
    data = bytearray(path.read_bytes())
    at = chunk.chunk_start_offset
    data[at + 9 + 24 : at + 9 + 28] = b"\0\0\0\0"  # the chunk's uncompressed_crc field
    data[at + chunk.chunk_length // 2] ^= 0x01
    path.write_bytes(bytes(data))
    code, err = run(["identify", str(path), "--robot", str(PUMA)], capsys)
    assert code == 0 and f"nocrc.mcap: chunk at offset {at} has no CRC: not verified" in err, err


def test_estimate_replay_names_milliseconds_as_identify_does(tmp_path: Path, ident: Path, capsys: pytest.CaptureFixture[str]) -> None:
    def stamped_in_ms(records: list[JointStateRecord]) -> None:
        for r in records:
            r.sample.time_s = 2.0 * r.sequence  # 2 ms cycles stamped as if milliseconds were seconds
    path = write_mcap(tmp_path / "ms.mcap", _records(0, stamped_in_ms))
    code, err = run(["estimate", "--robot", str(PUMA), "--params", str(ident), "--replay", str(path), "--out", str(tmp_path / "e.jsonl")], capsys)
    assert_clean_error(code, err, r"ms\.mcap: column t: the time stamps look like milliseconds")
    code, err = run(["identify", str(path), "--robot", str(PUMA)], capsys)
    assert_clean_error(code, err, r"ms\.mcap: column t: the time stamps look like milliseconds")


def _all_nan(records: list[JointStateRecord]) -> None:
    for r in records:
        for field in ("position", "velocity", "torque", "commanded_current", "measured_current"):
            setattr(r.sample, field, np.full(6, np.nan))


@pytest.mark.parametrize("case", ["csv line of megabytes", "every CDR value NaN", "no extra channel"])
def test_no_internal_error_from_any_input(case: str, tmp_path: Path, ident: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Three inputs that ended in "internal error", exit 1, in every command that reads them."""
    if case == "csv line of megabytes":
        bad = tmp_path / "long.csv"
        bad.write_text(",".join(HEADER) + "\n" + "1" * 5_000_000 + "\n" + "\n".join(",".join(map(str, r)) for r in DATA.tolist()) + "\n")
        expect = r"long\.csv: line 2: not a CSV row \(field larger than field limit"
    elif case == "every CDR value NaN":
        bad = write_mcap(tmp_path / "nan.mcap", _records(0, _all_nan))
        expect = r"nan\.mcap: only 0 usable records of 600 \(.*600 position not finite"
    else:
        bad = write_mcap(tmp_path / "noextra.mcap", _records(), topics=(JOINT_STATES_TOPIC,))
        expect = r"noextra\.mcap: .*600 /joint_states messages but no /armid/joint_state_extra channel"
    estimate = ["estimate", "--robot", str(PUMA), "--params", str(ident), "--out", str(tmp_path / "e.jsonl")]
    for argv in (["identify", str(bad), "--robot", str(PUMA)], ["check", str(bad), "--model", str(ident), "--robot", str(PUMA)],
                 ["diagnose", str(EXAMPLE), "--validate", str(bad), "--robot", str(PUMA)],
                 [*estimate, "--replay", str(bad)], [*estimate, "--replay", str(EXAMPLE), "--reference", str(bad)]):
        code, err = run(argv, capsys)
        assert "internal error" not in err, (argv, err)
        if case == "every CDR value NaN" and argv[0] in ("identify", "check", "diagnose"):
            expect_here = r"nan\.mcap: only 0 usable"
        else:
            expect_here = expect
        assert_clean_error(code, err, expect_here)


# -- robot files -----------------------------------------------------------------------------------

@pytest.mark.parametrize("what", ["/dev/zero", "a URDF that is /dev/zero", "a pipe", "a robot file whose urdf is /dev/zero", "a folder"])
def test_a_robot_path_that_is_not_a_regular_file_is_refused_before_it_is_read(what: str, tmp_path: Path,
                                                                             capsys: pytest.CaptureFixture[str]) -> None:
    """``--robot /dev/zero`` read without bound (2-4 GB) and printed an empty reason."""
    if what == "/dev/zero":
        robot, expect = "/dev/zero", r"/dev/zero: a device, not a regular file"
    elif what == "a URDF that is /dev/zero":
        (tmp_path / "zero.urdf").symlink_to("/dev/zero")
        robot, expect = str(tmp_path / "zero.urdf"), r"zero\.urdf: urdf: .*zero\.urdf is a device, not a regular file"
    elif what == "a pipe":
        os.mkfifo(tmp_path / "robot.yaml")
        robot, expect = str(tmp_path / "robot.yaml"), r"robot\.yaml: a pipe, not a regular file"
    elif what == "a folder":
        robot, expect = str(tmp_path), r": a directory, not a regular file"
    else:
        (tmp_path / "arm.yaml").write_text("name: arm\nurdf: /dev/zero\njoints: [{name: a}]\n")
        robot, expect = str(tmp_path / "arm.yaml"), r"arm\.yaml: urdf: /dev/zero is a device, not a regular file"
    assert_clean_error(*run(["identify", str(EXAMPLE), "--robot", robot], capsys), expect)


def test_a_robot_file_beyond_the_size_limit_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from armid.io.robot_file import ROBOT_FILE_LIMIT_BYTES

    big = tmp_path / "big.yaml"
    with open(big, "wb") as f:
        f.truncate(ROBOT_FILE_LIMIT_BYTES + 1)
    assert_clean_error(*run(["identify", str(EXAMPLE), "--robot", str(big)], capsys), r"big\.yaml: \d+ MiB, larger than any robot description")


# -- notes that are true ---------------------------------------------------------------------------

def test_a_recording_that_starts_at_sequence_47_lost_nothing_before_it(tmp_path: Path) -> None:
    """Its first chunk corrupt: the records lost are the chunk's (counted by its own span),
    numbered from 47, not "47 records (sequence 0..46) lost"."""
    from armid.io.recordings import read_mcap_arrays

    path = write_mcap(tmp_path / "s47.mcap", _records(47))
    first = _chunks(path)[0]
    data = bytearray(path.read_bytes())
    mid = first.chunk_start_offset + first.chunk_length // 2
    data[mid : mid + 4] = bytes(b ^ 0xFF for b in data[mid : mid + 4])
    path.write_bytes(bytes(data))
    arrays, _, notes = read_mcap_arrays(path)
    kept = int(arrays["sequence"][0])
    said = [n for n in notes if "fails its CRC" in n]
    assert len(said) == 1 and f"{kept - 47} records (" in said[0] and f"sequence 47..{kept - 1}," in said[0], notes


def test_numbers_that_repeat_are_no_negative_count_of_missing_records(tmp_path: Path) -> None:
    from armid.io.recordings import read_mcap_arrays

    def back(records: list[JointStateRecord]) -> None:
        for r in records[300:]:
            r.sequence -= 5
    _, _, notes = read_mcap_arrays(write_mcap(tmp_path / "dup.mcap", _records(0, back)))
    assert not any(re.search(r"-\d+ records", n) for n in notes), notes
    assert any("numbered no higher than the record before (first: sequence 295 after 299)" in n for n in notes), notes


def test_no_noise_ratio_over_a_zero_denominator() -> None:
    """Four of six joints held still (their positions constant: no noise at all above the
    cut-off), the recorded velocities noisy: said as noisier, not "3.85e+298x noisier"."""
    from armid.identify.preprocess import PrepareOptions, prepare
    from armid.identify.recordings import Recording
    from armid.io.robot_file import load_robot

    rng = np.random.default_rng(0)
    t = np.arange(4000) * 0.002
    q = np.tile(Q[0], (t.size, 1))
    qd = 0.01 * rng.standard_normal(q.shape)
    for j in (0, 1):
        q[:, j] += 0.5 * np.sin(2 * np.pi * 0.3 * t)
        qd[:, j] += 0.5 * 2 * np.pi * 0.3 * np.cos(2 * np.pi * 0.3 * t)
    tau = np.tile(TAU[0], (t.size, 1)) + 0.01 * rng.standard_normal(q.shape)
    prep = prepare(Recording("still.csv", t, q, tau, qd), load_robot(PUMA), PrepareOptions(lowpass_hz=5.0))
    said = [n for n in prep.notes if n.startswith("velocity from positions")]
    assert said and not re.search(r"e\+\d\dx", said[0]) and "carries no noise" in said[0], prep.notes


# -- the drives ------------------------------------------------------------------------------------

def test_a_faulted_run_marks_its_records_after_the_fault_invalid(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """"their records after that are not valid" was said and none was marked."""
    import can

    emcy = can.Message(arbitration_id=0x80 + 2, data=struct.pack("<HB5s", 0x2310, 0x01, b"\0" * 5), is_extended_id=False)
    code, err, arrays = record_with(lambda bus: bus.send(emcy), tmp_path, capsys)
    assert code == 1 and "the run faulted joint 2: their records after that are marked invalid" in err, err
    valid = arrays["valid"]
    first = int(np.flatnonzero(~valid[:, 1])[0])
    assert first > 0 and not valid[first:, 1].any() and valid[:, [0, 2, 3, 4, 5]].all()


def test_a_flood_of_foreign_sync_frames_is_named_a_second_sync_producer(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Every drive faulted and nothing named the cause."""
    import can

    def flood(bus: Any) -> None:
        for k in range(2000):
            bus.send(can.Message(arbitration_id=0x80, data=[k % 240 + 1], is_extended_id=False))
    code, err, _ = record_with(flood, tmp_path, capsys)
    assert "a second SYNC producer on the bus: a SYNC frame (COB-ID 0x080, counter 1) that this master did not send" in err, err
    faults = [line for line in err.splitlines() if ": fault 0x" in line]
    assert code == 1 and faults and all("a second SYNC producer on the bus (" in line for line in faults), err


# -- what was not used, said where the operator looks --------------------------------------------

def test_the_payload_estimator_says_its_drops_and_counts_another_encoding(ident: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Puts of another encoding were ignored uncounted, and nothing of the drops reached
    ``armid estimate live``'s stderr; ``armid serve``'s summary omitted its unreadable puts."""
    import zenoh

    from armid.daq.stream import Stream, key, session_config
    from armid.schema.joint_states import JointStates

    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    box: dict[str, int] = {}
    argv = ["estimate", "live", "--robot", str(PUMA), "--params", str(ident), "--duration", "6", "--zenoh-listen", endpoint, "--out", os.devnull]
    estimator = threading.Thread(target=lambda: box.setdefault("estimate", main(argv)))
    estimator.start()
    time.sleep(1.0)
    serve = subprocess.Popen([sys.executable, "-m", "armid.cli", "serve", "--robot", str(PUMA), "--duration", "8", "--no-payload",
                              "--zenoh-connect", endpoint], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, stderr=subprocess.PIPE, text=True)
    with zenoh.open(session_config(connect=[endpoint])) as session:
        for _ in range(300):  # both subscribers declared: the service says so
            if any(str(r.ok.key_expr).endswith("alive/estimator") for r in session.liveliness().get(key("puma560", "alive/**"), timeout=1.0) if r.ok):
                break
            time.sleep(0.1)
        time.sleep(0.5)
        stream = Stream(session, "puma560", "recorder", lambda: {})
        other = session.declare_publisher(key("puma560", "joint_state"), encoding=zenoh.Encoding("application/octet-stream;armid.JointState/1"))
        records = [JointStates.of_sample(r.sequence, r.sample) for r in _records()]
        records[100].position[0, 2] = np.nan
        for r in records[:200]:
            stream.publish(r)
        for r in records[200:203]:
            other.put(r.pack())
        time.sleep(0.5)
        other.undeclare()
        stream.close()
    estimator.join(60)
    served = serve.communicate(timeout=120)[1]
    err = capsys.readouterr().err + served
    assert box == {"estimate": 0} and serve.returncode == 0, err
    assert "armid estimate: dropped a record (not finite): record 100: position not finite (NaN or infinite); further ones counted" in err, err
    assert re.search(r"armid estimate: dropped a record \(encoding\): a put refused: .*armid\.JointState/1", err), err
    [summary] = [line for line in err.splitlines() if re.match(r"armid estimate: \d+ estimates published; not used: ", line)]
    assert re.search(r"dropped (1 not finite, 3 encoding|3 encoding, 1 not finite) \(last: ", summary), summary
    assert re.search(r"armid serve: 200 records received, 0 skipped, 0 lost, 3 unreadable \(last: .*JointState/1", err), err


def test_robot_dev_zero_end_to_end_in_a_process_of_its_own() -> None:
    """As a user runs it: one line, exit 2, at once (it read 2-4 GB before)."""
    proc = subprocess.run([sys.executable, "-m", "armid.cli", "identify", str(EXAMPLE), "--robot", "/dev/zero"], capture_output=True,
                          text=True, timeout=60, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert_clean_error(proc.returncode, proc.stderr, r"/dev/zero: a device, not a regular file")

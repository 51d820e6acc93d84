"""Recordings the ROS 2 world opens (issue 21): what the simulated arm's driver acquired is
recorded as ``sensor_msgs/msg/JointState`` plus armid's extra channel in ROS 2 CDR, and the
``mcap`` library's ROS 2 decoder (``mcap-ros2-support``, no ROS installed) reads every
message back equal to what was acquired; armid's own reader gives the same arrays."""

from __future__ import annotations

import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from armid.daq.acquisition import Acquisition, Sink
from armid.daq.recorder import McapRecorder
from armid.io.recordings import read_mcap_arrays
from armid.io.rig_file import load_rig
from armid.resources import config_file
from armid.schema.joint_state import EXTRA_TOPIC, EXTRA_TYPE, JOINT_STATE_TYPE, JOINT_STATES_TOPIC, JointStateRecord
from armid.schema.joint_states import JointStates
from armid.simulated import simulated_driver


@pytest.fixture(scope="module")
def acquired(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[JointStateRecord], Path]:
    rig = load_rig(config_file("rigs/sim.yaml")).with_bus(channel=f"armid-ros2-{uuid.uuid4().hex[:8]}")
    path = tmp_path_factory.mktemp("ros2") / "run.mcap"
    recorder = McapRecorder(path, [j.name for j in rig.robot.joints], {"robot": rig.robot.name, "rig": rig.name})
    kept: list[JointStates] = []
    driver, sim = simulated_driver(rig)
    try:
        driver.start()
        acq = Acquisition(driver, [Sink("recorder", recorder.write, bounded=False), Sink("keep", kept.append, bounded=False)])
        acq.start()
        deadline = time.monotonic() + 60
        while acq.sequence < 1500 and time.monotonic() < deadline and not acq.error:
            time.sleep(0.05)
        acq.stop()
    finally:
        driver.close()
        sim.close()
        recorder.close()
    rows = [part.record(k) for part in kept for k in range(len(part))]  # one cycle at a time, as the ROS 2 writer takes them
    assert len(rows) >= 1500
    return rows, path


def test_the_ros2_decoder_reads_every_message_back_equal(acquired: tuple[list[JointStateRecord], Path]) -> None:
    from mcap_ros2.reader import read_ros2_messages

    kept, path = acquired
    states, extras = {}, {}
    for m in read_ros2_messages(str(path)):
        assert m.channel.message_encoding == "cdr" and m.schema is not None and m.schema.encoding == "ros2msg"
        if m.channel.topic == JOINT_STATES_TOPIC:
            assert m.schema.name == JOINT_STATE_TYPE
            states[(m.log_time_ns, m.sequence_count)] = m.ros_msg
        else:
            assert m.channel.topic == EXTRA_TOPIC and m.schema.name == EXTRA_TYPE
            extras[(m.log_time_ns, m.sequence_count)] = m.ros_msg
    assert len(states) == len(extras) == len(kept)
    by_sequence = {int(e.sequence): (states[k], e) for k, e in extras.items()}
    for r in kept:
        s = r.sample
        state, extra = by_sequence[r.sequence]
        ns = int(round(s.time_s * 1e9))
        assert state.header.stamp.sec * 1_000_000_000 + state.header.stamp.nanosec == ns
        assert list(state.position) == s.position.tolist() and list(state.velocity) == s.velocity.tolist()
        assert s.torque is not None and list(state.effort) == s.torque.tolist()  # the driver's torque, applied once
        assert int(extra.cycle) == s.cycle and list(extra.valid) == s.valid.tolist()
        assert list(extra.velocity_fresh) == s.velocity_fresh.tolist()
        assert list(extra.commanded_current) == s.commanded_current.tolist()
        assert list(extra.measured_current) == s.measured_current.tolist()
        assert list(extra.statusword) == s.status.tolist()


def test_chunks_are_zstd_and_the_run_metadata_is_there(acquired: tuple[list[JointStateRecord], Path]) -> None:
    from mcap.reader import make_reader

    _, path = acquired
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.chunk_indexes
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert meta["armid.run"]["robot"] == "puma560"


def test_armids_reader_gives_what_was_acquired(acquired: tuple[list[JointStateRecord], Path]) -> None:
    kept, path = acquired
    arrays, metadata, notes = read_mcap_arrays(path)
    assert notes == [] and metadata["robot"] == "puma560"
    assert np.array_equal(arrays["sequence"], [r.sequence for r in kept])
    for name, attr in (("position", "position"), ("velocity", "velocity"), ("measured_current", "measured_current"),
                       ("commanded_current", "commanded_current"), ("torque", "torque"), ("valid", "valid"), ("status", "status")):
        assert np.array_equal(arrays[name], np.array([getattr(r.sample, attr) for r in kept])), name


def test_the_cdr_bytes_are_what_a_ros2_serializer_writes() -> None:
    """The CDR armid writes (``rosbags``' typestore) against the other library's serializer (``mcap_ros2``)."""
    from mcap_ros2._dynamic import serialize_dynamic

    from armid.io.ros2_cdr import ros2_messages
    from armid.schema import Sample
    from armid.schema.joint_state import ROS2_MSGDEFS

    encode = {kind: serialize_dynamic(kind, text)[kind] for kind, text in ROS2_MSGDEFS.items()}
    rng = np.random.default_rng(0)
    for n in (1, 2, 6, 7):
        names = [f"joint_{'x' * k}" for k in range(n)]
        for k in range(20):
            s = Sample(k, 1.234 + 0.002 * k, rng.random(n) > 0.3, rng.normal(size=n), rng.normal(size=n), rng.random(n) > 0.5,
                       rng.normal(size=n), rng.normal(size=n), rng.integers(0, 65536, n), rng.normal(size=n))
            r = JointStateRecord(k * 1_000_003, s)
            ns = int(round(s.time_s * 1e9))
            header = {"stamp": {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}, "frame_id": ""}
            state = encode[JOINT_STATE_TYPE]({"header": header, "name": names, "position": s.position.tolist(),
                                              "velocity": s.velocity.tolist(), "effort": s.joint_torque().tolist()})
            extra = encode[EXTRA_TYPE]({"header": header, "sequence": r.sequence, "cycle": s.cycle, "valid": s.valid.tolist(),
                                        "velocity_fresh": s.velocity_fresh.tolist(), "commanded_current": s.commanded_current.tolist(),
                                        "measured_current": s.measured_current.tolist(), "statusword": s.status.tolist()})
            assert ros2_messages(r, names) == (bytes(state), bytes(extra))


def test_the_columns_read_in_place_are_what_a_ros2_decoder_reads_and_other_layouts_are_left_to_it() -> None:
    """The recording reader's fast path (``ros2_columns``: every message of a kind read as one
    array) against mcap_ros2's generic decoder, message by message; a batch whose layouts
    differ (another joint name, another joint count, a byte of padding) is not read in place."""
    from mcap.records import Schema
    from mcap_ros2.decoder import DecoderFactory

    from armid.io.ros2_cdr import ros2_columns, ros2_messages
    from armid.schema import Sample
    from armid.schema.joint_state import ROS2_MSGDEFS

    factory = DecoderFactory()
    decode = {kind: factory.decoder_for("cdr", Schema(id=k, name=kind, encoding="ros2msg", data=text.encode()))
              for k, (kind, text) in enumerate(ROS2_MSGDEFS.items(), 1)}
    rng = np.random.default_rng(1)
    for n in (1, 6, 7):
        names = [f"joint_{'x' * k}" for k in range(n)]
        pairs = []
        for k in range(30):
            s = Sample(k, 1.5 + 0.002 * k, rng.random(n) > 0.3, rng.normal(size=n), rng.normal(size=n), rng.random(n) > 0.5,
                       rng.normal(size=n), rng.normal(size=n), rng.integers(0, 65536, n), rng.normal(size=n))
            pairs.append(ros2_messages(JointStateRecord(k * 1_000_003, s), names))
        for kind, msgs in ((JOINT_STATE_TYPE, [p[0] for p in pairs]), (EXTRA_TYPE, [p[1] for p in pairs])):
            cols = ros2_columns(msgs, kind)
            assert cols is not None
            for k, m in enumerate(msgs):
                d = decode[kind](m)
                assert cols["sec"][k, 0] == d.header.stamp.sec and cols["nanosec"][k, 0] == d.header.stamp.nanosec
                fields = ("position", "velocity", "effort") if kind == JOINT_STATE_TYPE else (
                    "sequence", "cycle", "valid", "velocity_fresh", "commanded_current", "measured_current", "statusword")
                for name in fields:
                    assert np.array_equal(cols[name][k], np.atleast_1d(np.asarray(getattr(d, name), cols[name].dtype))), (kind, name, k)
        states = [p[0] for p in pairs]
        other_name = ros2_messages(JointStateRecord(99, Sample(99, 9.0, *(np.ones(n, bool), np.zeros(n), np.zeros(n), np.ones(n, bool),
                                                                           np.zeros(n), np.zeros(n), np.zeros(n, np.int64)), torque=np.zeros(n))),
                                   [("y" if k == 0 else "") + name for k, name in enumerate(names)])[0]
        assert ros2_columns(states + [other_name], JOINT_STATE_TYPE) is None  # same length or not, another name
        value = states[0][:-1] + b"\x00"  # the last byte is a value's (the last effort's): still read in place
        assert ros2_columns(states[:3] + [value], JOINT_STATE_TYPE) is not None
        frame = bytearray(states[0])
        frame[16] = 0x41  # frame_id's one byte (the terminating zero): structure
        assert ros2_columns(states[:3] + [bytes(frame)], JOINT_STATE_TYPE) is None
        assert ros2_columns(states[:3] + [states[0] + b"\x00"], JOINT_STATE_TYPE) is None  # another length
    assert ros2_columns([b"\x00\x01\x00\x00\x01"], JOINT_STATE_TYPE) is None  # cut short: not this type


def test_a_stamp_ros2_time_cannot_hold_is_named_not_a_struct_error() -> None:
    """Issue 35: a run stamped after 2038 failed in ``struct`` (int32 seconds) where the service
    writes its copy; ROS 2's Time cannot hold it, and the error says so and names the record."""
    import numpy as np
    import pytest

    from armid.io.ros2_cdr import ros2_messages
    from armid.schema.errors import RecordFormatError
    from armid.schema.joint_state import JointStateRecord, Sample

    z = np.zeros(6)

    def record(t: float) -> JointStateRecord:
        return JointStateRecord(7, Sample(7, t, np.ones(6, bool), z, z, np.ones(6, bool), z, z, np.zeros(6, np.int64), torque=z))

    names = [f"j{k}" for k in range(6)]
    assert ros2_messages(record(2.0e9), names)[0]  # 2033: fine
    for t in (2.2e9, float("nan")):
        with pytest.raises(RecordFormatError, match=r"record 7: time stamp .* cannot be written in a ROS 2 recording .*2038-01-19"):
            ros2_messages(record(t), names)

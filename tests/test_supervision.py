"""Supervision that speaks: what a drive does on the bus reaches ``armid record``'s output,
named by node and joint, and a recording that lost a drive ends non-zero (issue 35).

Each case runs ``armid record`` on the simulated arm (a real virtual CAN bus, real CiA 402
nodes) and puts frames on the same bus from a third handle, as another device would.
"""

from __future__ import annotations

import struct
import time
import uuid
from pathlib import Path

import can
import numpy as np
import pytest
from cli_runs import record_with

from armid.daq.supervision import Supervision
from armid.drivers.interface import DriveFault, Event, HeartbeatLost
from armid.schema.joint_states import JointStates

ROOT = Path(__file__).resolve().parent.parent
RIG = ROOT / "config" / "rigs" / "sim.yaml"
DURATION_S = 3.0


def _emcy(node: int, code: int, register: int = 0x01, data: bytes = b"\0" * 5) -> can.Message:
    return can.Message(arbitration_id=0x80 + node, data=struct.pack("<HB5s", code, register, data), is_extended_id=False)


def test_an_emcy_storm_is_said_once_with_its_count_and_the_run_ends_non_zero(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    def inject(bus: can.BusABC) -> None:
        for _ in range(2000):
            bus.send(_emcy(2, 0x2310))
        bus.send(_emcy(5, 0xDEAD))
        for _ in range(20):
            bus.send(can.Message(arbitration_id=0x80 + 3, data=[0x10], is_extended_id=False))

    code, err, arrays = record_with(inject, tmp_path, capsys, DURATION_S)
    assert code == 1, err
    assert err.count("joint 2 (node 2): fault 0x2310: continuous over-current") == 2, err  # as it came, and in the sum-up
    assert "(2,000 times)" in err
    assert "joint 5 (node 5): fault 0xDEAD" in err
    assert "joint 3 (node 3): EMCY (COB-ID 0x083) has 1 bytes, CiA 301 says 8" in err
    assert "unpack requires" not in err
    assert "the run faulted joints 2, 5" in err
    assert np.all(np.diff(arrays["sequence"]) == 1)  # the recording lost nothing for it


def test_a_drive_stopped_by_nmt_is_named_and_the_others_record_on(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, err, arrays = record_with(lambda bus: bus.send(can.Message(arbitration_id=0, data=[0x02, 4], is_extended_id=False)),
                                    tmp_path, capsys, DURATION_S)
    assert code == 1, err
    assert "joint 4 (node 4): stopped by an NMT command" in err
    assert "the run lost joint 4" in err
    valid = arrays["valid"]
    n = len(arrays["sequence"])
    assert n >= 0.95 * DURATION_S / 0.002  # the cycles do not wait for a drive that sends nothing
    assert valid[:, [0, 1, 2, 4, 5]].all(), "the other joints lost records"
    assert not valid[-100:, 3].any()


def test_a_reset_of_every_node_loses_every_drive_at_once(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, err, arrays = record_with(lambda bus: bus.send(can.Message(arbitration_id=0, data=[0x81, 0], is_extended_id=False)),
                                    tmp_path, capsys, DURATION_S)
    assert code == 1, err
    for j in range(1, 7):
        assert f"joint {j} (node {j}): reset: its boot-up message came" in err
    assert "the run lost joints 1, 2, 3, 4, 5, 6" in err
    assert len(arrays["sequence"]) >= 0.95 * DURATION_S / 0.002


def test_frames_of_the_wrong_length_and_error_frames_are_said(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    def inject(bus: can.BusABC) -> None:
        for _ in range(5):
            bus.send(can.Message(arbitration_id=0x180 + 3, data=[1, 2, 3], is_extended_id=False))  # node 3's TPDO1
        for _ in range(25):
            bus.send(can.Message(is_error_frame=True, arbitration_id=0x20000004, data=bytes(8)))

    code, err, _ = record_with(inject, tmp_path, capsys, DURATION_S)
    assert code == 0, err  # nothing was lost: said, not failed
    assert "joint 3 (node 3): TPDO1 (COB-ID 0x183) has 3 bytes, the mapping has" in err
    assert "CAN error frames within 100 ms" in err and "check wiring and termination" in err


def test_supervision_says_each_kind_once_per_drive_and_knows_a_lost_one() -> None:
    said: list[str] = []
    sup = Supervision(said.append)
    for _ in range(3):
        sup.fault(HeartbeatLost(1, 2, 0x8130, "no heartbeat"))
    sup.events([Event("frame_length", "joint 1: bad", 0), Event("frame_length", "joint 1: bad", 0), Event("emcy", "dup", 0)])
    assert said == ["joint 2 (node 2): fault 0x8130: no heartbeat", "joint 1: bad"]
    assert sup.summary() == ["joint 2 (node 2): fault 0x8130: no heartbeat (3 times)", "joint 1: bad (2 times)"]
    assert sup.failed and sup.lost == {1} and "lost joint 2" in sup.verdict()


def test_the_service_says_what_the_drives_said_once_and_counts_it(tmp_path: Path) -> None:
    """``armid serve`` hears a recorder's fault and drive events on the run's Zenoh events
    (real sessions on loopback, sent by the recorder's own Supervision and Stream): each said
    once by type, joint and code, counted in its status."""
    import socket

    import zenoh

    from armid.daq.stream import Stream, session_config
    from armid.io.robot_file import load_robot
    from armid.serve import EstimatorService

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    robot = load_robot(ROOT / "config" / "robots" / "puma560.yaml")
    said: list[str] = []
    session = zenoh.open(session_config(listen=[endpoint]))
    service = EstimatorService(session, robot, tmp_path / "serve", log=said.append)
    other = zenoh.open(session_config(connect=[endpoint]))
    stream = Stream(other, robot.name, "recorder", lambda: {})
    recorder_said: list[str] = []
    supervision = Supervision(recorder_said.append, stream)  # as armid record holds it
    try:
        time.sleep(1.0)  # the subscriber's declaration reaches the publisher
        for _ in range(50):
            supervision.fault(DriveFault(1, 2, 0x2310, "continuous over-current"))
        supervision.events([Event("frame_length", "joint 3: TPDO1 has 3 bytes", 2)])
        for _ in range(100):
            reports = {r["type"]: r for r in service.drive_reports.values()}
            if reports.get("DriveFault", {}).get("count") == 50 and "frame_length" in reports:
                break
            time.sleep(0.05)
        reports = {r["type"]: r for r in service.drive_reports.values()}
        assert reports["DriveFault"]["count"] == 50 and reports["frame_length"]["count"] == 1, reports
        assert said.count("the drives said: joint 2 (node 2): continuous over-current") == 1, said
        assert "the drives said: joint 3: TPDO1 has 3 bytes" in said
    finally:
        stream.close()
        service.close()
        other.close()
        session.close()


def test_a_drive_gone_silent_is_named_lost_while_acquisition_goes_on() -> None:
    """A drive that stops answering (heartbeat and PDOs, as on power loss) while ``armid
    record``'s acquisition runs: the supervision names it lost, by joint and node, once; the
    records go on with that joint invalid. The simulated arm and the driver on a virtual bus."""
    from armid.daq.acquisition import Acquisition, Sink
    from armid.drivers.canopen_driver import CanopenDriver
    from armid.io.rig_file import load_rig
    from armid.sim_bus.arm import SimulatedArm

    channel = f"armid-sup-{uuid.uuid4().hex[:8]}"
    rig = load_rig(RIG).with_bus(channel=channel)
    buses = [can.Bus(interface="virtual", channel=channel) for _ in range(2)]
    arm = SimulatedArm(rig, bus=buses[0])
    driver = CanopenDriver(rig, bus=buses[1])
    driver.pacing = "consumer"
    said: list[str] = []
    supervision = Supervision(said.append)
    records: list = []
    acq = Acquisition(driver, [Sink("list", records.append, bounded=False)], on_fault=supervision.fault)
    try:
        driver.start()
        acq.start()
        while acq.sequence < 200:
            time.sleep(0.01)
        arm.drive(3).go_silent()
        silent_from = acq.sequence
        while acq.sequence < silent_from + 500:
            time.sleep(0.01)
            supervision.events(driver.events())
    finally:
        acq.stop()
        driver.close()
        arm.close()
        for bus in buses:
            bus.shutdown()
    assert supervision.lost == {3}, said
    assert [s for s in said if "joint 4 (node 4)" in s] == [said[0]] and "no heartbeat" in said[0], said
    states = JointStates.concat(records)
    valid = states.valid[states.sequence > silent_from + 100]
    assert valid.size and not valid[:, 3].any() and valid[:, [0, 1, 2, 4, 5]].all()

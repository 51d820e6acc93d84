"""Recording size and fidelity: a 6-axis run on the simulated arm (2 ms), recorded as ROS 2
MCAP (``daq.recorder``) and, for comparison, in the JSON layout armid wrote before (one
uncompressed JSON message per cycle, 32 KiB chunks), from the very same records.

The ROS 2 file is then read back with the ``mcap`` library's ROS 2 decoder
(``mcap_ros2.reader.read_ros2_messages``) and every message compared with what was acquired.

    python benchmarks/bench_recording.py [--seconds 60]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np
from figures_json import recorded

from armid.daq.acquisition import Acquisition, Sink
from armid.daq.recorder import McapRecorder
from armid.io.rig_file import load_rig
from armid.resources import config_file
from armid.schema.joint_state import JOINT_STATES_TOPIC
from armid.schema.joint_states import JointStates
from armid.simulated import simulated_driver


class JsonRecorder:
    """The layout ``armid record`` wrote before the ROS 2 format (kept here to measure against)."""

    def __init__(self, path: Path, names: list[str], kt: np.ndarray, metadata: dict[str, str]) -> None:
        from mcap.writer import CompressionType, Writer

        self._file = open(path, "wb")  # noqa: SIM115
        self._writer = Writer(self._file, chunk_size=32 * 1024, compression=CompressionType.NONE)
        self._writer.start(profile="", library="armid")
        schema = self._writer.register_schema("armid.JointState", "jsonschema", b"{}")
        self._channel = self._writer.register_channel("/joint_state", "json", schema)
        self._writer.add_metadata("armid.run", metadata)
        self.names, self.kt = names, kt

    def write(self, states: JointStates) -> None:
        for k in range(len(states)):
            self._write_one(states, k)

    def _write_one(self, states: JointStates, k: int) -> None:
        record = states.record(k)
        s = record.sample
        ns = int(round(s.time_s * 1e9))
        msg = {"header": {"stamp": {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}, "frame_id": ""}, "name": self.names,
               "position": s.position.tolist(), "velocity": s.velocity.tolist(), "effort": (s.measured_current * self.kt).tolist(),
               "sequence": record.sequence, "cycle": s.cycle, "valid": s.valid.tolist(), "velocity_fresh": s.velocity_fresh.tolist(),
               "commanded_current": s.commanded_current.tolist(), "measured_current": s.measured_current.tolist(), "status": s.status.tolist()}
        self._writer.add_message(self._channel, ns, json.dumps(msg).encode(), ns, record.sequence % 2**32)

    def close(self) -> None:
        self._writer.finish()
        self._file.close()


def acquire(out: Path, seconds: float) -> tuple[list[JointStates], Path, Path]:
    """Run the simulated arm for ``seconds`` of arm time, recording both layouts and keeping every record."""
    rig = load_rig(config_file("rigs/sim.yaml")).with_bus(channel=f"armid-size-{uuid.uuid4().hex[:8]}")
    names = [j.name for j in rig.robot.joints]
    kt = np.array([j.torque_constant for j in rig.robot.joints])
    ros2, legacy = out / "ros2.mcap", out / "json.mcap"
    recorder = McapRecorder(ros2, names, {"robot": rig.robot.name})
    old = JsonRecorder(legacy, names, kt, {"robot": rig.robot.name})
    kept: list[JointStates] = []
    driver, sim = simulated_driver(rig)
    sinks = [Sink("ros2", recorder.write, bounded=False), Sink("json", old.write, bounded=False), Sink("keep", kept.append, bounded=False)]
    try:
        driver.start()
        acq = Acquisition(driver, sinks)
        acq.start()
        deadline = time.monotonic() + 20 * seconds + 30
        while acq.sequence * rig.period_s < seconds and time.monotonic() < deadline and not acq.error:
            time.sleep(0.05)
        acq.stop()
    finally:
        driver.close()
        sim.close()
        recorder.close()
        old.close()
    return kept, ros2, legacy


def compare(path: Path, kept: list[JointStates]) -> tuple[int, list[str]]:
    """Read ``path`` with mcap_ros2's decoder; (cycles compared, differences) against ``kept``."""
    from mcap_ros2.reader import read_ros2_messages

    states, extras = {}, {}
    for m in read_ros2_messages(str(path)):
        key = (m.log_time_ns, m.sequence_count) if hasattr(m, "sequence_count") else m.log_time_ns
        (states if m.channel.topic == JOINT_STATES_TOPIC else extras)[key] = m.ros_msg
    by_seq = {int(e.sequence): (states.get(k), e) for k, e in extras.items()}
    wrong = []
    rows = [part.record(k) for part in kept for k in range(len(part))]
    for r in rows:
        s = r.sample
        state, extra = by_seq.get(r.sequence, (None, None))
        if state is None or extra is None:
            wrong.append(f"sequence {r.sequence}: not in the file")
            continue
        ns = int(round(s.time_s * 1e9))
        pairs = {"stamp": (state.header.stamp.sec * 1_000_000_000 + state.header.stamp.nanosec, ns),
                 "position": (list(state.position), s.position.tolist()), "velocity": (list(state.velocity), s.velocity.tolist()),
                 "effort": (list(state.effort), s.joint_torque().tolist()), "cycle": (int(extra.cycle), s.cycle),
                 "valid": (list(extra.valid), s.valid.tolist()), "velocity_fresh": (list(extra.velocity_fresh), s.velocity_fresh.tolist()),
                 "commanded_current": (list(extra.commanded_current), s.commanded_current.tolist()),
                 "measured_current": (list(extra.measured_current), s.measured_current.tolist()),
                 "statusword": (list(extra.statusword), s.status.tolist()),
                 "extra stamp": (extra.header.stamp.sec * 1_000_000_000 + extra.header.stamp.nanosec, ns)}
        wrong += [f"sequence {r.sequence}: {name} {a} != {b}" for name, (a, b) in pairs.items() if a != b]
    return len(rows), wrong


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        kept, ros2, legacy = acquire(Path(tmp), args.seconds)
        n, wrong = compare(ros2, kept)
        a, b = ros2.stat().st_size, legacy.stat().st_size
        print(f"{n} cycles ({n * 0.002:.1f} s of 6 joints at 2 ms)")
        print(f"ROS 2 CDR + zstd: {a:,} bytes ({a / n:.0f} B/cycle); JSON (before): {b:,} bytes ({b / n:.0f} B/cycle); ratio {a / b:.3f}")
        print(f"read back by mcap_ros2: {n - len({w.split(':')[0] for w in wrong})} of {n} cycles equal to what was acquired")
        for w in wrong[:5]:
            print("  ", w)
        return 0 if not wrong and a <= b / 4 else 1


if __name__ == "__main__":
    with recorded("recording"):
        code = main()
        if code:
            sys.exit(code)

"""MCAP recordings that the ROS 2 world opens: ``ros2 bag``, Foxglove, PlotJuggler, ``armid identify``.

Two channels, both ROS 2 CDR with their ``ros2msg`` schemas (what rosbag2's MCAP storage
writes), one message each per cycle with the same log time and MCAP sequence number:

- ``/joint_states``: ``sensor_msgs/msg/JointState`` (header stamp, joint names, position,
  velocity, effort = the driver's torque, N*m or N);
- ``/armid/joint_state_extra``: ``armid_msgs/msg/JointStateExtra``, what identification
  needs beside it: sequence and cycle counters, validity per joint, velocity freshness,
  commanded and measured current (A), statusword.

The schemas are :data:`armid.schema.joint_state.ROS2_MSGDEFS`. Metadata ``armid.run`` holds
robot, rig, drive configuration read back from the drives, excitation parameters and
software versions. Metadata ``armid.run_end``, written when a run that says how it ended is
closed (``armid excite``), holds ``completed`` (``true``/``false``), ``stop`` (the line that
stopped the run: a drive fault, lost frames, a safety stop; absent when it completed),
``stop_cycle`` and ``records``: every reader says the stop. Chunks are zstd-compressed; the
summary indexes them.

Crash safety: a chunk is closed after about 16 KiB of messages (about 35 cycles, 0.07 s at
2 ms), never between a cycle's two messages, and at least every 0.25 s; each closed chunk is
handed to the operating system at once. A recorder killed at any instant leaves every
completed chunk on disk: at most the last quarter second is lost.
:func:`armid.io.recordings.read_mcap_arrays` reads such a file up to where it breaks and
says what it could not read.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from armid.io.ros2_cdr import ros2_messages
from armid.schema.errors import ArmidError
from armid.schema.joint_state import (
    EXTRA_TOPIC,
    EXTRA_TYPE,
    JOINT_STATE_TYPE,
    JOINT_STATES_TOPIC,
    ROS2_MSGDEFS,
    JointStateRecord,
)
from armid.schema.joint_states import JointStates

CHUNK_BYTES = 16 * 1024
FLUSH_S = 0.25
TOPIC = JOINT_STATES_TOPIC
RUN_END = "armid.run_end"
"""The metadata record of how the run ended (see the module docstring)."""
_RECORD_OVERHEAD = 9 + 22  # an MCAP message record's opcode, length and fixed fields


class RecorderWriteError(ArmidError, OSError):
    """The recording's file could not be written (a full disk, a file-size limit, a folder gone):
    the run stops; what was handed to the operating system before it reads back."""

    def __init__(self, path: Path, err: OSError) -> None:
        super().__init__(f"{path}: cannot write ({err.strerror or err})")
        self.path = path


class McapRecorder:
    """Write records to ``path``; ``close`` writes the summary (a killed recorder leaves none)."""

    def __init__(self, path: str | Path, joint_names: list[str], metadata: dict[str, Any]) -> None:
        from mcap.writer import CompressionType, IndexType, Writer

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        # chunks are closed here (whole cycles only), never by the writer's own size limit
        # every index (chunk indexes in the summary, a message index after each chunk): rosbags'
        # reader finds no message without the message indexes (it read 0 of 2,078 in a 2 s
        # run); they cost 16 bytes a message (a 2 s run 66 -> 103 kB). armid's own reader
        # walks the chunks and checks each by its CRC either way
        self._writer = Writer(self._file, chunk_size=1 << 62, compression=CompressionType.ZSTD, index_types=IndexType.ALL)
        self._writer.start(profile="ros2", library="armid")
        self._channel = {}
        for topic, kind in ((JOINT_STATES_TOPIC, JOINT_STATE_TYPE), (EXTRA_TOPIC, EXTRA_TYPE)):
            schema = self._writer.register_schema(kind, "ros2msg", ROS2_MSGDEFS[kind].encode())
            self._channel[topic] = self._writer.register_channel(topic, "cdr", schema)
        self._writer.add_metadata("armid.run", {k: v if isinstance(v, str) else json.dumps(v) for k, v in metadata.items()})
        self.names = list(joint_names)
        self._last_flush = time.monotonic()
        self._chunk_bytes = 0
        self.count = 0

    def write(self, states: JointStates) -> None:
        """Write ``states`` (one cycle or several); :class:`RecorderWriteError` when the file
        cannot take them."""
        try:
            for k in range(len(states)):
                self._write(states.record(k))
        except OSError as err:
            raise RecorderWriteError(self.path, err) from None

    def _write(self, record: JointStateRecord) -> None:
        ns = int(round(record.sample.time_s * 1e9))
        seq = record.sequence % 2**32
        for topic, data in zip((JOINT_STATES_TOPIC, EXTRA_TOPIC), ros2_messages(record, self.names)):
            self._writer.add_message(self._channel[topic], ns, data, ns, seq)
            self._chunk_bytes += len(data) + _RECORD_OVERHEAD
        self.count += 1
        now = time.monotonic()
        if self._chunk_bytes >= CHUNK_BYTES or now - self._last_flush >= FLUSH_S:
            self._writer.flush()  # closes the chunk (a whole number of cycles) and hands it to the OS
            self._chunk_bytes = 0
            self._last_flush = now

    def close(self, end: dict[str, Any] | None = None) -> None:
        """Write the summary and close the file. ``end``: how the run ended (``completed``,
        ``stop``, ``stop_cycle``; ``records`` is this recorder's count unless given), written
        first as metadata :data:`RUN_END` after the last chunk."""
        try:
            if end is not None:
                self._writer.flush()  # the last records' chunk first: the end record comes after them
                doc = {"records": self.count, **{k: v for k, v in end.items() if v is not None}}
                self._writer.add_metadata(RUN_END, {k: v if isinstance(v, str) else json.dumps(v) for k, v in doc.items()})
            self._writer.finish()
        except OSError as err:
            raise RecorderWriteError(self.path, err) from None
        finally:
            try:
                self._file.close()
            except OSError:  # the buffer that could not be written: already said above
                pass

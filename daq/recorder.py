"""MCAP recordings: the run's record, readable by Foxglove, PlotJuggler and ``armid identify``.

Channel ``/joint_state`` holds one JSON message per cycle shaped like
``sensor_msgs/msg/JointState`` (header stamp, names, position, velocity, effort = measured
current times the torque constant) plus what identification needs: the cycle counter,
the sequence number, validity per joint, commanded and measured current. Metadata
``armid.run`` holds robot, rig, drive configuration read back from the drives,
excitation parameters and software versions.

Crash safety: chunks are small (32 KiB, about 0.15 s at 2 ms) and the file is flushed to
the operating system at least every 0.25 s, so a recorder killed at any instant leaves
every completed chunk on disk: at most the last half second is lost. :func:`read_mcap`
reads such a file up to where it breaks and says what it could not read.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from armid.identify.recordings import MCAP_TOPIC
from armid.identify.recordings import read_mcap_arrays as read_mcap  # noqa: F401  (the reader lives with the other readers)
from armid.identify.spatial import Array

from .record_format import JointStateRecord

CHUNK_BYTES = 32 * 1024
FLUSH_S = 0.25
TOPIC = MCAP_TOPIC
SCHEMA_NAME = "armid.JointState"

_SCHEMA = {
    "type": "object",
    "title": "sensor_msgs/msg/JointState (armid)",
    "properties": {
        "header": {"type": "object", "properties": {"stamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
                                                     "frame_id": {"type": "string"}}},
        "name": {"type": "array", "items": {"type": "string"}},
        "position": {"type": "array", "items": {"type": "number"}},
        "velocity": {"type": "array", "items": {"type": "number"}},
        "effort": {"type": "array", "items": {"type": "number"}},
        "sequence": {"type": "integer"},
        "cycle": {"type": "integer"},
        "valid": {"type": "array", "items": {"type": "boolean"}},
        "velocity_fresh": {"type": "array", "items": {"type": "boolean"}},
        "commanded_current": {"type": "array", "items": {"type": "number"}},
        "measured_current": {"type": "array", "items": {"type": "number"}},
        "status": {"type": "array", "items": {"type": "integer"}},
    },
}


class McapRecorder:
    """Write records to ``path``; ``close`` writes the summary (a killed recorder leaves none)."""

    def __init__(self, path: str | Path, joint_names: list[str], torque_constants: Array, metadata: dict[str, Any]) -> None:
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._file, chunk_size=CHUNK_BYTES, compression=CompressionType.NONE)
        self._writer.start(profile="", library="armid")
        schema = self._writer.register_schema(SCHEMA_NAME, "jsonschema", json.dumps(_SCHEMA).encode())
        self._channel = self._writer.register_channel(TOPIC, "json", schema)
        self._writer.add_metadata("armid.run", {k: v if isinstance(v, str) else json.dumps(v) for k, v in metadata.items()})
        self.names = joint_names
        self.kt = np.asarray(torque_constants, float)
        self._last_flush = time.monotonic()
        self.count = 0

    def write(self, record: JointStateRecord) -> None:
        s = record.sample
        ns = int(round(s.time_s * 1e9))
        msg = {
            "header": {"stamp": {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}, "frame_id": ""},
            "name": self.names,
            "position": s.position.tolist(),
            "velocity": s.velocity.tolist(),
            "effort": (s.measured_current * self.kt).tolist(),
            "sequence": record.sequence,
            "cycle": s.cycle,
            "valid": s.valid.tolist(),
            "velocity_fresh": s.velocity_fresh.tolist(),
            "commanded_current": s.commanded_current.tolist(),
            "measured_current": s.measured_current.tolist(),
            "status": s.status.tolist(),
        }
        self._writer.add_message(self._channel, ns, json.dumps(msg).encode(), ns, record.sequence % 2**32)
        self.count += 1
        now = time.monotonic()
        if now - self._last_flush >= FLUSH_S:
            self._file.flush()
            self._last_flush = now

    def close(self) -> None:
        self._writer.finish()
        self._file.close()

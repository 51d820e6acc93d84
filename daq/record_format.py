"""The joint-state record on the wire: a compact little-endian layout, versioned by name.

The schema's name and version travel in the Zenoh encoding
(``application/octet-stream;armid.JointState/1``), so a subscriber knows what it holds
before it decodes a byte. Layout: a 32-byte header (sequence u64, cycle u64, time f64,
joint count u16, flags u16, reserved u32), then 36 bytes per joint (valid u8, velocity
fresh u8, statusword u16, position, velocity, commanded current, measured current f64).
``sequence`` counts records without gaps, so that a subscriber can see what it missed.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
from armid.drivers.interface import Sample
from armid.identify.spatial import Array

SCHEMA = "armid.JointState"
VERSION = 1
ENCODING = f"application/octet-stream;{SCHEMA}/{VERSION}"
_HEADER = struct.Struct("<QQdHHI")
_JOINT = np.dtype([("valid", "u1"), ("fresh", "u1"), ("status", "<u2"), ("position", "<f8"), ("velocity", "<f8"),
                   ("commanded", "<f8"), ("measured", "<f8")])


@dataclass
class JointStateRecord:
    sequence: int
    sample: Sample

    def pack(self) -> bytes:
        s = self.sample
        n = s.position.shape[0]
        joints = np.zeros(n, _JOINT)
        joints["valid"], joints["fresh"], joints["status"] = s.valid, s.velocity_fresh, s.status
        joints["position"], joints["velocity"] = s.position, s.velocity
        joints["commanded"], joints["measured"] = s.commanded_current, s.measured_current
        return _HEADER.pack(self.sequence, s.cycle, s.time_s, n, 0, 0) + joints.tobytes()

    @staticmethod
    def unpack(data: bytes) -> JointStateRecord:
        if len(data) < _HEADER.size:
            raise ValueError(f"{SCHEMA}/{VERSION}: {len(data)} bytes, shorter than the {_HEADER.size}-byte header")
        seq, cycle, t, n, _, _ = _HEADER.unpack_from(data)
        if len(data) != _HEADER.size + n * _JOINT.itemsize:
            raise ValueError(f"{SCHEMA}/{VERSION}: {len(data)} bytes for {n} joints, expected {_HEADER.size + n * _JOINT.itemsize}")
        j = np.frombuffer(data, _JOINT, n, _HEADER.size)
        sample = Sample(int(cycle), float(t), j["valid"].astype(bool), j["position"].copy(), j["velocity"].copy(),
                        j["fresh"].astype(bool), j["commanded"].copy(), j["measured"].copy(), j["status"].astype(np.int64))
        return JointStateRecord(int(seq), sample)


def check_encoding(encoding: str) -> None:
    """Refuse a record whose schema or version this code does not read."""
    if not encoding.endswith(f";{SCHEMA}/{VERSION}"):
        raise ValueError(f"encoding {encoding!r} is not {ENCODING!r}")


def as_arrays(records: list[JointStateRecord]) -> dict[str, Array]:
    return {
        "sequence": np.array([r.sequence for r in records]),
        "cycle": np.array([r.sample.cycle for r in records]),
        "t": np.array([r.sample.time_s for r in records]),
        "valid": np.array([r.sample.valid for r in records]),
        "position": np.array([r.sample.position for r in records]),
        "velocity": np.array([r.sample.velocity for r in records]),
        "commanded_current": np.array([r.sample.commanded_current for r in records]),
        "measured_current": np.array([r.sample.measured_current for r in records]),
    }

"""The joint-state record: one cycle of every joint, its units, and its one binary codec.

Units are SI at the joint, everywhere after the driver: position in rad (m for a prismatic
joint), velocity in rad/s (m/s), current in A, torque in N*m (N). The driver applies each
joint's torque constant to the measured current, ``torque = measured_current * torque_constant``,
and the torque travels beside the currents: a reader takes it as recorded. Where a recording
carries currents only (a CSV's ``i1..in``, an MCAP in the older JSON layout), the reader applies
the robot file's torque constant instead (``armid.io.recordings``); a torque command is divided
by it into a current. Each record is scaled once.

Binary codec (the Zenoh stream): the schema's name and version travel in the Zenoh
encoding (``application/octet-stream;armid.JointState/2``), so a subscriber knows what it
holds before it decodes a byte. Layout, little-endian: a 32-byte header (sequence u64,
cycle u64, time f64, joint count u16, flags u16, reserved u32), then 44 bytes per joint
(valid u8, velocity fresh u8, statusword u16, position, velocity, commanded current,
measured current, torque f64); a payload holds one such record or several back to back.
``sequence`` counts records without gaps, so that a subscriber can see what it missed. The
codec is :class:`~armid.schema.joint_states.JointStates`' (the record as columns).

Recordings (MCAP) carry the same record as ROS 2 messages: ``sensor_msgs/msg/JointState``
on ``/joint_states`` (position, velocity, effort = torque) and the rest in
``armid_msgs/msg/JointStateExtra`` on ``/armid/joint_state_extra`` (:data:`ROS2_MSGDEFS`).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import RecordFormatError

Array = NDArray[np.float64]

SCHEMA = "armid.JointState"
VERSION = 2
ENCODING = f"application/octet-stream;{SCHEMA}/{VERSION}"


@dataclass
class Sample:
    """One cycle of every joint, keyed by the cycle counter (not by arrival time), SI units.

    ``valid[j]`` is False when joint j's frames for this cycle did not arrive by the
    deadline; its values are then the last known ones. ``velocity_fresh[j]`` is False when
    the plan did not carry velocity this cycle (the value is the last reported one).
    ``commanded_current`` is what was in force during the period that ends at this cycle.
    ``torque`` is ``measured_current`` times each joint's torque constant (N*m or N), set by
    the driver; ``None`` only for a sample built by hand without one.
    """

    cycle: int
    time_s: float
    valid: Array
    position: Array
    velocity: Array
    velocity_fresh: Array
    commanded_current: Array
    measured_current: Array
    status: Array  # statusword per joint (0 when unknown)
    torque: Array | None = None

    @staticmethod
    def empty(cycle: int, time_s: float, n: int) -> Sample:
        z = np.zeros(n)
        return Sample(cycle, time_s, np.zeros(n, bool), z.copy(), z.copy(), np.zeros(n, bool), z.copy(), z.copy(), np.zeros(n, np.int64),
                      z.copy())

    def joint_torque(self) -> Array:
        """``torque``; a sample built without one has NaN (never a silent zero)."""
        return self.torque if self.torque is not None else np.full(self.measured_current.shape, np.nan)


@dataclass
class JointStateRecord:
    """One numbered sample: a cycle of :class:`~armid.schema.joint_states.JointStates` as the ROS 2
    writer takes it (:meth:`JointStates.record <armid.schema.joint_states.JointStates.record>`)."""

    sequence: int
    sample: Sample


def check_encoding(encoding: str) -> None:
    """Refuse a record whose schema or version this code does not read."""
    if not encoding.endswith(f";{SCHEMA}/{VERSION}"):
        raise RecordFormatError(f"encoding {encoding!r} is not {ENCODING!r}")


# --- the same record as ROS 2 messages (MCAP recordings) ---
JOINT_STATES_TOPIC = "/joint_states"
EXTRA_TOPIC = "/armid/joint_state_extra"
JOINT_STATE_TYPE = "sensor_msgs/msg/JointState"
EXTRA_TYPE = "armid_msgs/msg/JointStateExtra"

_HEADER_DEFS = """================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec"""

ROS2_MSGDEFS = {
    JOINT_STATE_TYPE: "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n" + _HEADER_DEFS,
    EXTRA_TYPE: ("# armid's part of a joint-state record; header.stamp equals the /joint_states message's\n"
                 "std_msgs/Header header\nuint64 sequence\nuint64 cycle\nbool[] valid\nbool[] velocity_fresh\n"
                 "float64[] commanded_current\nfloat64[] measured_current\nuint16[] statusword\n" + _HEADER_DEFS),
}
"""``ros2msg`` schema text of each message type, as rosbag2 writes it (dependencies after ``MSG:`` lines)."""


class _Cdr:
    """A little-endian CDR (XCDR1) buffer: what ROS 2's rmw writes. Alignment counts from the
    end of the 4-byte encapsulation header."""

    def __init__(self) -> None:
        self.buf = bytearray(b"\x00\x01\x00\x00")

    def align(self, size: int) -> None:
        pad = -(len(self.buf) - 4) % size
        if pad:
            self.buf += bytes(pad)

    def u32(self, value: int) -> None:
        self.align(4)
        self.buf += struct.pack("<I", value)

    def header(self, ns: int) -> None:
        self.align(4)
        self.buf += struct.pack("<iII", ns // 1_000_000_000, ns % 1_000_000_000, 1) + b"\x00"  # stamp, frame_id ""

    def strings(self, values: list[bytes]) -> None:
        self.u32(len(values))
        for v in values:
            self.u32(len(v) + 1)
            self.buf += v + b"\x00"

    def array(self, values: NDArray[Any], dtype: str, size: int) -> None:
        self.u32(len(values))
        self.align(size)
        self.buf += np.ascontiguousarray(values, dtype).tobytes()


ROS2_SECONDS = (-(2.0**31), 2.0**31)
"""The stamps ``builtin_interfaces/Time`` can hold (``sec`` is an int32)."""


def ros2_messages(record: JointStateRecord, names: list[str]) -> tuple[bytes, bytes]:
    """The record as CDR bytes of (``sensor_msgs/msg/JointState``, ``armid_msgs/msg/JointStateExtra``),
    byte for byte what a ROS 2 serializer writes for :data:`ROS2_MSGDEFS` (tested against
    ``mcap_ros2``'s), at a small fraction of a generic serializer's cost per cycle."""
    s = record.sample
    if not (np.isfinite(s.time_s) and ROS2_SECONDS[0] <= s.time_s < ROS2_SECONDS[1]):
        raise RecordFormatError(f"record {record.sequence}: time stamp {s.time_s:.6g} s cannot be written in a ROS 2 recording "
                                "(builtin_interfaces/Time counts int32 seconds: 1901-12-13 to 2038-01-19)")
    ns = int(round(s.time_s * 1e9))
    state = _Cdr()
    state.header(ns)
    state.strings([n.encode() for n in names])
    for values in (s.position, s.velocity, s.joint_torque()):
        state.array(values, "<f8", 8)
    extra = _Cdr()
    extra.header(ns)
    extra.align(8)
    extra.buf += struct.pack("<QQ", record.sequence, s.cycle)
    extra.array(s.valid, "u1", 1)
    extra.array(s.velocity_fresh, "u1", 1)
    extra.array(s.commanded_current, "<f8", 8)
    extra.array(s.measured_current, "<f8", 8)
    extra.array(np.asarray(s.status, np.int64) & 0xFFFF, "<u2", 2)
    return bytes(state.buf), bytes(extra.buf)


def _cdr_layout(msg: bytes, fields: tuple[tuple[str, str], ...]) -> tuple[dict[str, tuple[int, str, int]], NDArray[np.bool_]] | None:
    """Where each numeric field of one CDR message lies (offset, dtype, count) and which bytes
    are structure (the encapsulation, lengths, strings, padding); None if ``msg`` does not
    parse as ``fields`` (kinds: ``header``, ``strings``, or a dtype and ``[]`` for an array).
    Alignment counts from the end of the 4-byte encapsulation header, as :class:`_Cdr` writes."""
    numeric: dict[str, tuple[int, str, int]] = {}
    structure = np.ones(len(msg), bool)
    at = 4

    def take(name: str, dtype: str, count: int) -> None:
        nonlocal at
        size = np.dtype(dtype).itemsize
        at += -(at - 4) % size
        if at + size * count > len(msg):
            raise ValueError
        numeric[name] = (at, dtype, count)
        structure[at : at + size * count] = False
        at += size * count

    def length() -> int:
        nonlocal at
        at += -(at - 4) % 4
        if at + 4 > len(msg):
            raise ValueError
        (n,) = struct.unpack_from("<I", msg, at)
        at += 4
        return int(n)

    try:
        for name, kind in fields:
            if kind == "header":
                take("sec", "<i4", 1)
                take("nanosec", "<u4", 1)
                skip = length()  # frame_id: structure (read before ``at`` moves on: length() moves it)
                at += skip
            elif kind == "strings":
                for _ in range(length()):
                    skip = length()
                    at += skip
            elif kind.endswith("[]"):
                take(name, kind[:-2], length())
            else:
                take(name, kind, 1)
    except (ValueError, struct.error):
        return None
    return (numeric, structure) if at == len(msg) else None


_STATE_FIELDS = (("header", "header"), ("name", "strings"), ("position", "<f8[]"), ("velocity", "<f8[]"), ("effort", "<f8[]"))
_EXTRA_FIELDS = (("header", "header"), ("sequence", "<u8"), ("cycle", "<u8"), ("valid", "u1[]"), ("velocity_fresh", "u1[]"),
                 ("commanded_current", "<f8[]"), ("measured_current", "<f8[]"), ("statusword", "<u2[]"))


def ros2_columns(messages: list[bytes], kind: str) -> dict[str, NDArray[Any]] | None:
    """The numeric fields of many CDR messages of one type (``JOINT_STATE_TYPE`` or
    ``EXTRA_TYPE``) as columns (messages, values), read in place: what a generic decoder does
    message by message (3 s for the demo's 30,000 cycles), at a small fraction of the cost.
    Only when every message has the first one's layout to the byte (the same length, joint
    names, frame id and padding: what :func:`ros2_messages` writes for one arm); None
    otherwise, and the caller decodes them one by one."""
    if not messages or any(len(m) != len(messages[0]) for m in messages):
        return None
    found = _cdr_layout(messages[0], _STATE_FIELDS if kind == JOINT_STATE_TYPE else _EXTRA_FIELDS)
    if found is None:
        return None
    numeric, structure = found
    table = np.frombuffer(b"".join(messages), np.uint8).reshape(len(messages), len(messages[0]))
    if not np.array_equal(table[:, structure], np.broadcast_to(table[0, structure], (len(messages), int(structure.sum())))):
        return None
    out = {}
    for name, (offset, dtype, count) in numeric.items():
        width = np.dtype(dtype).itemsize * count
        out[name] = np.ascontiguousarray(table[:, offset : offset + width]).view(dtype).reshape(len(messages), count)
    return out

"""ROS 2 CDR of a recording's two message types, through ``rosbags``' typestore.

The types are armid's own ``ros2msg`` schemas (:data:`~armid.schema.joint_state.ROS2_MSGDEFS`,
the text the recorder stores beside them), registered once into an empty typestore: the bytes
:func:`ros2_messages` writes are those of every ROS 2 serializer, and :func:`decoded_columns`
reads any message a ROS 2 tool wrote for them, checking each one.

One path of armid's own remains, :func:`ros2_columns`: messages of one layout (what the
recorder writes for one arm) read in place as arrays, because decoding them one by one is far
slower: for a 10-minute recording at 2 ms (300,000 cycles) the typestore's decoding and the
gathering of its values cost 17.5 s of CPU, reading in place 0.7 s (the whole file is read in
2.4 s). The first message is checked against the typestore's decoding on every read.
"""

from __future__ import annotations

import struct
from functools import lru_cache
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from armid.identify.errors import RecordingError
from armid.schema.errors import RecordFormatError
from armid.schema.joint_state import (
    EXTRA_TOPIC,
    EXTRA_TYPE,
    JOINT_STATE_TYPE,
    JOINT_STATES_TOPIC,
    ROS2_MSGDEFS,
    ROS2_SECONDS,
    JointStateRecord,
)
from armid.schema.ros2_types import DIAGNOSTIC_ARRAY_TYPE, INERTIA_STAMPED_TYPE, LIVE_MSGDEFS

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

PER_JOINT = ("position", "velocity", "effort", "valid", "velocity_fresh", "commanded_current", "measured_current", "statusword")
"""The per-joint fields of the two message types together, by their message names."""
STATE_FIELDS = ("position", "velocity", "effort")
"""Those of ``sensor_msgs/msg/JointState``; the others are ``armid_msgs/msg/JointStateExtra``'s."""


@lru_cache(maxsize=1)
def typestore() -> Typestore:
    """A ``rosbags`` typestore that holds the two message types and what they use, from armid's
    schemas, with their (de)serializers built: about 0.1 s on the first call, so that a writer
    that calls it when it opens does not spend it on its first record."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    defs = {**ROS2_MSGDEFS, **LIVE_MSGDEFS}
    for kind, text in defs.items():
        store.register(get_types_from_msg(text, kind))
    for kind in defs:
        store.get_msgdef(kind)  # generates the type's serializer and deserializer
    return store


def ros2_messages(record: JointStateRecord, names: list[str]) -> tuple[bytes, bytes]:
    """The record as CDR bytes of (``sensor_msgs/msg/JointState``, ``armid_msgs/msg/JointStateExtra``)."""
    s = record.sample
    if not (np.isfinite(s.time_s) and ROS2_SECONDS[0] <= s.time_s < ROS2_SECONDS[1]):
        raise RecordFormatError(f"record {record.sequence}: time stamp {s.time_s:.6g} s cannot be written in a ROS 2 recording "
                                "(builtin_interfaces/Time counts int32 seconds: 1901-12-13 to 2038-01-19)")
    store = typestore()
    ns = int(round(s.time_s * 1e9))
    header = _header(ns)

    def floats(values: Any) -> NDArray[np.float64]:
        return np.ascontiguousarray(values, np.float64)

    state = store.types[JOINT_STATE_TYPE](header=header, name=list(names), position=floats(s.position), velocity=floats(s.velocity),
                                          effort=floats(s.joint_torque()))
    extra = store.types[EXTRA_TYPE](header=header, sequence=record.sequence, cycle=s.cycle, valid=np.ascontiguousarray(s.valid, bool),
                                    velocity_fresh=np.ascontiguousarray(s.velocity_fresh, bool),
                                    commanded_current=floats(s.commanded_current), measured_current=floats(s.measured_current),
                                    statusword=(np.asarray(s.status, np.int64) & 0xFFFF).astype(np.uint16))
    return (bytes(store.serialize_cdr(state, JOINT_STATE_TYPE, little_endian=True)),
            bytes(store.serialize_cdr(extra, EXTRA_TYPE, little_endian=True)))


def _header(stamp_ns: int, frame_id: str = "") -> Any:
    """A ``std_msgs/msg/Header`` at ``stamp_ns`` (nanoseconds since the epoch)."""
    store = typestore()
    if not ROS2_SECONDS[0] * 1e9 <= stamp_ns < ROS2_SECONDS[1] * 1e9:
        raise RecordFormatError(f"time stamp {stamp_ns} ns cannot be written in a ROS 2 header (int32 seconds)")
    return store.types["std_msgs/msg/Header"](stamp=store.types["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000,
                                                                                            nanosec=stamp_ns % 1_000_000_000),
                                              frame_id=frame_id)


def _cdr(message: Any, kind: str) -> bytes:
    return bytes(typestore().serialize_cdr(message, kind, little_endian=True))


def joint_state_cdr(names: list[str], stamp_ns: int, position: Any, velocity: Any, effort: Any) -> bytes:
    """One ``sensor_msgs/msg/JointState`` as CDR: the live stream's message (effort = joint torque)."""
    def floats(values: Any) -> NDArray[np.float64]:
        return np.ascontiguousarray(values, np.float64)

    msg = typestore().types[JOINT_STATE_TYPE](header=_header(stamp_ns), name=list(names), position=floats(position),
                                              velocity=floats(velocity), effort=floats(effort))
    return _cdr(msg, JOINT_STATE_TYPE)


def inertia_stamped_cdr(stamp_ns: int, frame_id: str, mass: float, com: Any, inertia: Any) -> bytes:
    """One ``geometry_msgs/msg/InertiaStamped`` as CDR: ``mass`` (kg), ``com`` (3, m) and
    ``inertia`` (ixx, ixy, ixz, iyy, iyz, izz; kg m^2, about the centre of mass) in ``frame_id``'s axes."""
    store = typestore()
    c = [float(x) for x in com]
    ixx, ixy, ixz, iyy, iyz, izz = (float(x) for x in inertia)
    body = store.types["geometry_msgs/msg/Inertia"](m=float(mass), com=store.types["geometry_msgs/msg/Vector3"](x=c[0], y=c[1], z=c[2]),
                                                    ixx=ixx, ixy=ixy, ixz=ixz, iyy=iyy, iyz=iyz, izz=izz)
    return _cdr(store.types[INERTIA_STAMPED_TYPE](header=_header(stamp_ns, frame_id), inertia=body), INERTIA_STAMPED_TYPE)


def diagnostic_array_cdr(stamp_ns: int, statuses: list[dict[str, Any]]) -> bytes:
    """One ``diagnostic_msgs/msg/DiagnosticArray`` as CDR; each status a dict of ``level`` (0-3),
    ``name``, ``message``, ``hardware_id`` and ``values`` (key to text)."""
    store = typestore()
    status = store.types["diagnostic_msgs/msg/DiagnosticStatus"]
    pair = store.types["diagnostic_msgs/msg/KeyValue"]
    items = [status(level=int(s["level"]), name=str(s["name"]), message=str(s["message"]), hardware_id=str(s.get("hardware_id", "")),
                    values=[pair(key=str(k), value=str(v)) for k, v in (s.get("values") or {}).items()]) for s in statuses]
    return _cdr(store.types[DIAGNOSTIC_ARRAY_TYPE](header=_header(stamp_ns), status=items), DIAGNOSTIC_ARRAY_TYPE)


def decode(data: bytes, kind: str) -> Any:
    """One CDR message of ``kind`` (``JOINT_STATE_TYPE`` or ``EXTRA_TYPE``) as the typestore's
    message object; raises ``ValueError`` (``rosbags``' ``SerdeError``) when it is not one."""
    return typestore().deserialize_cdr(data, kind)


def fields_of(state: Any, extra: Any) -> dict[str, Any]:
    """The per-joint fields (:data:`PER_JOINT`) of one cycle's two decoded messages."""
    return {name: getattr(state if name in STATE_FIELDS else extra, name) for name in PER_JOINT}


def kind_of(data: bytes) -> str | None:
    """Which of the two types ``data`` decodes as with every per-joint field of one non-zero
    count (None: neither). Tells a recording's channels apart when their records were lost."""
    for kind, sized in ((JOINT_STATE_TYPE, ("name", *STATE_FIELDS)), (EXTRA_TYPE, [f for f in PER_JOINT if f not in STATE_FIELDS])):
        try:
            m = decode(data, kind)
        except Exception:  # not this type
            continue
        sizes = {len(getattr(m, name)) for name in sized}
        if len(sizes) == 1 and 0 not in sizes:
            return kind
    return None


def same_length(states: dict[str, Any] | None, extras: dict[str, Any] | None) -> dict[str, Any] | None:
    """Both kinds' columns together when every per-joint field has as many values as the
    positions (else None: the one-by-one path names the field that has not)."""
    if states is None or extras is None:
        return None
    cols = {**states, **{k: v for k, v in extras.items() if k not in ("sec", "nanosec")}}
    return cols if len({cols[name].shape[1] for name in PER_JOINT}) == 1 else None


def decoded_columns(states: list[tuple[int, bytes]], extras: list[tuple[int, bytes]], src: str) -> dict[str, Any]:
    """One cycle's messages (``states[k]`` and ``extras[k]``: the file offset of the chunk that
    held it, its CDR bytes) decoded one by one by the typestore, as columns; a message that is
    not its type, or a field with a count unlike the others', is refused naming it."""
    cols: dict[str, list[Any]] = {name: [] for name in ("sec", "nanosec", "sequence", "cycle", *PER_JOINT)}
    m: int | None = None

    def decoded(topic: str, kind: str, k: int, pos: int, data: bytes) -> Any:
        try:
            return decode(data, kind)
        except Exception as err:  # the CRC held: the recorder wrote something that is not this type
            raise RecordingError(src, f"{topic} message {k} (in the chunk at byte {pos}): not a {kind} in CDR ({err})") from None

    for k, ((ps, ds), (pe, de)) in enumerate(zip(states, extras)):
        s, e = decoded(JOINT_STATES_TOPIC, JOINT_STATE_TYPE, k, ps, ds), decoded(EXTRA_TOPIC, EXTRA_TYPE, k, pe, de)
        fields = fields_of(s, e)
        m = len(s.position) if m is None else m
        wrong = next((name for name, v in fields.items() if len(v) != m), None)
        if wrong is not None:
            raise RecordingError(src, f"{JOINT_STATES_TOPIC if wrong in STATE_FIELDS else EXTRA_TOPIC} "
                                      f"(sequence {e.sequence}): '{wrong}' has {len(fields[wrong])} values, the recording's other messages {m}")
        for name, v in fields.items():
            cols[name].append(list(v))
        for name, v in (("sec", s.header.stamp.sec), ("nanosec", s.header.stamp.nanosec), ("sequence", e.sequence), ("cycle", e.cycle)):
            cols[name].append([v])
    floats = ("position", "velocity", "effort", "commanded_current", "measured_current")
    return {name: np.array(v, float if name in floats else np.int64).reshape(len(states), -1) for name, v in cols.items()}


# --- the fast path: many messages of one layout read in place (see the module docstring) ---
_LAYOUT = {
    JOINT_STATE_TYPE: (("header", "header"), ("name", "strings"), ("position", "<f8[]"), ("velocity", "<f8[]"), ("effort", "<f8[]")),
    EXTRA_TYPE: (("header", "header"), ("sequence", "<u8"), ("cycle", "<u8"), ("valid", "u1[]"), ("velocity_fresh", "u1[]"),
                 ("commanded_current", "<f8[]"), ("measured_current", "<f8[]"), ("statusword", "<u2[]")),
}


def _cdr_layout(msg: bytes, fields: tuple[tuple[str, str], ...]) -> tuple[dict[str, tuple[int, str, int]], NDArray[np.bool_]] | None:
    """Where each numeric field of one little-endian CDR message lies (offset, dtype, count)
    and which bytes are structure (the encapsulation, lengths, strings, padding); None if
    ``msg`` does not parse as ``fields`` (kinds: ``header``, ``strings``, or a dtype and ``[]``
    for an array). Alignment counts from the end of the 4-byte encapsulation header."""
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
        if msg[:4] != b"\x00\x01\x00\x00":
            raise ValueError
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


def ros2_columns(messages: list[bytes], kind: str) -> dict[str, NDArray[Any]] | None:
    """The numeric fields of many CDR messages of one type (``JOINT_STATE_TYPE`` or
    ``EXTRA_TYPE``) as columns (messages, values), read in place. Only when every message has
    the first one's layout to the byte (the same length, joint names, frame id and padding:
    what :func:`ros2_messages` writes for one arm) and the typestore decodes the first one to
    the same values; None otherwise, and the caller decodes them one by one."""
    if not messages or any(len(m) != len(messages[0]) for m in messages):
        return None
    found = _cdr_layout(messages[0], _LAYOUT[kind])
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
    try:
        first = decode(messages[0], kind)
    except Exception:  # not this type after all: the one-by-one path names it
        return None
    stamp = {"sec": first.header.stamp.sec, "nanosec": first.header.stamp.nanosec}
    for name, column in out.items():  # byte for byte: a NaN is a value like any other
        if column[0].tobytes() != np.atleast_1d(np.asarray(stamp[name] if name in stamp else getattr(first, name), column.dtype)).tobytes():
            return None
    return out

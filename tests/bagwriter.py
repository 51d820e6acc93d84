"""rosbag2 bags of ``sensor_msgs/msg/JointState`` written by ``rosbags`` (its Writer and its own
typestore of a ROS 2 distribution), never by armid: the bags of the tests.

    from bagwriter import Message, write_bag
    write_bag(tmp_path / "bag", "mcap", [Message(stamp_ns, names, position, velocity, effort), ...])
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

JOINT_STATE = "sensor_msgs/msg/JointState"


@dataclass
class Message:
    """One message: its header stamp (ns), joint names and values; ``received_ns`` is the bag's
    receive time (the stamp when None); ``topic``, ``raw``: another topic, bytes of one's own."""

    stamp_ns: int
    names: Sequence[str]
    position: Any
    velocity: Any = ()
    effort: Any = ()
    received_ns: int | None = None
    topic: str = "/joint_states"
    raw: bytes | None = None
    msgtype: str = JOINT_STATE
    extra: dict[str, Any] = field(default_factory=dict)


def _store() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def cdr(m: Message, store: Any = None) -> bytes:
    """The message as CDR by ``rosbags``' serializer."""
    store = store or _store()
    if m.raw is not None:
        return m.raw
    header = store.types["std_msgs/msg/Header"](stamp=store.types["builtin_interfaces/msg/Time"](sec=m.stamp_ns // 10**9, nanosec=m.stamp_ns % 10**9),
                                                frame_id="base")
    if m.msgtype != JOINT_STATE:
        return bytes(store.serialize_cdr(store.types[m.msgtype](**m.extra), m.msgtype))

    def floats(v: Any) -> np.ndarray:
        return np.ascontiguousarray(v, np.float64).reshape(-1)

    msg = store.types[JOINT_STATE](header=header, name=list(m.names), position=floats(m.position), velocity=floats(m.velocity),
                                   effort=floats(m.effort))
    return bytes(store.serialize_cdr(msg, JOINT_STATE))


def write_bag(folder: Path, storage: str, messages: Iterable[Message], compression: str | None = None) -> Path:
    """A rosbag2 bag (``storage``: ``sqlite3`` or ``mcap``) at ``folder`` holding ``messages`` in
    their order, each on its topic with its type (``compression``: zstd by ``file`` or by
    ``message``, as ``ros2 bag record --compression-mode`` does); returns the folder."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    store = _store()
    plugin = {"sqlite3": StoragePlugin.SQLITE3, "mcap": StoragePlugin.MCAP}[storage]
    bag = Writer(folder, version=9, storage_plugin=plugin)
    if compression is not None:
        bag.set_compression({"file": CompressionMode.FILE, "message": CompressionMode.MESSAGE}[compression], CompressionFormat.ZSTD)
    with bag as writer:
        connections: dict[tuple[str, str], Any] = {}
        for m in messages:
            key = (m.topic, m.msgtype)
            if key not in connections:
                connections[key] = writer.add_connection(m.topic, m.msgtype, typestore=store)
            writer.write(connections[key], m.stamp_ns if m.received_ns is None else m.received_ns, cdr(m, store))
    return folder


def storage_file(folder: Path) -> Path:
    """The one storage file of a bag's folder (``.db3`` or ``.mcap``)."""
    (found,) = [p for p in folder.iterdir() if p.suffix in (".db3", ".mcap")]
    return found


def arm_messages(t_ns: Sequence[int], names: Sequence[str], q: Any, qd: Any, effort: Any, order: Sequence[int]) -> list[Message]:
    """One message a sample, its joints in ``order`` (indices into ``names`` and the columns)."""
    names = [names[k] for k in order]
    q, qd, effort = (np.asarray(a, float)[:, order] for a in (q, qd, effort))
    return [Message(int(t_ns[k]), names, q[k], qd[k], effort[k]) for k in range(len(t_ns))]

"""A ROS 2 arm's ``sensor_msgs/msg/JointState`` over rmw_zenoh as armid's records (``record --ros2-source``).

The messages of one topic are matched **by name** to the robot file's joints (drivers publish
them in any order, often alphabetical), stamped with their header stamps, and numbered as the
acquisition numbers a driver's cycles: the same :class:`~armid.schema.joint_states.JointStates`
the recorder and the Zenoh stream take. ``effort`` is the joint torque; a message without
velocities or efforts gives NaN there. What a source must not do is named, never absorbed
(:class:`Ros2SourceError`): stop (no message for ``timeout_s``), jump back in time (or repeat a
stamp), change its joint names, or be two publishers at once. A first message that lacks one of
the robot's joints is bad input (:class:`~armid.schema.errors.RecordingError`); joints the robot
file does not have (a gripper's) are left out, and said.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Sequence
from typing import Any

import numpy as np

from armid.io.rmw_zenoh import Ros2Node, read_attachment
from armid.io.ros2_cdr import decode
from armid.schema.errors import ArmidError, RecordingError
from armid.schema.joint_state import JOINT_STATE_TYPE
from armid.schema.joint_states import JointStates


class Ros2SourceError(ArmidError):
    """A live ROS 2 source did what a recording cannot absorb (stopped, went back in time,
    changed its joints): the run stops on it, what was recorded kept (exit 1)."""


def joint_order(names: Sequence[str], joints: Sequence[str], topic: str) -> tuple[np.ndarray[Any, np.dtype[np.intp]], list[str]]:
    """Where each of ``joints`` (the robot file's) lies in a message's ``names``, and the
    message's names the robot does not have; a robot joint absent is :class:`RecordingError`."""
    where = {n: k for k, n in enumerate(names)}
    if len(where) != len(names):
        raise RecordingError(topic, f"joint names repeat in one message: {list(names)}")
    missing = [j for j in joints if j not in where]
    if missing:
        raise RecordingError(topic, f"the messages have no joint {', '.join(missing)} of the robot file (they name {', '.join(names)})")
    return np.array([where[j] for j in joints], np.intp), [n for n in names if n not in set(joints)]


class Ros2JointStateSource:
    """Subscribe to ``topic`` through ``node``; :meth:`take` gives what arrived as records."""

    def __init__(self, node: Ros2Node, topic: str, joints: Sequence[str], timeout_s: float = 2.0) -> None:
        self.topic = topic
        self.joints = list(joints)
        self.timeout_s = timeout_s
        self.sequence = 0
        self.extra_names: list[str] = []
        self._names: tuple[str, ...] | None = None
        self._index: np.ndarray[Any, np.dtype[np.intp]] | None = None
        self._last_ns: int | None = None
        self._gid: bytes | None = None
        self._inbox: deque[tuple[bytes, bytes | None]] = deque()
        self._arrived = threading.Event()
        self._last_arrival = time.monotonic()
        self.first_stamp_s: float | None = None
        node.subscribe(topic, JOINT_STATE_TYPE, self._on_message)

    def _on_message(self, cdr: bytes, att: bytes | None) -> None:
        self._inbox.append((cdr, att))
        self._last_arrival = time.monotonic()
        self._arrived.set()

    def wait_first(self, timeout_s: float, where: str) -> None:
        """Until the first message is in; :class:`Ros2SourceError` naming ``where`` if none in ``timeout_s``."""
        if not self._arrived.wait(timeout_s):
            raise Ros2SourceError(f"{self.topic}: no sensor_msgs/msg/JointState within {timeout_s:g} s ({where})")

    def silent_for(self) -> float:
        """Seconds since the last message arrived."""
        return time.monotonic() - self._last_arrival

    def take(self) -> JointStates | None:
        """The messages that arrived since the last call, as numbered records (None: none)."""
        if self.silent_for() > self.timeout_s:
            raise Ros2SourceError(f"{self.topic}: no message for {self.timeout_s:g} s after {self.sequence} records: the source stopped")
        batch = []
        while self._inbox:
            batch.append(self._inbox.popleft())
        if not batch:
            return None
        return self._records(batch)

    def _records(self, batch: list[tuple[bytes, bytes | None]]) -> JointStates:
        n, m = len(batch), len(self.joints)
        t = np.empty(n)
        q, qd, tau = np.empty((n, m)), np.full((n, m), np.nan), np.full((n, m), np.nan)
        fresh = np.zeros((n, m), bool)
        for k, (cdr, att) in enumerate(batch):
            self._publisher(att)
            try:
                msg = decode(cdr, JOINT_STATE_TYPE)
            except Exception as err:
                raise Ros2SourceError(f"{self.topic}: message {self.sequence + k} is not a sensor_msgs/msg/JointState in CDR ({err})") from None
            names = tuple(msg.name)
            if self._names is None:
                self._index, self.extra_names = joint_order(names, self.joints, self.topic)
                self._names = names
            elif names != self._names:
                raise Ros2SourceError(f"{self.topic}: the joint names changed at message {self.sequence + k}: "
                                      f"{list(self._names)} before, {list(names)} now")
            ns = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
            if self._last_ns is not None and ns <= self._last_ns:
                what = "repeats the stamp" if ns == self._last_ns else f"goes back in time by {(self._last_ns - ns) / 1e9:.6g} s"
                raise Ros2SourceError(f"{self.topic}: message {self.sequence + k} {what} ({ns / 1e9:.9f} s after {self._last_ns / 1e9:.9f} s)")
            self._last_ns = ns
            t[k] = ns / 1e9
            idx = self._index
            assert idx is not None
            q[k] = np.asarray(msg.position, float)[idx] if len(msg.position) == len(names) else np.nan
            if len(msg.velocity) == len(names):
                qd[k] = np.asarray(msg.velocity, float)[idx]
                fresh[k] = True
            if len(msg.effort) == len(names):
                tau[k] = np.asarray(msg.effort, float)[idx]
        if self.first_stamp_s is None:
            self.first_stamp_s = float(t[0])
        seq = np.arange(self.sequence, self.sequence + n, dtype=np.int64)
        self.sequence += n
        nan = np.full((n, m), np.nan)
        return JointStates(seq, seq.copy(), t, np.isfinite(q), fresh, q, qd, nan, nan.copy(), tau, np.zeros((n, m), np.int64))

    def _publisher(self, att: bytes | None) -> None:
        """A second publisher on the topic is named: two arms' states interleaved are no one arm's."""
        if att is None:
            return
        try:
            gid = read_attachment(att)[2]
        except ValueError:
            return  # an older rmw_zenoh's layout: the messages are still JointState's
        if self._gid is None:
            self._gid = gid
        elif gid != self._gid:
            raise Ros2SourceError(f"{self.topic}: a second publisher (GID {gid.hex()}) beside {self._gid.hex()}: "
                                  "two sources interleaved are no one arm's record")

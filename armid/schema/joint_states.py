"""Joint states: the one record after the driver, as columns.

A driver yields one :class:`~armid.schema.joint_state.Sample` per cycle; the acquisition numbers
it and from then on every part of armid holds :class:`JointStates`: one or many cycles of every
joint as arrays, frozen. The acquisition's sinks, the Zenoh stream, the recorder, a recording
read back, the pipeline and both estimators take it; it is sliced and concatenated, never turned
back into rows (the ROS 2 writer takes one cycle at a time through :meth:`JointStates.record`).

The Zenoh codec (:meth:`JointStates.pack`, :meth:`JointStates.unpack`) keeps the wire format of
``armid.JointState/2`` (:mod:`armid.schema.joint_state`): a payload holds one record or several
back to back, each with its own header. Time travels as the driver stamped it (f64 seconds);
:meth:`JointStates.recorded` rounds it, once, to the nanosecond clock of a recording, which is
how a recording reads back: what is computed from a live stream equals what is computed from its
recording.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import RecordFormatError
from .joint_state import SCHEMA, VERSION, JointStateRecord, Sample

_HEADER = np.dtype([("sequence", "<u8"), ("cycle", "<u8"), ("time", "<f8"), ("joints", "<u2"), ("flags", "<u2"), ("reserved", "<u4")])
_JOINT = np.dtype([("valid", "u1"), ("fresh", "u1"), ("status", "<u2"), ("position", "<f8"), ("velocity", "<f8"),
                   ("commanded", "<f8"), ("measured", "<f8"), ("torque", "<f8")])
HEADER_BYTES, JOINT_BYTES = _HEADER.itemsize, _JOINT.itemsize  # 32, 44


@functools.cache
def _wire(n_joints: int) -> np.dtype[Any]:
    """One record on the wire: the header, then ``n_joints`` joints (made once per joint count)."""
    layout: list[Any] = [*_HEADER.descr, ("joint", _JOINT, (n_joints,))]  # the header's fields at the top: one lookup less per field
    return np.dtype(layout)


def recording_seconds(t: NDArray[np.float64]) -> NDArray[np.float64]:
    """Times on a recording's clock: whole nanoseconds, ``sec + 1e-9 * nanosec`` (what a ROS 2
    stamp written from ``t`` reads back as)."""
    ns = np.round(np.asarray(t, float) * 1e9)
    finite = np.isfinite(ns)
    whole = np.where(finite, ns, 0).astype(np.int64)
    return np.where(finite, whole // 1_000_000_000 + 1e-9 * (whole % 1_000_000_000), t)


@dataclass(frozen=True, eq=False)
class JointStates:
    """Cycles of every joint: ``sequence``, ``cycle``, ``time`` (s) (n,); per joint (n, N):
    ``valid``, ``velocity_fresh``, ``position``, ``velocity``, ``commanded_current``,
    ``measured_current``, ``torque``, ``status``. SI units at the joint. ``torque`` is NaN
    where a source carried currents only (:func:`armid.identify.recordings.recording_of`
    applies the torque constants there, and only there)."""

    sequence: NDArray[np.int64]
    cycle: NDArray[np.int64]
    time: NDArray[np.float64]
    valid: NDArray[np.bool_]
    velocity_fresh: NDArray[np.bool_]
    position: NDArray[np.float64]
    velocity: NDArray[np.float64]
    commanded_current: NDArray[np.float64]
    measured_current: NDArray[np.float64]
    torque: NDArray[np.float64]
    status: NDArray[np.int64]

    @staticmethod
    def of_sample(sequence: int, s: Sample) -> JointStates:
        """The driver's sample as the record numbered ``sequence`` (views of its arrays)."""
        return JointStates(np.array([sequence], np.int64), np.array([s.cycle], np.int64), np.array([s.time_s], float),
                           np.asarray(s.valid, bool)[None], np.asarray(s.velocity_fresh, bool)[None], s.position[None], s.velocity[None], s.commanded_current[None],
                           s.measured_current[None], s.joint_torque()[None], np.asarray(s.status, np.int64)[None])

    @staticmethod
    def of_log(sequence: NDArray[Any], time: NDArray[Any], valid: NDArray[Any], position: NDArray[Any], torque: NDArray[Any]) -> JointStates:
        """Records of a log that holds positions and joint torques only (a CSV's rows, a test's
        arm): velocity and currents NaN, velocity fresh, status 0."""
        q = np.asarray(position, float)
        nan, count = np.full(q.shape, np.nan), np.asarray(sequence, np.int64)
        return JointStates(count, count.copy(), np.asarray(time, float), np.asarray(valid, bool).reshape(q.shape), np.ones(q.shape, bool), q,
                           nan, nan, nan, np.asarray(torque, float), np.zeros(q.shape, np.int64))

    @staticmethod
    def empty(n_joints: int) -> JointStates:
        z, b = np.zeros((0, n_joints)), np.zeros((0, n_joints), bool)
        return JointStates(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), b, b, z, z, z, z, z, np.zeros((0, n_joints), np.int64))

    @staticmethod
    def from_columns(columns: Mapping[str, NDArray[Any]]) -> JointStates:
        """The columns a recording's reader gives (``t`` for the time; ``torque`` absent where
        it recorded currents only, ``velocity_fresh`` and ``status`` absent where it did not say)."""
        q = np.asarray(columns["position"], float)
        n = q.shape[0]
        torque = columns.get("torque")
        return JointStates(np.asarray(columns["sequence"], np.int64), np.asarray(columns["cycle"], np.int64), np.asarray(columns["t"], float),
                           np.asarray(columns["valid"], bool).reshape(q.shape), np.asarray(columns.get("velocity_fresh", np.ones(q.shape, bool)), bool),
                           q, np.asarray(columns["velocity"], float), np.asarray(columns["commanded_current"], float),
                           np.asarray(columns["measured_current"], float), np.full(q.shape, np.nan) if torque is None else np.asarray(torque, float),
                           np.asarray(columns.get("status", np.zeros(q.shape, np.int64)), np.int64).reshape(n, -1))

    @staticmethod
    def concat(parts: Sequence[JointStates]) -> JointStates:
        """The records of ``parts`` one after the other (all of one arm)."""
        if len(parts) == 1:
            return parts[0]
        if not parts:
            raise ValueError("no records to concatenate")
        return JointStates(*(np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(JointStates)))

    def __len__(self) -> int:
        return int(self.sequence.shape[0])

    @property
    def n_joints(self) -> int:
        return int(self.position.shape[1])

    def __getitem__(self, index: slice | NDArray[Any]) -> JointStates:
        """The records at ``index`` (a slice, indices or a mask), as records."""
        return JointStates(*(getattr(self, f.name)[index] for f in fields(JointStates)))

    def unusable(self, velocity: bool = True) -> dict[str, NDArray[np.bool_]]:
        """Why each record cannot be used, by reason (a mask each; a record may have several):
        the one place that decides it, for identification (:func:`armid.identify.recordings.recording_of`,
        so for ``armid identify`` of a recording and the service alike) and the payload
        estimator. A joint flagged invalid, a time stamp, position or joint torque that is not
        finite, and (``velocity``: for a consumer that reads the drives' velocity) a velocity
        that is not finite on a cycle that says it is fresh. ``torque`` NaN throughout (a
        source of currents only) is for the caller to replace first."""
        why: dict[str, NDArray[np.bool_]] = {
            "flagged invalid": ~np.all(self.valid, axis=1), "time not finite": ~np.isfinite(self.time),
            "position not finite": ~np.all(np.isfinite(self.position), axis=1),
            "torque not finite": ~np.all(np.isfinite(self.torque), axis=1)}
        if velocity:
            why["velocity not finite"] = ~np.all(np.isfinite(self.velocity) | ~self.velocity_fresh, axis=1)
        return why

    def recorded(self) -> JointStates:
        """The records with their times on a recording's clock (:func:`recording_seconds`):
        the one place a time stamp is rounded."""
        return replace(self, time=recording_seconds(self.time))

    def record(self, k: int) -> JointStateRecord:
        """Record ``k`` as one numbered sample (views): the ROS 2 writer's input."""
        return JointStateRecord(int(self.sequence[k]), Sample(int(self.cycle[k]), float(self.time[k]), self.valid[k], self.position[k],
                                                              self.velocity[k], self.velocity_fresh[k], self.commanded_current[k],
                                                              self.measured_current[k], self.status[k], self.torque[k]))

    def pack(self) -> bytes:
        """The records as one Zenoh payload: each ``armid.JointState/2`` record, back to back."""
        out = np.zeros(len(self), _wire(self.n_joints))
        j = out["joint"]
        out["sequence"], out["cycle"], out["time"], out["joints"] = self.sequence, self.cycle, self.time, self.n_joints
        j["valid"], j["fresh"], j["status"] = self.valid, self.velocity_fresh, self.status
        j["position"], j["velocity"], j["commanded"], j["measured"], j["torque"] = (
            self.position, self.velocity, self.commanded_current, self.measured_current, self.torque)
        return out.tobytes()

    @staticmethod
    def unpack(data: bytes) -> JointStates:
        """A Zenoh payload's records (one or more, of one arm); :class:`RecordFormatError` naming
        what does not fit."""
        name = f"{SCHEMA}/{VERSION}"
        if len(data) < HEADER_BYTES:
            raise RecordFormatError(f"{name}: {len(data)} bytes, shorter than the {HEADER_BYTES}-byte header")
        n = int(np.frombuffer(data, _HEADER, 1)[0]["joints"])
        size = HEADER_BYTES + n * JOINT_BYTES
        if len(data) % size:
            raise RecordFormatError(f"{name}: {len(data)} bytes for records of {n} joints, not a whole number of {size}-byte records")
        out = np.frombuffer(data, _wire(n))
        j = out["joint"]
        if len(out) > 1 and np.any(out["joints"] != n):
            raise RecordFormatError(f"{name}: records of {sorted(set(out['joints'].tolist()))} joints in one payload; one arm's only")
        return JointStates(out["sequence"].astype(np.int64), out["cycle"].astype(np.int64), out["time"].astype(float),
                           j["valid"].astype(bool), j["fresh"].astype(bool), j["position"].copy(), j["velocity"].copy(),
                           j["commanded"].copy(), j["measured"].copy(), j["torque"].copy(), j["status"].astype(np.int64))

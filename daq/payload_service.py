"""The on-line payload estimator as a service: Zenoh stream in, estimates out.

It subscribes to ``armid/<robot>/joint_state``, folds every record into a
:class:`~identify.payload.PayloadRLS` on the record's own time stamp (no configured period),
and publishes ``armid/<robot>/estimate/payload`` (JSON, ``null`` for what is unknown, never
``NaN``) on every record whose sequence number is a multiple of ``publish_every`` (10: 50 Hz
at 2 ms). It holds the liveliness token ``armid/<robot>/alive/payload_estimator`` and
answers ``armid/<robot>/status``. The subscriber callback only queues bytes; a worker
thread does the estimation, so the stream is never held up. When the worker falls more
than ``max_backlog_s`` of the arm's time behind (the records' own time stamps: the same
threshold at 100 Hz and at 1 kHz) it skips to the newest, restarts the derivative filter
and says how many records it skipped; a gap in the sequence numbers does the same.

:class:`EstimateStream` is the part shared with replay: records in, the estimate documents
that would be published out. ``armid estimate --replay`` runs it on a recording, so its
output is what the service would have published.
"""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from identify.errors import RecordingError
from identify.payload import PayloadRLS
from identify.spatial import Array

from .record_format import JointStateRecord, check_encoding
from .stream import key


class EstimateStream:
    """Records in sequence order -> the documents to publish (pure, no I/O)."""

    def __init__(self, estimator: PayloadRLS, torque_constants: Array, publish_every: int = 10, strict_time: bool = False,
                 source: str = "stream") -> None:
        """``strict_time``: a record whose time is not after the previous one is refused
        (:class:`RecordingError`, for a recording); otherwise it is dropped, counted in
        ``time_faults`` and the derivatives restart (a live stream whose clock stepped)."""
        if publish_every < 1:
            raise ValueError(f"publish_every must be at least 1, got {publish_every}")
        self.estimator = estimator
        self.kt = np.asarray(torque_constants, float)
        self.publish_every = publish_every
        self.strict_time = strict_time
        self.source = source
        self.last_sequence: int | None = None
        self.last_time: float | None = None
        self.skipped = 0
        self.lost = 0
        self.invalid = 0
        self.time_faults = 0

    def skip(self, count: int) -> None:
        """``count`` records will not be seen: the derivatives start again after them."""
        self.skipped += count
        self.last_sequence = None  # skipped, not lost: the next record's number is no gap
        self.estimator.restart_filter()

    def feed(self, records: Iterable[tuple[int, float, Array, Array, Array]]) -> list[dict[str, Any]]:
        """(sequence, time, valid, position, measured current) per record; returns what to publish.

        The same as :meth:`feed_arrays` on the records stacked."""
        rows = list(records)
        if not rows:
            return []
        seq, t, valid, q, current = zip(*rows)
        return self.feed_arrays(np.array(seq, np.int64), np.array(t, float), np.array(valid, bool), np.array(q, float),
                                np.array(current, float))

    def feed_arrays(self, seq: Array, t: Array, valid: Array, q: Array, current: Array) -> list[dict[str, Any]]:
        """Records as arrays, in sequence order: sequence numbers (n,), times (n,) in s, valid
        flags, positions and measured currents (n, N). Returns the documents to publish, one on
        every record whose sequence number is a multiple of ``publish_every``.

        Runs of consecutive valid records go to the estimator in one batch each; a gap in
        the sequence numbers or an invalid record restarts the derivative filter; a record
        whose time is not after the one before is refused (``strict_time``) or dropped and
        counted in ``time_faults`` (the clock stepped: the derivatives restart)."""
        out: list[dict[str, Any]] = []
        n = int(np.size(t))
        if n == 0:
            return out
        seq = np.asarray(seq, np.int64)
        t = np.asarray(t, float)
        valid = np.asarray(valid, bool).reshape(n, -1)
        prev_t = np.concatenate([[-np.inf if self.last_time is None else self.last_time], t[:-1]])
        prev_s = np.concatenate([[seq[0] - 1 if self.last_sequence is None else self.last_sequence], seq[:-1]])
        fault = ~(t > prev_t)
        gap = ~fault & (seq != prev_s + 1)
        bad = ~fault & ~valid.all(axis=1)
        torque = np.asarray(current, float) * self.kt

        def flush(a: int, b: int) -> None:
            if b <= a:
                return
            marks = np.flatnonzero(seq[a:b] % self.publish_every == 0)
            snaps: list[dict[str, Any]] = []
            extra: list[dict[str, Any]] = []

            def publish(k: int) -> None:  # the state now; the documents (and their projections) after the batch
                snaps.append(self.estimator.snapshot())
                extra.append({"sequence": int(seq[a + k]), "record_time": float(t[a + k]), "skipped": self.skipped, "lost": self.lost,
                              "invalid": self.invalid, "time_faults": self.time_faults})

            self.estimator.partial_fit(t[a:b], q[a:b], torque[a:b], marks.tolist(), publish)
            for doc, more in zip(self.estimator.estimates(snaps), extra):
                doc.update(more)
                out.append(doc)

        start = 0
        for k in np.flatnonzero(fault | gap | bad).tolist():
            flush(start, k)
            start = k + 1
            if fault[k]:
                if self.strict_time:
                    raise RecordingError(self.source, f"record {seq[k]}: time {t[k]:.6g} s is not after the previous record's "
                                                      f"{prev_t[k]:.6g} s (time going backwards or repeated); refused")
                self.time_faults += 1  # the clock stepped: go on from its new time
                self.estimator.restart_filter()
                continue
            if gap[k]:
                self.lost += max(0, int(seq[k] - prev_s[k] - 1))
                self.estimator.restart_filter()
                start = k
            if bad[k]:
                self.invalid += 1
                self.estimator.restart_filter()
                start = k + 1
        flush(start, n)
        self.last_sequence, self.last_time = int(seq[-1]), float(t[-1])
        return out


def _from_record(r: JointStateRecord) -> tuple[int, float, Array, Array, Array]:
    """The record's time as the recording keeps it (whole nanoseconds, ``sec + 1e-9 nsec``):
    the estimator differentiates on time stamps, so live and replay see the same floats."""
    s = r.sample
    ns = int(round(s.time_s * 1e9))
    return r.sequence, ns // 1_000_000_000 + 1e-9 * (ns % 1_000_000_000), s.valid, s.position, s.measured_current


class PayloadService:
    """Run an :class:`EstimateStream` on a Zenoh session until :meth:`close`."""

    def __init__(self, session: Any, robot: str, stream: EstimateStream, max_backlog_s: float = 0.5,
                 on_estimate: Callable[[dict[str, Any]], None] | None = None) -> None:
        import zenoh

        if not max_backlog_s > 0:
            raise ValueError(f"max_backlog_s must be a positive number of seconds, got {max_backlog_s}")
        self.session = session
        self.robot = robot
        self.stream = stream
        self.max_backlog_s = max_backlog_s
        self.behind = 0  # times the worker fell behind and skipped
        self.on_estimate = on_estimate
        self._pending: deque[bytes] = deque()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.published = 0
        self.errors: list[str] = []
        self.last: dict[str, Any] | None = None
        self._pub = session.declare_publisher(key(robot, "estimate/payload"), encoding=zenoh.Encoding.APPLICATION_JSON)
        self._token = session.liveliness().declare_token(key(robot, "alive/payload_estimator"))
        self._queryable = session.declare_queryable(key(robot, "status"), self._on_query)
        self._sub = session.declare_subscriber(key(robot, "joint_state"), self._on_sample)
        self._thread = threading.Thread(target=self._run, name="armid-payload", daemon=True)
        self._thread.start()

    def _on_sample(self, sample: Any) -> None:
        try:
            check_encoding(str(sample.encoding))
            self._pending.append(sample.payload.to_bytes())
            self._wake.set()
        except Exception as err:  # a callback never kills the receive thread
            if len(self.errors) < 100:
                self.errors.append(f"{type(err).__name__}: {err}")

    @property
    def backlog(self) -> int:
        """Records received and not yet estimated on."""
        return len(self._pending)

    def _on_query(self, query: Any) -> None:
        st = self.stream
        doc = {"component": "payload_estimator", "updates": st.estimator.n_updates_ if hasattr(st.estimator, "n_updates_") else 0,
               "published": self.published, "skipped": st.skipped, "lost": st.lost, "invalid": st.invalid,
               "backlog": len(self._pending), "behind": self.behind, "last": self.last}
        query.reply(key(self.robot, "status"), json.dumps(doc))

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.1)
            self._wake.clear()
            batch = []
            while self._pending:
                batch.append(self._pending.popleft())
            if not batch:
                continue
            try:
                records = [_from_record(JointStateRecord.unpack(b)) for b in batch]
                if records[-1][1] - records[0][1] > self.max_backlog_s:
                    # behind by more than max_backlog_s of the arm's time: the newest record only
                    self.behind += 1
                    self.stream.skip(len(records) - 1)
                    records = records[-1:]
                for doc in self.stream.feed(records):
                    self._pub.put(json.dumps(doc))
                    self.published += 1
                    self.last = doc
                    if self.on_estimate:
                        self.on_estimate(doc)
            except Exception as err:
                if len(self.errors) < 100:
                    self.errors.append(f"{type(err).__name__}: {err}")

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(2.0)
        for entity in (self._sub, self._queryable, self._token, self._pub):
            try:
                entity.undeclare()
            except Exception:  # already gone with the session
                pass


def wait_for(predicate: Callable[[], bool], timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()

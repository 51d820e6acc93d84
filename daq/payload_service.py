"""The on-line payload estimator as a service: Zenoh stream in, estimates out.

It subscribes to ``armid/<robot>/joint_state``, folds every record into a
:class:`~identify.payload.PayloadRLS` on the record's own time stamp (no configured period),
and publishes ``armid/<robot>/estimate/payload`` (JSON, ``null`` for what is unknown, never
``NaN``) on every record whose sequence number is a multiple of ``publish_every`` (10: 50 Hz
at 2 ms). It holds the liveliness token ``armid/<robot>/alive/payload_estimator`` and
answers ``armid/<robot>/status``. The subscriber callback only queues bytes; a worker
thread does the estimation, so the stream is never held up. When the worker falls more
than ``max_backlog`` records behind it skips to the newest, restarts the derivative filter
and says how many it skipped; a gap in the sequence numbers does the same.

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

from armid.identify.errors import RecordingError
from armid.identify.payload import PayloadRLS
from armid.schema import Array
from armid.schema.joint_state import JointStateRecord, check_encoding

from .stream import key


class EstimateStream:
    """Records in sequence order -> the documents to publish (pure, no I/O)."""

    def __init__(self, estimator: PayloadRLS, publish_every: int = 10, strict_time: bool = False, source: str = "stream") -> None:
        """``strict_time``: a record whose time is not after the previous one is refused
        (:class:`RecordingError`, for a recording); otherwise it is dropped, counted in
        ``time_faults`` and the derivatives restart (a live stream whose clock stepped)."""
        if publish_every < 1:
            raise ValueError(f"publish_every must be at least 1, got {publish_every}")
        self.estimator = estimator
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
        self.estimator.restart_filter()

    def feed(self, records: Iterable[tuple[int, float, Array, Array, Array]]) -> list[dict[str, Any]]:
        """(sequence, time, valid, position, torque) per record, SI (the driver applied the torque
        constants); returns what to publish.

        Runs of consecutive valid records go to the estimator in one batch each; a gap in
        the sequence numbers or an invalid record restarts the derivative filter."""
        out: list[dict[str, Any]] = []
        run: list[tuple[int, float, Array, Array]] = []

        def flush() -> None:
            if not run:
                return
            seqs = [x[0] for x in run]

            def publish(k: int) -> None:
                doc = self.estimator.estimate()
                doc.update({"sequence": int(seqs[k]), "record_time": float(run[k][1]), "skipped": self.skipped, "lost": self.lost,
                            "invalid": self.invalid, "time_faults": self.time_faults})
                out.append(doc)

            self.estimator.partial_fit(np.array([x[1] for x in run]), np.array([x[2] for x in run]), np.array([x[3] for x in run]),
                                       [k for k, sq in enumerate(seqs) if sq % self.publish_every == 0], publish)
            run.clear()

        for seq, t, valid, q, torque in records:
            if self.last_time is not None and not t > self.last_time:
                if self.strict_time:
                    flush()
                    raise RecordingError(self.source, f"record {seq}: time {t:.6g} s is not after the previous record's "
                                                      f"{self.last_time:.6g} s (time going backwards or repeated); refused")
                flush()
                self.time_faults += 1  # the clock stepped: go on from its new time
                self.estimator.restart_filter()
                self.last_sequence, self.last_time = seq, t
                continue
            self.last_time = t
            if self.last_sequence is not None and seq != self.last_sequence + 1:
                flush()
                self.lost += max(0, seq - self.last_sequence - 1)
                self.estimator.restart_filter()
            self.last_sequence = seq
            if not np.all(valid):
                flush()
                self.invalid += 1
                self.estimator.restart_filter()
                continue
            run.append((seq, t, q, np.asarray(torque, float)))
        flush()
        return out


def _from_record(r: JointStateRecord) -> tuple[int, float, Array, Array, Array]:
    """The record's time as the recording keeps it (whole nanoseconds, ``sec + 1e-9 nsec``):
    the estimator differentiates on time stamps, so live and replay see the same floats."""
    s = r.sample
    ns = int(round(s.time_s * 1e9))
    return r.sequence, ns // 1_000_000_000 + 1e-9 * (ns % 1_000_000_000), s.valid, s.position, s.joint_torque()


class PayloadService:
    """Run an :class:`EstimateStream` on a Zenoh session until :meth:`close`."""

    def __init__(self, session: Any, robot: str, stream: EstimateStream, max_backlog: int = 250,
                 on_estimate: Callable[[dict[str, Any]], None] | None = None) -> None:
        import zenoh

        self.session = session
        self.robot = robot
        self.stream = stream
        self.max_backlog = max_backlog
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
               "backlog": len(self._pending), "last": self.last}
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
            if len(batch) > self.max_backlog:
                self.stream.skip(len(batch) - 1)  # behind: the newest record only
                batch = batch[-1:]
            try:
                records = [_from_record(JointStateRecord.unpack(b)) for b in batch]
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

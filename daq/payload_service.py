"""The on-line payload estimator as a service: Zenoh stream in, estimates out.

It subscribes to ``armid/<robot>/joint_state``, folds every record into a
:class:`~identify.payload.PayloadRLS` on the record's own time stamp (no configured period),
and publishes ``armid/<robot>/estimate/payload`` (JSON, ``null`` for what is unknown, never
``NaN``) on every record whose sequence number is a multiple of ``publish_every`` (10: 50 Hz
at 2 ms). It holds the liveliness token ``armid/<robot>/alive/payload_estimator`` and
answers ``armid/<robot>/status``. The subscriber callback only queues bytes; a worker
thread does the estimation, so the stream is never held up. When the worker falls more
than ``max_backlog_s`` of the arm's time behind (the records' own time stamps: the same
threshold at 100 Hz and at 1 kHz) it catches up if it can do so in at most ``max_backlog_s``
of its own CPU time (a busy machine stalled it: nothing is lost), else it skips to the newest,
restarts the derivative filter and says how many records it skipped and why (a slow
estimator); a gap in the sequence numbers restarts the filter too.

:class:`EstimateStream` is the part shared with replay: records in, the estimate documents
that would be published out. ``armid estimate --replay`` runs it on a recording, so its
output is what the service would have published.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from armid.identify.errors import RecordingError
from armid.identify.payload.rls import PayloadRLS
from armid.schema import Array
from armid.schema.joint_state import check_encoding
from armid.schema.joint_states import JointStates

from .stream import key

RESYNC_RECORDS = 10
"""This many consecutive records on a timeline of their own (each after the one before, the
last accepted record's time not) are a clock that stepped: the stream follows it."""
REORDER_RECORDS = 16
"""The service holds at most this many records back waiting for an earlier one (32 ms at 2 ms)."""
JUMP_MIN_S, JUMP_STEPS = 1.0, 100.0
"""A record further ahead of the last accepted one than 1 s and 100 typical steps per
sequence number is a time jump (a corrupt stamp): dropped, unless the stream stays there."""

STOP_WAIT_S = 30.0
"""How long :meth:`PayloadService.close` waits for the worker's batch to end. A batch is at most
``max_backlog_s`` of its CPU time (the catch-up rule) or one record, but a loaded machine
stretches that several-fold in wall time: at 2 s a service stopped beside two busy loops left
the worker inside a batch, and the interpreter's exit aborted the process (SIGABRT)."""


class EstimateStream:
    """Records in sequence order -> the documents to publish (pure, no I/O).

    Every record is screened before the estimator sees it (:meth:`_screen`): one that is not
    finite, flagged invalid, late, or stamped far ahead of the stream is dropped, counted by
    reason in ``dropped`` (the last one in ``last_drop``) and the derivatives restart; the
    records around it go on. A clock that stepped is followed after ``RESYNC_RECORDS``."""

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
        self.resyncs = 0
        self.dropped: dict[str, int] = {}
        self.last_drop: str | None = None
        self.typical_step: float | None = None
        self._last_taken_sequence = 0
        self._clock_offset = 0.0  # the estimator's clock minus the records' (the steps of a stepped clock)
        self._other_timeline: list[float] = []

    def drop(self, reason: str, detail: str) -> None:
        """Count a record that is not used, by reason; say the last one."""
        self.dropped[reason] = self.dropped.get(reason, 0) + 1
        self.last_drop = detail

    def skip(self, count: int) -> None:
        """``count`` records will not be seen: the derivatives start again after them."""
        self.skipped += count
        self.last_sequence = None  # skipped, not lost: the next record's number is no gap
        self.estimator.restart_filter()

    def final(self) -> dict[str, Any]:
        """The run's one answer (:meth:`PayloadRLS.final_estimate`) with what the stream did not
        use; a replay writes it last."""
        return {**self.estimator.final_estimate(), "sequence": self.last_sequence, "record_time": self.last_time, **self.counts()}

    def counts(self) -> dict[str, Any]:
        """What the stream did not use so far, as every document and the status carry it."""
        return {"skipped": self.skipped, "lost": self.lost, "invalid": self.invalid, "time_faults": self.time_faults,
                "dropped": dict(self.dropped), "last_drop": self.last_drop}

    def _screen(self, records: JointStates) -> tuple[NDArray[np.bool_], NDArray[np.bool_], list[dict[str, Any]], Array]:
        """Which records the estimator takes, before which the derivatives restart (a gap in
        the sequence numbers, a dropped record, a stepped clock), the counts after each, and
        each record's time on the estimator's clock (a stepped clock's step taken out: the
        estimator's time never goes back).
        Sequential: each record is judged against the last *accepted* one, so one bad stamp
        costs one record, not the stream."""
        seq, t, q, torque = records.sequence, records.time, records.position, records.torque
        n = t.size
        take = np.zeros(n, bool)
        restart = np.zeros(n, bool)
        after: list[dict[str, Any]] = []
        counts = self.counts()
        unusable = records.unusable(velocity=False)  # the one judgement identification makes too; the velocity is not read here
        flagged = ~unusable.pop("flagged invalid")
        finite = ~np.logical_or.reduce(list(unusable.values()))
        shifted = np.empty(n)
        for k, (sk, tk) in enumerate(zip(seq.tolist(), t.tolist())):
            take[k], restart[k] = self._judge(sk, tk, bool(finite[k]), bool(flagged[k]), q[k], torque[k])
            shifted[k] = tk + self._clock_offset
            if not take[k] or restart[k]:
                counts = self.counts()
            after.append(counts)
        return take, restart, after, shifted

    def _judge(self, sk: int, tk: float, finite: bool, flagged: bool, q: Array, torque: Array) -> tuple[bool, bool]:
        """(taken, restart before it) for one record; counts what is not taken."""
        if self.last_sequence is not None and sk <= self.last_sequence:
            self.drop("out of order", f"record {sk} came after record {self.last_sequence}")
            return False, False
        gap = self.last_sequence is not None and sk != self.last_sequence + 1
        if gap:
            self.lost += sk - self.last_sequence - 1  # type: ignore[operator]
        self.last_sequence = sk  # received: not lost, whatever becomes of it
        if not finite:
            what = "time" if not np.isfinite(tk) else "position" if not np.isfinite(q).all() else "torque"
            self.drop("not finite", f"record {sk}: {what} not finite (NaN or infinite)")
            return False, True
        if not flagged:
            self.invalid += 1
            return False, True
        if self.last_time is not None and not self._on_timeline(sk, tk):
            return False, True
        if self.last_time is not None and not gap:
            step = tk - self.last_time
            self.typical_step = step if self.typical_step is None else self.typical_step + 0.05 * (step - self.typical_step)
        self.last_time, self._last_taken_sequence = tk, sk
        return True, gap

    def _on_timeline(self, sequence: int, time_s: float) -> bool:
        """Whether a record's time follows the last accepted one; if not, it is dropped, and
        ``RESYNC_RECORDS`` in a row on a timeline of their own move the stream there."""
        step = time_s - (self.last_time or 0.0)
        typical = self.typical_step or 0.0
        ahead = self.typical_step is not None and step > max(JUMP_MIN_S, JUMP_STEPS * typical * max(1, sequence - self._last_taken_sequence))
        if step > 0 and not ahead:
            self._other_timeline.clear()
            return True
        other = self._other_timeline
        if other and not (other[-1] < time_s <= other[-1] + max(JUMP_MIN_S, JUMP_STEPS * typical)):
            other.clear()
        other.append(time_s)
        if len(other) >= RESYNC_RECORDS:  # the clock stepped and stays there: follow it
            self.resyncs += 1
            self.time_faults += 1
            other.clear()
            self._clock_offset += (self.last_time or 0.0) + typical - time_s
            self.last_time, self._last_taken_sequence = time_s, sequence
            self.drop("time", f"record {sequence}: the clock stepped to {time_s:.6g} s; followed after {RESYNC_RECORDS} records")
            return False
        if self.strict_time and step <= 0:
            raise RecordingError(self.source, f"record {sequence}: time {time_s:.6g} s is not after the previous record's "
                                              f"{self.last_time:.6g} s (time going backwards or repeated); refused")
        self.time_faults += 1
        self.drop("time", f"record {sequence}: time {time_s:.6g} s " + (f"jumps {step:.6g} s ahead of the stream" if ahead else
                  f"is not after the previous record's {self.last_time:.6g} s"))
        return False

    def feed(self, records: JointStates) -> list[dict[str, Any]]:
        """Records in sequence order, on the time stamps they carry (the service's are on the
        recording's clock: :meth:`JointStates.recorded`); the estimator takes their sequence
        numbers, times, valid flags, positions and joint torques, SI. Returns the documents to
        publish, one on every record whose sequence number is a multiple of ``publish_every``.

        Runs of consecutive accepted records go to the estimator in one batch each; the
        derivative filter restarts where :meth:`_screen` says."""
        out: list[dict[str, Any]] = []
        n = len(records)
        if n == 0:
            return out
        seq, t, q, torque = records.sequence, records.time, records.position, records.torque
        take, restart, counts, clock = self._screen(records)

        def flush(a: int, b: int) -> None:
            if b <= a:
                return
            marks = np.flatnonzero(seq[a:b] % self.publish_every == 0)
            snaps: list[dict[str, Any]] = []
            extra: list[dict[str, Any]] = []

            def publish(k: int) -> None:  # the state now; the documents (and their projections) after the batch
                snaps.append(self.estimator.snapshot())
                extra.append({"sequence": int(seq[a + k]), "record_time": float(t[a + k]), **counts[a + k]})

            self.estimator.partial_fit(clock[a:b], q[a:b], torque[a:b], marks.tolist(), publish)
            for doc, more in zip(self.estimator.estimates(snaps), extra):
                doc.update(more)
                out.append(doc)

        start = 0
        for k in range(n):
            if restart[k] or not take[k]:
                flush(start, k)
                start = k + 1 if not take[k] else k
                if restart[k]:
                    self.estimator.restart_filter()
        flush(start, n)
        return out


class PayloadService:
    """Run an :class:`EstimateStream` on a Zenoh session until :meth:`close`."""

    def __init__(self, session: Any, robot: str, stream: EstimateStream, max_backlog_s: float = 0.5,
                 on_estimate: Callable[[dict[str, Any]], None] | None = None, log: Callable[[str], None] | None = None) -> None:
        """``log`` is told, in words, each time the worker falls behind and skips: how far, and
        whether it was computing or not running (the figures that tell a slow estimator from a
        busy machine)."""
        import zenoh

        if not max_backlog_s > 0:
            raise ValueError(f"max_backlog_s must be a positive number of seconds, got {max_backlog_s}")
        # nothing runs for the first time once records arrive: the projection's compiled kernel
        # loads in about 1 s holding the interpreter, which stalled a bus loop in the same process
        stream.estimator.warm()
        self.session = session
        self.robot = robot
        self.stream = stream
        self.max_backlog_s = max_backlog_s
        self.behind = 0  # times the worker fell behind and skipped
        self.caught_up = 0  # times it fell behind and caught up (a stall, not a slow estimator)
        self.on_estimate = on_estimate
        self.log = log
        self._clock = _WorkerClock()
        self._pending: deque[tuple[float, bytes]] = deque()  # (arrival on the monotonic clock, record)
        self._held: JointStates | None = None  # the reorder buffer, in sequence order
        self._released: int | None = None
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.published = 0
        self.errors: list[str] = []
        self.last: dict[str, Any] | None = None
        self.wrong_encoding = 0  # puts refused for their encoding (the callback counts, the worker files them as drops)
        self._wrong_encoding_said: str | None = None
        self._wrong_encoding_filed = 0
        self._said: set[str] = set()  # the kinds of drop said so far (each said once, then counted)
        self._pub = session.declare_publisher(key(robot, "estimate/payload"), encoding=zenoh.Encoding.APPLICATION_JSON)
        self._token = session.liveliness().declare_token(key(robot, "alive/payload_estimator"))
        self._queryable = session.declare_queryable(key(robot, "status"), self._on_query)
        self._sub = session.declare_subscriber(key(robot, "joint_state"), self._on_sample)
        self._thread = threading.Thread(target=self._run, name="armid-payload", daemon=True)
        self._thread.start()

    def _on_sample(self, sample: Any) -> None:
        try:
            check_encoding(str(sample.encoding))
        except Exception as err:  # another schema's copy: refused, counted (a callback never kills the receive thread)
            self._wrong_encoding_said = str(err)
            self.wrong_encoding += 1
            self._wake.set()
            return
        try:
            self._pending.append((time.monotonic(), sample.payload.to_bytes()))
            self._wake.set()
        except Exception as err:  # a callback never kills the receive thread
            if len(self.errors) < 100:
                self.errors.append(f"{type(err).__name__}: {err}")

    def _file_refused(self) -> None:
        """The puts the callback refused for their encoding, counted among the stream's drops."""
        n = self.wrong_encoding - self._wrong_encoding_filed
        if n > 0:
            self._wrong_encoding_filed += n
            self.stream.dropped["encoding"] = self.stream.dropped.get("encoding", 0) + n
            self.stream.last_drop = f"a put refused: {self._wrong_encoding_said}"

    def _say_drops(self) -> None:
        """Each kind of record not used, said once as it first happens (then counted: the
        status, every document and the summary carry the counts)."""
        if self.log is None:
            return
        st = self.stream
        for reason in st.dropped:
            if reason not in self._said:
                self._said.add(reason)
                self.log(f"dropped a record ({reason}): {st.last_drop}; further ones counted")
        if st.invalid and "invalid" not in self._said:
            self._said.add("invalid")
            self.log("a record flagged invalid by its driver is not used; further ones counted")

    @property
    def running(self) -> bool:
        """The worker is still inside a batch (after :meth:`close`: it outlived ``STOP_WAIT_S``)."""
        return self._thread.is_alive()

    @property
    def backlog(self) -> int:
        """Records received and not yet estimated on."""
        return len(self._pending)

    def _on_query(self, query: Any) -> None:
        st = self.stream
        doc = {"component": "payload_estimator", "updates": st.estimator.n_updates_ if hasattr(st.estimator, "n_updates_") else 0,
               "published": self.published, **st.counts(), "backlog": len(self._pending), "behind": self.behind,
               "caught_up": self.caught_up, "last": self.last}
        query.reply(key(self.robot, "status"), json.dumps(doc))

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.1)
            self._wake.clear()
            self._file_refused()
            self._say_drops()
            batch = []
            while self._pending:
                batch.append(self._pending.popleft())
            if not batch and self._held is None:
                continue
            waited_s = time.monotonic() - batch[0][0] if batch else 0.0
            try:
                records = self._in_order(self._records([b for _, b in batch]), idle=not batch)
                if records is None:
                    continue
                records = self._caught_up_or_newest(records, waited_s)
                self._clock.start()
                for doc in self.stream.feed(records):
                    self._pub.put(json.dumps(doc))
                    self.published += 1
                    self.last = doc
                    if self.on_estimate:
                        self.on_estimate(doc)
                self._clock.stop(len(records))
                self._say_drops()
            except Exception as err:
                if len(self.errors) < 100:
                    self.errors.append(f"{type(err).__name__}: {err}")

    def _caught_up_or_newest(self, records: JointStates, waited_s: float) -> JointStates:
        """A batch more than ``max_backlog_s`` of the arm's time behind: all of it when the
        worker can catch up in at most ``max_backlog_s`` of its CPU time (a busy machine
        stalled it; a cold-start payload run beside two busy loops skipped 539 records that
        would have taken it about 0.1 s), else the newest record only, the skip said and counted."""
        behind_s = self._behind_s(records)
        if behind_s <= self.max_backlog_s:
            return records
        catch_up_s = self._clock.cost_per_record * len(records)  # its CPU time to catch up (inf before a batch)
        if catch_up_s <= self.max_backlog_s:
            self.caught_up += 1
            return records
        self.behind += 1
        self.stream.skip(len(records) - 1)
        if self.log is not None:
            self.log(f"{behind_s:.2f} s of the arm's time behind: skipped {len(records) - 1} records to the newest (catching up would "
                     f"take {catch_up_s:.3g} s of its CPU time); the oldest waited {waited_s:.3f} s here; " + self._clock.since_last())
        return records[len(records) - 1 :]

    @staticmethod
    def _behind_s(records: JointStates) -> float:
        """How much of the arm's time the batch spans: its steps' median times their count
        (one corrupt stamp in the batch is not a backlog)."""
        if len(records) < 2:
            return 0.0
        steps = np.diff(records.time)
        return float(np.median(steps)) * steps.size if np.isfinite(steps).all() else 0.0

    def _in_order(self, records: JointStates | None, idle: bool) -> JointStates | None:
        """Records released in sequence order (a reorder buffer): a record waits while the one
        before it may still come, up to ``REORDER_RECORDS`` records or until the stream goes
        idle for a wake interval; then the gap is a gap. A sequence number received twice: the
        later record."""
        parts = [p for p in (self._held, records) if p is not None]
        if not parts:
            return None
        held = JointStates.concat(parts)
        newest_first = held.sequence[::-1]
        _, at = np.unique(newest_first, return_index=True)  # sorted, the later of each number
        held = held[len(held) - 1 - at]
        seqs = held.sequence.tolist()
        last, cut = self._released, len(seqs)
        for k, first in enumerate(seqs):
            if last is not None and first > last + 1 and len(seqs) - k <= REORDER_RECORDS and not idle:
                cut = k
                break
            last = first if last is None else max(last, first)
        self._released = last
        self._held = held[cut:] if cut < len(seqs) else None
        return held[:cut] if cut else None

    def _records(self, batch: list[bytes]) -> JointStates | None:
        """The batch's records on the recording's clock (:meth:`_in_order` orders them); a
        payload that cannot be read or is of another arm is dropped, counted and said, never the batch."""
        n_joints = self.stream.estimator.arm.robot.n_joints
        parts = []
        for b in batch:
            try:
                r = JointStates.unpack(b)
            except Exception as err:  # the payload's own bytes: nothing else is lost with it
                self.stream.drop("malformed", f"a record of {len(b)} bytes could not be read: {err}")
                continue
            if r.n_joints != n_joints:
                self.stream.drop("joints", f"record {int(r.sequence[0])} has {r.n_joints} joints; this arm has {n_joints}")
                continue
            parts.append(r)
        return JointStates.concat(parts).recorded() if parts else None

    def request_stop(self) -> None:
        """Ask the worker to stop after its batch (:meth:`close` then waits for it)."""
        self._stop.set()
        self._wake.set()

    def close(self, wait_s: float = STOP_WAIT_S) -> None:
        """Stop the worker after its batch (waiting up to ``wait_s``), then leave the session."""
        self.request_stop()
        self._thread.join(wait_s)
        for entity in (self._sub, self._queryable, self._token, self._pub):
            try:
                entity.undeclare()
            except Exception:  # already gone with the session
                pass


class _WorkerClock:
    """How the worker spent its last batch and the time since: computing (its own CPU time) or
    not running (descheduled, or waiting for the interpreter lock), so that a skip says which;
    and what a record costs it in CPU time over its recent batches (what catching up a backlog
    would take)."""

    DECAY = 0.99  # per record: the cost follows the last hundred records or so, whatever the batches

    def __init__(self) -> None:
        self._start: tuple[float, float, float] | None = None  # wall, the worker's CPU, the process's CPU
        self._last: tuple[float, float, float, float] | None = None  # wall, the worker's CPU, the process's CPU taken; wall at its end
        self._cpu = self._records = 0.0  # decayed sums over the batches: the worker's CPU time, the records it fed

    def start(self) -> None:
        self._start = time.monotonic(), time.thread_time(), time.process_time()

    def stop(self, records: int) -> None:
        """The batch of ``records`` is done."""
        if self._start is not None:
            wall = time.monotonic()
            self._last = wall - self._start[0], time.thread_time() - self._start[1], time.process_time() - self._start[2], wall
            kept = self.DECAY**records
            self._cpu = kept * self._cpu + self._last[1]
            self._records = kept * self._records + records

    @property
    def cost_per_record(self) -> float:
        """CPU seconds the worker spends on a record (inf before it knows)."""
        return self._cpu / self._records if self._records > 0 else float("inf")

    def since_last(self) -> str:
        """The batch before: its wall time and the CPU time in it; then the wait until now."""
        load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
        where = f"load average {load:.1f} on {os.cpu_count()} CPUs"
        if self._last is None:
            return f"the first batch; {where}"
        wall, cpu, process, end = self._last
        return (f"the batch before took {wall:.3f} s, {cpu:.3f} s of it computing (this process's threads {process:.3f} s), "
                f"and ended {time.monotonic() - end:.3f} s ago; {where}")


def wait_for(predicate: Callable[[], bool], timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()

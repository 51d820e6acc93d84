"""Acquisition: one record per cycle from a driver, fanned out without ever waiting.

The acquisition thread reads the driver's samples (one per SYNC cycle, keyed by the cycle
counter, with late joints already marked invalid by the driver's deadline), numbers them
with a gap-free sequence, and hands each to its sinks through their own queues. The
recorder's queue is unbounded, so that no record is ever dropped for the disk. A
streaming or estimating sink has a bounded queue that drops its oldest record when full,
and counts the drops. A slow subscriber, disk or estimator therefore never holds up the
next cycle. Stale data (a joint whose position has not changed for ``stale_cycles`` while
commanded) is counted per joint.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from armid.drivers.interface import DriveFault, Driver, DriverError
from armid.schema.joint_state import JointStateRecord

Handler = Callable[[JointStateRecord], None]


@dataclass
class Sink:
    """A consumer on its own thread; ``bounded`` sinks drop their oldest record when behind."""

    name: str
    handle: Handler
    bounded: bool = True
    capacity: int = 1000
    dropped: int = 0
    handled: int = 0
    errors: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.queue: queue.Queue[JointStateRecord | None] = queue.Queue(self.capacity if self.bounded else 0)
        self.thread = threading.Thread(target=self._run, name=f"armid-sink-{self.name}", daemon=True)

    def offer(self, record: JointStateRecord | None) -> None:
        while True:
            try:
                self.queue.put_nowait(record)
                return
            except queue.Full:
                try:
                    self.queue.get_nowait()
                    self.dropped += 1
                except queue.Empty:
                    pass

    def _run(self) -> None:
        while True:
            record = self.queue.get()
            if record is None:
                return
            try:
                self.handle(record)
                self.handled += 1
            except Exception as err:  # a sink's fault must not stop acquisition
                if len(self.errors) < 100:
                    self.errors.append(f"{type(err).__name__}: {err}")


class Acquisition:
    """Read ``driver`` on a thread; ``on_fault`` hears of drive faults (acquisition goes on);
    ``on_sample`` runs inline on every record (a control law: it must be fast)."""

    def __init__(self, driver: Driver, sinks: list[Sink], on_fault: Callable[[DriveFault], None] | None = None,
                 stale_cycles: int = 50, on_sample: Callable[[JointStateRecord], None] | None = None) -> None:
        self.driver = driver
        self.on_sample = on_sample  # inline, before the sinks: the control law of excitation
        self.sinks = sinks
        self.on_fault = on_fault
        self.stale_cycles = stale_cycles
        self.sequence = 0
        self.invalid = np.zeros(driver.n_joints, np.int64)
        self.stale = np.zeros(driver.n_joints, np.int64)
        self._stale_run = np.zeros(driver.n_joints, np.int64)
        self._last_position: np.ndarray | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="armid-acquisition", daemon=True)
        self.error: str | None = None
        self.last: JointStateRecord | None = None

    def start(self) -> None:
        for s in self.sinks:
            s.thread.start()
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                sample = self.driver.read(timeout=1.0)
            except DriveFault as fault:
                if self.on_fault:
                    self.on_fault(fault)
                continue
            except DriverError as err:
                self.error = str(err)
                break
            self.invalid += ~sample.valid
            if self._last_position is not None:
                same = (sample.position == self._last_position) & (sample.commanded_current != 0) & sample.valid
                self._stale_run = np.where(same, self._stale_run + 1, 0)
                self.stale += self._stale_run == self.stale_cycles
            self._last_position = sample.position
            record = JointStateRecord(self.sequence, sample)
            self.sequence += 1
            self.last = record
            if self.on_sample is not None:
                try:
                    self.on_sample(record)
                except Exception as err:  # the control law failed: stop the arm, keep recording
                    self.error = f"control law: {type(err).__name__}: {err}"
                    self.driver.quick_stop()
            self.driver.acknowledge(sample.cycle)
            for s in self.sinks:
                s.offer(record)

    def stop(self) -> None:
        """Stop reading, then let every sink finish what it holds."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        for s in self.sinks:
            s.offer(None) if s.bounded else s.queue.put(None)
            s.thread.join(timeout=30.0)

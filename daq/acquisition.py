"""Acquisition: one record per cycle from a driver, fanned out without ever waiting.

The acquisition thread reads the driver's samples (one per SYNC cycle, keyed by the cycle
counter, with late joints already marked invalid by the driver's deadline), numbers them
with a gap-free sequence, and hands each to its sinks through their own queues. The
recorder's queue is unbounded, so that no record is ever dropped for the disk. A
streaming or estimating sink has a bounded queue that drops its oldest record when full,
and counts the drops. A slow subscriber, disk or estimator therefore never holds up the
next cycle. Stale data (a joint whose position has not changed for ``stale_cycles`` while
commanded) is counted per joint.

A sink that fails (the recorder's disk is full, the stream's session is gone) stops the run:
its thread keeps the first exception in ``failure`` and handles nothing more, and the
acquisition stops reading at the next cycle with ``error`` naming the sink and the cause
(and quick-stops the drives when a control law was commanding them). What the sink handled
before it failed stays where it went.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from armid.drivers.interface import DriveFault, Driver, DriverError
from armid.schema.errors import ArmidError
from armid.schema.joint_state import Sample
from armid.schema.joint_states import JointStates

Handler = Callable[[JointStates], None]


class SinkFailure(ArmidError):
    """A sink failed (its file could not be written, its stream is gone) and stopped the run."""


@dataclass
class Sink:
    """A consumer on its own thread; ``bounded`` sinks drop their oldest record when behind.
    ``failure``: the exception that stopped it (it then handles nothing more)."""

    name: str
    handle: Handler
    bounded: bool = True
    capacity: int = 1000
    dropped: int = 0
    handled: int = 0
    failure: BaseException | None = None

    def __post_init__(self) -> None:
        self.queue: queue.Queue[JointStates | None] = queue.Queue(self.capacity if self.bounded else 0)
        self.thread = threading.Thread(target=self._run, name=f"armid-sink-{self.name}", daemon=True)

    def offer(self, record: JointStates | None) -> None:
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
            except Exception as err:  # the acquisition sees it and stops the run
                self.failure = err
                return


class Acquisition:
    """Read ``driver`` on a thread; ``on_fault`` hears of drive faults (acquisition goes on);
    ``on_sample`` runs inline on every sample the driver yields (a control law: it must be fast).
    A joint whose drive faulted (or was lost) is marked invalid in every record after the fault,
    until :meth:`clear_faults`.
    ``error`` says why acquisition stopped on its own (the driver, the control law, a sink)."""

    def __init__(self, driver: Driver, sinks: list[Sink], on_fault: Callable[[DriveFault], None] | None = None,
                 stale_cycles: int = 50, on_sample: Callable[[Sample], None] | None = None) -> None:
        self.driver = driver
        self.on_sample = on_sample  # inline, before the sinks: the control law of excitation
        self.sinks = sinks
        self.on_fault = on_fault
        self.stale_cycles = stale_cycles
        self.sequence = 0
        self.invalid = np.zeros(driver.n_joints, np.int64)
        self.stale = np.zeros(driver.n_joints, np.int64)
        self._stale_run = np.zeros(driver.n_joints, np.int64)
        self._last_position: np.ndarray[Any, np.dtype[np.float64]] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="armid-acquisition", daemon=True)
        self.error: str | None = None
        self.failed: Sink | None = None  # the sink whose failure stopped the run
        self.last: JointStates | None = None
        self.faulted: set[int] = set()  # 0-based joints whose drive faulted or was lost: invalid in every record after it

    def clear_faults(self) -> None:
        """The drives were enabled again: their records are valid again from here on."""
        self.faulted.clear()

    def start(self) -> None:
        for s in self.sinks:
            s.thread.start()
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                sample = self.driver.read(timeout=1.0)
            except DriveFault as fault:
                self.faulted.add(fault.joint)
                if self.on_fault:
                    self.on_fault(fault)
                continue
            except DriverError as err:
                self.error = str(err)
                break
            if self.faulted:  # the verdict says a faulted drive's records after its fault are not valid: they are marked so
                sample.valid[sorted(self.faulted)] = False
            self.invalid += np.logical_not(sample.valid)
            if self._last_position is not None:
                same = (sample.position == self._last_position) & (sample.commanded_current != 0) & sample.valid
                self._stale_run = np.where(same, self._stale_run + 1, 0)
                self.stale += self._stale_run == self.stale_cycles
            self._last_position = sample.position
            record = JointStates.of_sample(self.sequence, sample)
            self.sequence += 1
            self.last = record
            if self.on_sample is not None:
                try:
                    self.on_sample(sample)
                except Exception as err:  # the control law failed: stop the arm, keep recording
                    self.error = f"control law: {type(err).__name__}: {err}"
                    self.driver.quick_stop()
            self.driver.acknowledge(sample.cycle)
            for s in self.sinks:
                s.offer(record)
                if s.failure is not None:
                    self._sink_failed(s)
                    return

    def _sink_failed(self, sink: Sink) -> None:
        """Stop on a sink's failure, saying which and why; a commanded arm quick-stops."""
        self.failed = sink
        self.error = f"{sink.name}: {sink.failure}"
        if self.on_sample is not None:
            self.driver.quick_stop()

    def stop(self) -> None:
        """Stop reading, then let every sink finish what it holds."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        for s in self.sinks:
            s.offer(None) if s.bounded else s.queue.put(None)
            s.thread.join(timeout=30.0)

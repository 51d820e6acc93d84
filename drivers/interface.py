"""The one driver interface every amplifier family implements (CANopen, Dynamixel serial).

A driver yields one :class:`Sample` per cycle, in SI joint units, and takes commands.
Faults are typed: a drive's EMCY or a lost heartbeat is raised by :meth:`Driver.read` as a
:class:`DriveFault` once, after which reading goes on; what does not stop the arm (a frame
of the wrong length, an unknown node, error frames) is an :class:`Event` in
:meth:`Driver.events`.
"""

from __future__ import annotations

import abc
import gc
import queue
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from armid.schema import Array, Sample
from armid.schema.errors import DriveConfigError, DriveFault, DriverError, HeartbeatLost

from .realtime import RealtimeScheduling, Timing, stall_sentence

if TYPE_CHECKING:
    import can

    from .rig import DriveUnits

__all__ = ["CycleClock", "DriveConfigError", "DriveFault", "Driver", "DriverError", "Event", "HeartbeatLost", "Sample"]


@dataclass(frozen=True)
class Event:
    """Something the operator should know that did not stop the arm."""

    kind: str  # "frame_length" | "unknown_node" | "error_frames" | "sdo_abort" | "late" | ...
    message: str
    joint: int | None = None
    time_s: float = field(default_factory=time.time)


class ProcessSettings:
    """Process-wide settings a 2 ms loop needs, held while any holder runs and put back as
    they were when the last one lets go (:meth:`restore`, safe to call twice).

    - the interpreter's switch interval (5 ms by default: a thread waiting for the GIL would
      wait more than two cycles) is lowered to a tenth of the period;
    - what exists after start-up is frozen out of the garbage collector's full collections
      (they walk every object and stall all threads for many milliseconds); unfrozen at the
      end, unless the process had frozen objects of its own before (those stay its business);
    - the process's Python threads run at real-time priority where the system allows it
      (:mod:`drivers.realtime`): :meth:`realtime` says what they got.
    """

    _lock = threading.Lock()
    _interval_holders = 0
    _interval_before = 0.005
    _freeze_holders = 0
    _froze = False
    _rt_holders = 0
    _rt: RealtimeScheduling | None = None

    def __init__(self) -> None:
        self._interval = self._freeze = self._realtime = False

    def realtime(self, hardware: bool = False) -> Timing:
        """SCHED_FIFO for this process's Python threads while any holder runs (the first takes
        it); above a master's for simulated ``hardware`` in a process of its own
        (:data:`~drivers.realtime.HARDWARE_ABOVE`)."""
        cls = type(self)
        with cls._lock:
            if not self._realtime:
                if cls._rt_holders == 0:
                    cls._rt = RealtimeScheduling(hardware)
                    cls._rt.acquire()
                cls._rt_holders += 1
                self._realtime = True
            assert cls._rt is not None and cls._rt.timing is not None
            return cls._rt.timing

    def fast_switching(self, period_s: float) -> None:
        cls = type(self)
        with cls._lock:
            if not self._interval:
                if cls._interval_holders == 0:
                    cls._interval_before = sys.getswitchinterval()
                cls._interval_holders += 1
                self._interval = True
            sys.setswitchinterval(min(sys.getswitchinterval(), period_s / 10))

    def freeze(self) -> None:
        cls = type(self)
        gc.collect()
        with cls._lock:
            if not self._freeze:
                if cls._freeze_holders == 0:
                    cls._froze = gc.get_freeze_count() == 0
                cls._freeze_holders += 1
                self._freeze = True
            if cls._froze:
                gc.freeze()

    def restore(self) -> None:
        cls = type(self)
        with cls._lock:
            if self._interval:
                self._interval = False
                cls._interval_holders -= 1
                if cls._interval_holders == 0:
                    sys.setswitchinterval(cls._interval_before)
            if self._freeze:
                self._freeze = False
                cls._freeze_holders -= 1
                if cls._freeze_holders == 0 and cls._froze:
                    gc.unfreeze()
                    cls._froze = False
            if self._realtime:
                self._realtime = False
                cls._rt_holders -= 1
                if cls._rt_holders == 0 and cls._rt is not None:
                    cls._rt.release()
                    cls._rt = None


def bus_time(stamp: float) -> float:
    """A frame's stamp (its sender's or the kernel's wall-clock time) on this process's
    monotonic clock, or now on a bus that stamps none. The wall clock can step (NTP, a
    hypervisor resyncing a paused guest: 0.7 s and 13.8 s in one CI run, issue 31), and a
    step read as bus time loses every drive's heartbeat at once. A frame stamped before a step
    and read after it is off by the step for that frame only: too old after a forward step
    (harmless: a newer heartbeat follows), and after a backward one never later than its read."""
    now = time.monotonic()
    if stamp <= 0:
        return now
    return min(now, stamp - wall_minus_monotonic())


def wall_minus_monotonic() -> float:
    """The wall clock's lead over the monotonic one, read between two monotonic reads that lie
    close together: a process descheduled between the two reads of a single pair took that
    pause off a frame's bus time (a drive's answer read as older than the SYNC it answered:
    issue 31)."""
    best_gap, offset = float("inf"), 0.0
    for _ in range(5):
        before = time.monotonic()
        wall = time.time()
        after = time.monotonic()
        if after - before < best_gap:
            best_gap, offset = after - before, wall - 0.5 * (before + after)
        if best_gap < 20e-6:
            break
    return offset


class CycleClock:
    """The absolute schedule of a driver's cycle thread: :meth:`wait` sleeps to the next
    period boundary; a cycle late by up to ``catch_up`` periods is made up by the next ones
    coming sooner, a cycle later than that restarts the schedule (and counts in ``late``)
    instead of bursting to catch up. A real bus keeps ``catch_up`` at one period; a paced
    simulation, whose arm steps one period per SYNC whenever it comes, makes up more."""

    def __init__(self, period_s: float, catch_up: int = 1) -> None:
        self.period_s = period_s
        self.catch_up = catch_up
        self.late = 0
        self.last_late = (0.0, 0.0)  # (time.monotonic(), s) of the newest restart and how late that cycle was
        self._next = time.perf_counter()

    def wait(self) -> None:
        self._next += self.period_s
        delay = self._next - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        elif delay < -self.catch_up * self.period_s:
            self.late += 1
            self.last_late = (time.monotonic(), -delay)
            self._next = time.perf_counter()


class CycleHeartbeat:
    """The master's heartbeat, sent by the SYNC thread every ``every`` cycles (the first
    cycle included): where no kernel times it, a thread of its own waits for the interpreter
    lock as any other, and a drive that saw SYNCs for 0.15 s without a heartbeat between
    them faulted the arm on a loaded machine. :meth:`stop` stops it (a hung master)."""

    def __init__(self, frame: can.Message, every: int) -> None:
        self.frame, self.every = frame, max(1, every)
        self.stopped = False

    def due(self, cycle: int) -> bool:
        return not self.stopped and (cycle - 1) % self.every == 0

    def stop(self) -> None:
        self.stopped = True


class Driver(abc.ABC):
    """Reads one :class:`Sample` per cycle and sends commands to the amplifiers."""

    n_joints: int
    period_s: float
    paced_by_consumer: bool = False
    """True when the driver's cycle waits for :meth:`acknowledge` (an arm simulated in this
    process never runs ahead of its control loop); a driver that cannot pace ignores it."""
    paced_by_drives: bool | None = False
    """True when each cycle waits for the drives' answers (armid's simulated drives in another
    process: a co-simulation); known after :meth:`start`."""
    timing_note: str = ""
    """What keeps the cycle and at what priority, said once at start-up (``drivers.realtime``)."""
    lost_cycles: Array
    """Cycles lost per joint since :meth:`start` (the driver sets it up in ``__init__``)."""
    drive_configuration: list[dict[str, int]]
    """What each drive reported of its configuration at :meth:`start` (the recording's metadata)."""
    units: list[DriveUnits]
    """Each joint's unit conversions: counts, currents, torque constant."""
    last_stall: tuple[float, float] = (0.0, 0.0)
    """(``time.monotonic()``, s) of the newest time this process was not scheduled when its cycle was due."""

    def __init__(self) -> None:
        self._events: deque[Event] = deque(maxlen=10_000)
        self._samples: queue.Queue[Sample] = queue.Queue(maxsize=100_000)
        self._faults: queue.Queue[DriveFault] = queue.Queue()

    def stall_note(self, within_s: float = 0.5) -> str:
        """Why frames went missing, for a stop that says so: this process not scheduled (with
        the figure) when it was within ``within_s``, else the drives or the line."""
        when, stall = self.last_stall
        if stall and time.monotonic() - when < within_s:
            return f"; {stall_sentence(stall)}"
        return "; this process ran on time: the drives or the line went silent"

    @abc.abstractmethod
    def start(self) -> None:
        """Configure the amplifiers and start cycling (drives stay disabled)."""

    @abc.abstractmethod
    def read(self, timeout: float | None = None) -> Sample:
        """The next cycle's sample; raises a pending :class:`DriveFault` first."""

    @abc.abstractmethod
    def command_torque(self, torque: Array) -> None:
        """Joint torques (N*m or N) for the next cycle (converted through each torque constant)."""

    def command_current(self, current: Array) -> None:
        """Motor currents (A) for the next cycle."""
        self.command_torque(np.asarray(current, float) * self.torque_constants)

    @abc.abstractmethod
    def command_position(self, position: Array) -> None:
        """Joint positions for the amplifiers' own position loops (cyclic synchronous position)."""

    @abc.abstractmethod
    def enable(self, timeout: float = 1.0) -> None:
        """Bring every drive to operation enabled; raises if one does not get there."""

    @abc.abstractmethod
    def disable(self) -> None:
        """Remove power from every motor (brakes hold)."""

    @abc.abstractmethod
    def quick_stop(self, joints: list[int] | None = None) -> None:
        """Quick-stop the given joints (default: all)."""

    @abc.abstractmethod
    def close(self) -> None:
        """Stop cycling and release the bus."""

    @property
    def torque_constants(self) -> Array:
        """Each joint's torque per ampere (N*m/A or N/A), from its drive's units."""
        return np.array([u.torque_constant for u in self.units])

    def acknowledge(self, cycle: int) -> None:  # noqa: B027 - an optional hook: most drivers pace nothing
        """The consumer has acted on ``cycle`` (a driver pacing a simulated arm waits for it)."""

    @property
    def pending(self) -> int:
        """Samples read from the bus but not yet returned by :meth:`read` (a backlog)."""
        return self._samples.qsize()

    @property
    def latest_cycle(self) -> int | None:
        """The newest cycle started on the bus: a command sent now applies from the next
        (``_cycle``, which a driver counts from :meth:`start`)."""
        cycle: int | None = getattr(self, "_cycle", None)
        return cycle

    def events(self) -> list[Event]:
        """Events since the last call."""
        out = list(self._events)
        self._events.clear()
        return out

    def _event(self, kind: str, message: str, joint: int | None = None) -> None:
        self._events.append(Event(kind, message, joint))

    def _publish(self, sample: Sample) -> None:
        """Hand a cycle's sample to :meth:`read`; a full backlog drops its oldest, with an event.

        Where a live record's torque comes from: ``torque = measured_current * torque_constants``
        (readers of current-only recordings apply the robot file's torque constants themselves)."""
        sample.torque = sample.measured_current * self.torque_constants
        try:
            self._samples.put_nowait(sample)
        except queue.Full:
            self._samples.get_nowait()
            self._samples.put_nowait(sample)
            self._event("overflow", "the reader is too slow: the oldest sample was dropped")

    def _next_sample(self, timeout: float | None, stalled: str) -> Sample:
        """:meth:`read`'s common part: a pending fault first, then the next sample within
        ``timeout`` (default ten periods and a second); ``stalled`` says what to check."""
        try:
            raise self._faults.get_nowait()
        except queue.Empty:
            pass
        wait = timeout if timeout is not None else 10 * self.period_s + 1.0
        try:
            return self._samples.get(timeout=wait)
        except queue.Empty:
            pass
        try:  # a fault that came while waiting is why no cycle came
            raise self._faults.get_nowait()
        except queue.Empty:
            raise DriverError(f"no cycle within {wait} s: {stalled}") from None

    def __enter__(self) -> Driver:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

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
import warnings
import weakref
from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from armid.schema import Array, Sample
from armid.schema.errors import DriveConfigError, DriveFault, DriverError, DriverTimeout, HeartbeatLost

from .realtime import RealtimeScheduling, Timing, stall_sentence

if TYPE_CHECKING:
    import can

    from .rig import DriveUnits, Pacing, Rig

__all__ = ["CycleClock", "DriveConfigError", "DriveFault", "Driver", "DriverError", "DriverTimeout", "Event", "HeartbeatLost", "Sample"]


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


class Lifecycle:
    """Whether a driver was started and closed: what its finalizer reads (never the driver itself,
    which it must not keep alive)."""

    def __init__(self) -> None:
        self.started = self.closed = False


def warn_unclosed(name: str, lifecycle: Lifecycle) -> None:
    """A driver started and never closed (garbage-collected, or alive at the interpreter's exit):
    its bus or port, threads and process-wide settings were never given back."""
    if lifecycle.started and not lifecycle.closed:
        warnings.warn(f"{name} was started and never closed: call close() (or use it as a context manager)",
                      ResourceWarning, stacklevel=2)


CARRIED_FIELDS = ("position", "velocity", "measured_current", "status")
"""What a drive reports each cycle; a cycle that did not carry one keeps the last value reported."""


class Driver(abc.ABC):
    """Reads one :class:`Sample` per cycle and sends commands to the amplifiers.

    The template every driver follows, in the manner of python-can's ``BusABC`` (public method
    here, protected hook in the protocol's class): :meth:`start` over :meth:`_start` (what a start
    that fails changed process-wide is put back, what it opened closed), :meth:`close` over
    :meth:`_close` (safe twice; a driver started and never closed warns with a
    ``ResourceWarning``), the command checks over :meth:`_command_torque` and
    :meth:`_command_position`, the carry-forward of what a cycle did not report
    (:meth:`_carry_forward`) and a lost drive with the others quick-stopped (:meth:`_declare_lost`).
    A subclass writes only its protocol."""

    n_joints: int
    period_s: float
    pacing: Pacing
    """What each cycle waits for (the rig's ``pacing``: ``clock``, ``drives`` or ``consumer``,
    :class:`~drivers.rig.Rig`); set before :meth:`start`. A driver that cannot pace ignores it."""
    timing_note: str = ""
    """What keeps the cycle and at what priority, said once at start-up (``drivers.realtime``)."""
    lost_cycles: Array
    """Cycles lost per joint since :meth:`start`."""
    drive_configuration: list[dict[str, int]]
    """What each drive reported of its configuration at :meth:`start` (the recording's metadata)."""
    units: list[DriveUnits]
    """Each joint's unit conversions: counts, currents, torque constant."""
    last_stall: tuple[float, float] = (0.0, 0.0)
    """(``time.monotonic()``, s) of the newest time this process was not scheduled when its cycle was due."""

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        self.n_joints = rig.n_joints
        self.period_s = rig.period_s
        self.units = [d.units for d in rig.drives]
        self.pacing = rig.pacing
        self.drive_configuration = []
        self.lost_cycles = np.zeros(self.n_joints, np.int64)
        self._events: deque[Event] = deque(maxlen=10_000)
        self._samples: queue.Queue[Sample] = queue.Queue(maxsize=100_000)
        self._faults: queue.Queue[DriveFault] = queue.Queue()
        self._settings = ProcessSettings()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None  # the cycle's thread, when the driver runs one
        self._cycle = 0
        self._emitted = Sample.empty(0, 0.0, self.n_joints)  # the newest sample handed to read()
        self._commanded = np.zeros(self.n_joints)  # current (A) the newest command asks for
        self._in_force = np.zeros(self.n_joints)  # current the amplifiers act on this cycle
        self._silent = np.zeros(self.n_joints, bool)  # declared lost, until heard from again
        self._lifecycle = Lifecycle()
        self._finalizer = weakref.finalize(self, warn_unclosed, type(self).__name__, self._lifecycle)

    @property
    def paced(self) -> bool:
        """True when the cycle waits for something other than the clock (its samples then carry
        the simulated arm's time: the cycle times the period)."""
        return self.pacing != "clock"

    @property
    def silent_limit_s(self) -> float:
        """How long a drive may send nothing usable before it is declared lost: the bound a
        supervisor may wait through while this process was not scheduled (the rig's declared
        limit where it has one; else none beyond the supervisor's own)."""
        return 0.0

    def stalled_within(self, seconds: float) -> bool:
        """Whether this process was not scheduled when its cycle was due within the last ``seconds``."""
        when, stall = self.last_stall
        return bool(stall) and time.monotonic() - when < seconds

    def waits_note(self) -> str:
        """Reply waits given again for simulated hardware that had not yet answered, in a sentence
        ("" when none: a driver without them, real hardware)."""
        return ""

    def stall_note(self, within_s: float = 0.5) -> str:
        """Why frames went missing, for a stop that says so: this process not scheduled (with
        the figure) when it was within ``within_s``, else the drives or the line."""
        when, stall = self.last_stall
        if stall and time.monotonic() - when < within_s:
            return f"; {stall_sentence(stall)}"
        return "; this process ran on time: the drives or the line went silent"

    # --- the template ---
    def start(self) -> None:
        """Configure the amplifiers and start cycling (drives stay disabled). A start that
        fails closes what it opened and changes nothing process-wide."""
        if self._lifecycle.closed:
            raise DriverError(f"{type(self).__name__} on {self.rig.source}: closed; open a new driver")
        self._lifecycle.started = True
        try:
            self._start()
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """Stop cycling and release the bus; safe to call twice."""
        if self._lifecycle.closed:
            return
        self._lifecycle.closed = True
        self._finalizer.detach()
        self._settings.restore()
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        self._close()

    def command_torque(self, torque: Array) -> None:
        """Joint torques (N*m or N) for the next cycle (converted through each torque constant)."""
        self._command_torque(self._checked(torque, "torque"))

    def command_current(self, current: Array) -> None:
        """Motor currents (A) for the next cycle."""
        self.command_torque(self._checked(current, "current") * self.torque_constants)

    def command_position(self, position: Array) -> None:
        """Joint positions for the amplifiers' own position loops (cyclic synchronous position)."""
        self._command_position(self._checked(position, "position"))

    def _checked(self, values: Array, what: str) -> Array:
        """A command as the drives take it: one finite value per joint, or a clear error."""
        out = np.asarray(values, float)
        if out.shape != (self.n_joints,) or not np.isfinite(out).all():
            raise ValueError(f"{what} command must be {self.n_joints} finite values, got {out}")
        return out

    # --- the protocol's hooks ---
    @abc.abstractmethod
    def _start(self) -> None:
        """Open the bus or port, configure each drive, start the cycle."""

    @abc.abstractmethod
    def _close(self) -> None:
        """Release what :meth:`_start` opened (the cycle's thread has stopped); called once."""

    @abc.abstractmethod
    def _command_torque(self, torque: Array) -> None:
        """Checked joint torques for the next cycle."""

    @abc.abstractmethod
    def _command_position(self, position: Array) -> None:
        """Checked joint positions for the next cycle."""

    @abc.abstractmethod
    def read(self, timeout: float | None = None) -> Sample:
        """The next cycle's sample; raises a pending :class:`DriveFault` first."""

    @abc.abstractmethod
    def enable(self, timeout: float = 1.0) -> None:
        """Bring every drive to operation enabled; raises if one does not get there."""

    @abc.abstractmethod
    def disable(self) -> None:
        """Remove power from every motor (brakes hold)."""

    @abc.abstractmethod
    def quick_stop(self, joints: list[int] | None = None) -> None:
        """Quick-stop the given joints (default: all)."""

    # --- what every protocol's cycle shares ---
    def _open_record(self, cycle: int, time_s: float) -> Sample:
        """A new cycle's sample: what the drives last reported carried forward, and the current
        the amplifiers act on this cycle (the command before the newest: this cycle's takes
        effect at the next)."""
        s = Sample.empty(cycle, time_s, self.n_joints)
        self._carry_forward(s)
        s.commanded_current[:] = self._in_force
        self._in_force = self._commanded.copy()
        return s

    def _carry_forward(self, sample: Sample, unwritten: list[tuple[str, list[int]]] | None = None) -> None:
        """What a cycle did not report keeps the last value reported (the newest sample handed
        to :meth:`read`): every field of every joint, or each field's joints in ``unwritten``."""
        prev = self._emitted
        if unwritten is None:
            for name in CARRIED_FIELDS:
                getattr(sample, name)[:] = getattr(prev, name)
            return
        for name, joints in unwritten:
            if joints:  # element by element: numpy's fancy indexing costs more for six joints
                mine, before = getattr(sample, name), getattr(prev, name)
                for j in joints:
                    mine[j] = before[j]

    def _declare_lost(self, joint: int, fault: DriveFault, kind: str) -> None:
        """A drive is lost (silent, or out of operation): the others are quick-stopped, and
        :meth:`read` raises ``fault`` once; ``kind`` names the event."""
        self.quick_stop([k for k in range(self.n_joints) if k != joint])
        self._fault(fault, kind)

    def _fault(self, fault: DriveFault, kind: str) -> None:
        """A drive's fault, raised once by :meth:`read` and said as an event."""
        self._faults.put(fault)
        self._event(kind, str(fault), fault.joint)

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
    def latest_cycle(self) -> int:
        """The newest cycle started on the bus: a command sent now applies from the next."""
        return self._cycle

    def events(self) -> list[Event]:
        """Events since the last call."""
        out = list(self._events)
        self._events.clear()
        return out

    def _event(self, kind: str, message: str, joint: int | None = None) -> None:
        self._events.append(Event(kind, message, joint))

    def _publish(self, sample: Sample) -> None:
        """Hand a cycle's sample to :meth:`read` (the newest emitted: what the next cycle carries
        forward); a full backlog drops its oldest, with an event.

        Where a live record's torque comes from: ``torque = measured_current * torque_constants``
        (readers of current-only recordings apply the robot file's torque constants themselves)."""
        sample.torque = sample.measured_current * self.torque_constants
        self._emitted = sample
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
            raise DriverTimeout(f"no cycle within {wait} s: {stalled}") from None

    def __enter__(self) -> Driver:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

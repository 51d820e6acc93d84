"""Running an excitation on the drives: control law, supervision every cycle, recording.

:class:`ExcitationControl` runs inline in the acquisition thread (one call per 2 ms
record): the reference from the active :class:`~identify.excitation.Plan` (or the pose it
holds between plans), PD plus feed-forward from the modeled parameters
(:class:`~daq.control.ComputedTorque`), the command clipped to each joint's torque limit,
so that excitation never commands beyond one. Every cycle it also checks the arm against
its limits; a crossing (tracking error, position, velocity, frames lost, a drive fault)
quick-stops every drive on the next SYNC and ends the run, and recording goes on.

:class:`ExcitationSession` owns the bus side (simulated arm when asked, driver, one
acquisition thread for the whole session) and runs plans one after another, each
recorded to its own folder (``run.mcap`` and the raw frames in ``can.log``).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from armid.drivers.interface import DriveFault, Driver, DriverError
from armid.drivers.realtime import Policy, calling_thread_at, calling_thread_policy, ordinary_policy, set_calling_thread
from armid.identify.control import ComputedTorque
from armid.identify.errors import UsageError
from armid.identify.excitation import Limits, Plan
from armid.identify.robot import Robot
from armid.schema import Array, versions
from armid.schema.joint_state import Sample
from armid.schema.joint_states import JointStates

from .acquisition import Acquisition, Sink
from .canlog import BusLog
from .recorder import McapRecorder

LOOP_BANDWIDTH_HZ = 2.0
"""PD bandwidth of the excitation loop. The feed-forward does the tracking; the PD only
corrects model error. A Python process on a loaded 2-core machine stalls for tens of ms
(up to 64 ms measured); at 2 Hz the loop crosses over near 26 rad/s with 76 degrees of PD
phase, so a 20 ms delay still leaves about 47 degrees of margin (at 3 Hz: 32, and coupled joints 1-3 were seen to oscillate; at 5 Hz: about 2)."""

LOST_CYCLES_STOP = 3
"""Consecutive cycles without a joint's frames after which the arm is stopped (unless this
process was not scheduled meanwhile: :meth:`ExcitationControl._waits_through`)."""
STALL_LOOKBACK_S = 0.05
"""A stall of this process counts for a gap in the frames when it was seen at most this long
before the gap began (the replies it delayed come a few cycles after it). The gap is timed on
this process's clock, not counted in cycles: a serial read waits its reply timeout (8 ms on the
simulated chain) in each silent cycle, so cycles times the period would understate it."""


@dataclass
class RunReport:
    """What one plan did on the arm."""

    name: str
    completed: bool
    stop_reason: str | None
    stop_cycle: int | None
    cycles: int
    records: int
    first_cycle: int
    max_tracking_error: list[float]
    peak_torque_fraction: list[float]
    saturated_cycles: list[int]
    recording: str
    window_s: tuple[float, float]
    waited_through: int = 0  # gaps in a joint's frames waited through while this process was not scheduled

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class _Active:
    plan: Plan
    period_s: float
    first_cycle: int | None = None
    done: threading.Event = field(default_factory=threading.Event)
    cycles: int = 0
    reference: tuple[Array, Array, Array] = field(init=False)

    def __post_init__(self) -> None:
        # the plan on its cycle grid, once: evaluated each cycle (twice), the Fourier series and
        # the plan's masks took a seventh of the control loop's interpreter time (py-spy)
        n = int(np.ceil(self.plan.duration_s / self.period_s)) + 1
        self.reference = self.plan.evaluate(np.arange(n) * self.period_s)

    def at(self, k: int) -> tuple[Array, Array, Array]:
        """The reference ``q, qd, qdd`` ``k`` cycles after the plan's first; past its end, the
        end pose at rest (as :meth:`Plan.evaluate` there)."""
        i = min(max(k, 0), self.reference[0].shape[0] - 1)
        return self.reference[0][i], self.reference[1][i], self.reference[2][i]


class ExcitationControl:
    """The 2 ms control law and its supervision (see the module docstring)."""

    def __init__(self, driver: Driver, robot: Robot, controller: ComputedTorque, limits: Limits, tracking_limit: Array,
                 period_s: float) -> None:
        self.driver = driver
        self.robot = robot
        self.controller = controller
        self.limits = limits
        self.tracking_limit = np.asarray(tracking_limit, float)
        self.period_s = period_s
        n = robot.n_joints
        self.hold: Array | None = None
        self.active: _Active | None = None
        self.stop_reason: str | None = None
        self.stop_cycle: int | None = None
        self.max_error = np.zeros(n)
        self.peak_torque = np.zeros(n)
        self.saturated = np.zeros(n, np.int64)
        self._invalid_run = np.zeros(n, np.int64)
        self._gap_began = np.zeros(n)  # time.monotonic() at each joint's first cycle without frames, in its current gap
        self._velocity_age = np.zeros(n, np.int64)  # cycles since each joint's drive last sent its velocity
        self.skipped = 0  # samples supervised but not commanded from (a newer one was waiting)
        self.waited_through = 0  # gaps in a joint's frames waited through: this process was not scheduled (_waits_through)
        # lost frames stop the arm once the drives are enabled; before that (the trajectories are
        # being designed, which can stall this process for longer than 3 cycles) they are only counted
        self.armed = False
        self.last_sample: Sample | None = None
        self._lock = threading.Lock()

    def start(self, plan: Plan) -> _Active:
        with self._lock:
            if self.stop_reason:
                raise DriverError(f"the arm was stopped ({self.stop_reason}); start a new session")
            self.max_error[:] = 0.0
            self.peak_torque[:] = 0.0
            self.saturated[:] = 0
            self.waited_through = 0
            self.active = _Active(plan, self.period_s)
            return self.active

    @property
    def plan_time(self) -> float:
        """Time into the active plan at the newest record (s); -1 without one."""
        active, last = self.active, self.last_sample
        if active is None or active.first_cycle is None or last is None:
            return -1.0
        return (last.cycle - active.first_cycle) * self.period_s

    def fault(self, fault: DriveFault) -> None:
        last = self.last_sample
        self._stop(f"drive fault: {fault}", last.cycle if last is not None else None)  # the cycle it was seen at

    def _waits_through(self, silent_s: float, gap_s: float) -> bool:
        """Frames missing for ``silent_s`` of cycles (``gap_s`` on this process's clock) while
        this process was not scheduled are waited through, up to the driver's declared silent
        limit (a serial chain's ``silent_cycles``: past it the driver declares the drive lost and
        stops the arm itself); a drive silent while this process ran on time stops the arm at
        :data:`LOST_CYCLES_STOP` cycles. Counted in ``waited_through`` (one per gap)."""
        limit = self.driver.silent_limit_s
        if silent_s >= limit or not self.driver.stalled_within(gap_s + STALL_LOOKBACK_S):
            return False
        if self._invalid_run.max() == LOST_CYCLES_STOP:
            self.waited_through += 1
        return True

    def _stop(self, reason: str, cycle: int | None) -> None:
        if self.stop_reason is None:
            self.stop_reason, self.stop_cycle = reason, cycle
            self.driver.quick_stop()
        if self.active is not None:
            self.active.done.set()

    def __call__(self, s: Sample) -> None:
        self.last_sample = s
        if self.stop_reason:
            return
        self._invalid_run = np.where(s.valid, 0, self._invalid_run + 1)
        if self._invalid_run.any():
            self._gap_began = np.where(self._invalid_run == 1, time.monotonic(), self._gap_began)
        self._velocity_age = np.where(s.velocity_fresh, 0, self._velocity_age + 1)
        if self.armed and (self._invalid_run >= LOST_CYCLES_STOP).any():
            j = int(np.argmax(self._invalid_run))
            silent_s = float(self._invalid_run[j]) * self.period_s
            if not self._waits_through(silent_s, time.monotonic() - float(self._gap_began[j])):
                return self._stop(f"joint {j + 1}: no frames for {int(self._invalid_run[j])} cycles{self.driver.stall_note()}", s.cycle)
        with self._lock:
            active = self.active
        if active is not None and active.first_cycle is None:
            active.first_cycle = s.cycle
        # the command sent now applies from the next SYNC: look that far ahead (a Python
        # process can fall a few cycles behind the bus; the drives must not see the lag)
        latest = self.driver.latest_cycle
        lead = max(1, (latest if latest is not None else s.cycle) + 1 - s.cycle)
        newest = self.driver.pending == 0
        if active is not None:
            assert active.first_cycle is not None  # set above, on the experiment's first cycle
            k = s.cycle - active.first_cycle
            q_ref, qd_ref, qdd_ref = active.at(k)
            active.cycles += 1
            if k * self.period_s >= active.plan.duration_s:
                self.hold = q_ref.copy()
                self.active = None
                active.done.set()
        elif self.hold is not None:
            q_ref, qd_ref, qdd_ref = self.hold, np.zeros_like(self.hold), np.zeros_like(self.hold)
        else:
            self.hold = s.position.copy()
            return
        q, qd = s.position, s.velocity
        valid = np.asarray(s.valid, dtype=bool)
        error = np.abs(q_ref - q)
        self.max_error = np.maximum(self.max_error, np.where(valid, error, 0.0))
        lim = self.limits
        checks = [
            (valid & (error > self.tracking_limit), "tracking error {v:.4f} rad beyond {lim:.4f}", error, self.tracking_limit),
            (valid & ((q < lim.position_low) | (q > lim.position_high)), "position {v:.4f} outside its range ending at {lim:.4f}", q,
             np.where(q < lim.position_low, lim.position_low, lim.position_high)),
            (valid & (np.abs(qd) > lim.velocity), "velocity {v:.4f} beyond {lim:.4f}", np.abs(qd), lim.velocity),
        ]
        for bad, text, value, limit in checks:
            if bad.any():
                j = int(np.flatnonzero(bad)[0])
                return self._stop(f"joint {j + 1}: " + text.format(v=value[j], lim=limit[j]) + f" at cycle {s.cycle}", s.cycle)
        if not newest:
            self.skipped += 1  # a newer sample is waiting: command from that one
            return
        # a velocity the drive did not send this cycle (a bus that carries it every other
        # cycle) is the last one it sent: carried forward by the reference's acceleration, so
        # that the damping term does not chatter at half the cycle rate (a bias of -1.6 sigma
        # on joint 2's viscous friction in the demo's single-link runs, -0.4 without it)
        qd = qd + qdd_ref * self._velocity_age * self.period_s
        if active is not None:
            # a command sent now goes out after SYNC latest+1 and is latched at SYNC latest+2
            q_ref, qd_ref, qdd_ref = active.at(s.cycle + lead - active.first_cycle)  # type: ignore[operator]
        q = q + qd * lead * self.period_s
        tau = self.controller(q, qd, q_ref, qd_ref, qdd_ref)
        over = np.abs(tau) > lim.torque
        self.saturated += over
        tau = np.clip(tau, -lim.torque, lim.torque)  # never command beyond a torque limit
        with np.errstate(divide="ignore", invalid="ignore"):
            self.peak_torque = np.maximum(self.peak_torque, np.nan_to_num(np.abs(tau) / lim.torque))
        self.driver.command_torque(tau)


class _Switch:
    """The recording sink: writes to whichever recorder the current run opened."""

    def __init__(self) -> None:
        self.recorder: McapRecorder | None = None
        self.count = 0
        self.first_sequence: int | None = None  # of the current recording: the stream's subscribers cut the run by these
        self.last_sequence: int | None = None

    def __call__(self, states: JointStates) -> None:
        recorder = self.recorder
        if recorder is not None:
            recorder.write(states)
            self.count += len(states)
            if self.first_sequence is None:
                self.first_sequence = int(states.sequence[0])
            self.last_sequence = int(states.sequence[-1])


class ExcitationSession:
    """Bus, drives and acquisition for a sequence of plans; ``with`` closes everything."""

    def __init__(self, rig: Any, driver: Driver | None = None, *, simulator: Any = None, tracking_limit_rad: float = 0.2,
                 stream: Any = None, bus: Any = None, bandwidth_hz: float | None = None, say: Callable[[str], None] | None = None) -> None:
        """``driver``: any :class:`Driver` (default: the one the rig names, from the registry,
        on ``bus`` for CANopen). ``simulator``: the simulated hardware the caller started
        (``armid.simulated``), closed with the session; its ``peer`` is :attr:`arm`.
        ``bandwidth_hz``: the loop's PD bandwidth (default: the rig's ``control_bandwidth_hz``,
        else :data:`LOOP_BANDWIDTH_HZ`). ``say``: where the drives' faults and events are said
        as they come (:class:`~armid.daq.supervision.Supervision`; default: nowhere)."""
        from armid.drivers import open_driver

        from .supervision import Supervision

        self.rig = rig
        self.robot: Robot = rig.robot
        self.simulator = simulator
        self.arm = getattr(simulator, "peer", None)
        self.driver = driver if driver is not None else open_driver(rig, **({"bus": bus} if bus is not None else {}))
        self.stream = stream
        self.supervision = Supervision(say or (lambda text: None), stream)
        self.limits = Limits.of(self.robot)
        armature = np.array([d.units.reflected_inertia for d in rig.drives], float)
        q_nominal = rig.simulation.get("initial_position") if rig.simulation else None
        bandwidth_hz = bandwidth_hz or rig.control_bandwidth_hz or LOOP_BANDWIDTH_HZ
        self.controller = ComputedTorque(self.robot, q_nominal=q_nominal, armature=armature, bandwidth_hz=bandwidth_hz,
                                         decoupled=True)
        self.control = ExcitationControl(self.driver, self.robot, self.controller, self.limits,
                                         np.full(self.robot.n_joints, tracking_limit_rad), rig.period_s)
        self._switch = _Switch()
        self._sink = Sink("recorder", self._switch, bounded=False)
        sinks = [self._sink]
        if stream is not None:
            sinks.append(Sink("zenoh", stream.publish, bounded=True, capacity=5000))
        self.acquisition: Acquisition | None = None
        self._sinks = sinks
        self.enabled = False
        self._loop_policy: Policy | None = None  # what the drivers gave this process's threads

    def start(self) -> None:
        self.driver.start()
        self.acquisition = Acquisition(self.driver, self._sinks, on_fault=self._on_fault, on_sample=self.control)
        self.acquisition.start()
        deadline = time.monotonic() + 2.0
        while self.control.hold is None and time.monotonic() < deadline:
            time.sleep(0.01)
        if self.control.hold is None:
            raise DriverError("no sample from the drives within 2 s of starting")
        # the loop's threads run now, at the drivers' policy; the caller's thread is ordinary
        # until it runs a plan (it may compute meanwhile: drivers.realtime.calling_thread_at)
        self._loop_policy = calling_thread_policy()
        set_calling_thread(ordinary_policy())

    def _invalid_run_reset(self) -> None:
        self.control._invalid_run[:] = 0
        self.control.armed = True

    def _on_fault(self, fault: DriveFault) -> None:
        self.control.fault(fault)
        self.supervision.fault(fault)

    @property
    def position(self) -> Array:
        """The pose the arm holds now."""
        assert self.control.hold is not None
        return self.control.hold.copy()

    def run(self, plan: Plan, out_dir: str | Path, name: str, metadata: dict[str, Any] | None = None,
            progress: Callable[[float, ExcitationControl], None] | None = None) -> RunReport:
        """Enable (first time), run ``plan`` from where the arm is, record it, hold the end pose.
        The calling thread runs at the loop's policy meanwhile, and is ordinary again after."""
        with calling_thread_at(self._loop_policy):
            return self._run(plan, out_dir, name, metadata, progress)

    def _run(self, plan: Plan, out_dir: str | Path, name: str, metadata: dict[str, Any] | None,
             progress: Callable[[float, ExcitationControl], None] | None) -> RunReport:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        assert self.acquisition is not None
        if np.abs(plan.start - self.position).max() > 0.02:
            raise UsageError(f"{name}: the plan starts {np.abs(plan.start - self.position).max():.3f} rad from where the arm is")
        meta = {
            "robot": self.robot.name, "rig": self.rig.name, "rig_file": self.rig.source, "period_s": self.rig.period_s,
            "pdo_plan": None if self.rig.is_serial else self.rig.pdo_plan, "driver": self.rig.driver, "drives": self.driver.drive_configuration,
            "excitation": {"name": name, "lead_in_s": plan.lead_in_s, "periods": plan.periods, "settle_s": plan.settle_s,
                           "window_s": list(plan.excitation_window), **(metadata or {})},
            "versions": _versions(),
        }
        recorder = McapRecorder(out / "run.mcap", [j.name for j in self.robot.joints], meta)
        # every frame on a CAN bus, the master's included
        can_log = BusLog(self.driver, out / "can.log") if getattr(self.driver, "network", None) is not None else None
        self._switch.first_sequence = self._switch.last_sequence = None
        self._switch.recorder = recorder
        written_before = self._switch.count
        interrupted: BaseException | None = None
        try:
            if not self.enabled:
                # enable first, holding the pose: the plan's clock starts once the drives follow
                self._invalid_run_reset()
                self.driver.enable()
                self.acquisition.clear_faults()  # every drive in operation again
                self.enabled = True
            active = self.control.start(plan)
            if self.stream is not None:
                from .experiment_stream import experiment_description

                self.stream.event("start", run=name, duration_s=plan.duration_s,
                                  experiment=experiment_description(name, plan, self.robot.n_joints, meta))
            while not active.done.wait(0.2):
                self.supervision.events(self.driver.events())
                if progress is not None:
                    progress(active.cycles * self.rig.period_s, self.control)
                if self.acquisition.error:
                    self.control._stop(f"acquisition: {self.acquisition.error}", None)
            if progress is not None:
                progress(active.cycles * self.rig.period_s, self.control)
            if self.control.stop_reason is not None:
                time.sleep(0.1)  # keep recording while the drives carry out the quick stop
            # let the recorder catch up with every record of this run, then switch it off
            target = self.acquisition.sequence
            deadline = time.monotonic() + 10.0
            while self._sink.handled < target and time.monotonic() < deadline:
                time.sleep(0.01)
        except BaseException as err:  # the run ends here too: its recording says so
            interrupted = err
            raise
        finally:
            self._switch.recorder = None
            time.sleep(0.005)
            recorder.close(self._run_end(interrupted))
            if can_log is not None:
                can_log.stop()
        c = self.control
        if self.stream is not None:  # the records the recording holds, by sequence number, and where the excitation lies
            self.stream.event("stop", run=name, completed=c.stop_reason is None, reason=c.stop_reason, stop_cycle=c.stop_cycle,
                              records=self._switch.count - written_before, first_sequence=self._switch.first_sequence,
                              last_sequence=self._switch.last_sequence, first_cycle=active.first_cycle or 0,
                              window_s=list(plan.excitation_window), cycles=active.cycles)
        return RunReport(name, c.stop_reason is None, c.stop_reason, c.stop_cycle, active.cycles, self._switch.count - written_before,
                         active.first_cycle or 0, c.max_error.tolist(), c.peak_torque.tolist(), c.saturated.tolist(), str(out / "run.mcap"),
                         plan.excitation_window, c.waited_through)

    def _run_end(self, interrupted: BaseException | None) -> dict[str, Any]:
        """How the run ended, for its recording's ``armid.run_end`` metadata: the stop line
        (``RunReport.stop_reason``, what ``armid excite`` prints after ``STOPPED:``), or what
        interrupted this process's run of the plan."""
        c = self.control
        reason = c.stop_reason
        if reason is None and interrupted is not None:
            reason = f"interrupted: {type(interrupted).__name__}" + (f": {interrupted}" if str(interrupted) else "")
        return {"completed": reason is None, "stop": reason, "stop_cycle": c.stop_cycle if c.stop_reason else None}

    def close(self) -> None:
        try:
            if self.enabled and self.control.stop_reason is None:
                self.driver.disable()
                time.sleep(0.02)
        finally:
            if self.acquisition is not None:
                self.acquisition.stop()
            self.driver.close()
            if self.simulator is not None:
                self.simulator.close()

    def __enter__(self) -> ExcitationSession:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _versions() -> dict[str, str]:
    """The software that made a recording (installed metadata, ``importlib.metadata``)."""
    return versions("python-can", "canopen", "numpy")

"""The simulated arm's physics: rigid-body forward dynamics plus what real arms add.

Pinocchio's ABA integrates the robot description (with the "true" parameters, which
need not be the modeled ones) one SYNC period at a time, in fixed sub-steps, with
semi-implicit Euler: ``v += a dt; q += v dt``. That is leapfrog, whose velocity belongs
half a sub-step before its position: the sensors report the position at the velocity's
instant (``q - v dt / 2``), so that velocity, differentiated position and the torque
held over the period agree, which is what tests of identification need.

On top of the rigid body, per joint and each off by default: Coulomb, viscous and Stribeck
friction, rotor inertia (Pinocchio's armature), a torque-constant error (the motor makes
``gain * kt * i`` while everyone believes ``kt * i``), cogging, a position spring, a
torque offset, a delay between the current and the position measurements; arm-wide: a
tilted gravity vector and a payload attached and removed while running. Sensors: a
first-order current loop, current noise; position and velocity are quantised by the
drives that report them. Deterministic for a given seed.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from armid.identify.pinocchio_bridge import to_pinocchio
from armid.identify.robot import Robot
from armid.schema import Array

from .physics_kernel import EFFECT_ROWS, substep

EFFECT_FIELDS = ("coulomb", "viscous", "stribeck", "stribeck_velocity", "rotor_inertia", "torque_gain", "cogging",
                 "cogging_period", "cogging_phase", "spring", "spring_rest", "offset", "delay_s", "load_friction")


@dataclass(frozen=True)
class JointEffects:
    """Effects of one joint, in joint units (N*m, N*m*s/rad, rad, s).

    Friction is ``(coulomb + stribeck exp(-(qd/stribeck_velocity)^2)) sign(qd) + viscous qd``,
    with the sign smoothed over ``|qd| < 1e-3`` rad/s. Cogging is ``cogging sin(2 pi q /
    cogging_period + cogging_phase)``. The spring pulls with ``spring (q - spring_rest)``.
    ``offset`` is a constant torque on the joint that the motor current does not show (a
    cable, a counterbalance): the current then reads ``offset / kt`` low. ``delay_s`` delays the
    position and velocity the drive reports relative to its current. ``load_friction`` adds
    Coulomb friction in proportion to the torque the motor transmits (a gear under load:
    ``load_friction |tau_motor| sign(qd)``; applied in :meth:`ArmPhysics.step`).
    """

    coulomb: float = 0.0
    viscous: float = 0.0
    stribeck: float = 0.0
    stribeck_velocity: float = 0.1
    rotor_inertia: float = 0.0
    torque_gain: float = 1.0
    cogging: float = 0.0
    cogging_period: float = 2.0 * np.pi / 12.0
    cogging_phase: float = 0.0
    spring: float = 0.0
    spring_rest: float = 0.0
    offset: float = 0.0
    delay_s: float = 0.0
    load_friction: float = 0.0

    def friction_slope(self, qd: float) -> float:
        """d(friction)/d(qd) >= 0: integrated implicitly, so that stiff friction stays stable."""
        s = 1.0 - np.tanh(qd / 1e-3) ** 2
        x = qd / self.stribeck_velocity
        stribeck = self.stribeck * np.exp(-(x**2)) * (s / 1e-3 - 2.0 * x / self.stribeck_velocity * np.tanh(qd / 1e-3))
        return float(max(0.0, self.viscous + self.coulomb * s / 1e-3 + stribeck))

    def torque(self, q: float, qd: float) -> float:
        """Torque the effects take away from the motor's (friction, spring, cogging)."""
        s = np.tanh(qd / 1e-3)
        x = min(abs(qd / self.stribeck_velocity), 30.0)
        t = (self.coulomb + self.stribeck * np.exp(-(x**2))) * s + self.viscous * qd
        if self.cogging:
            t += self.cogging * np.sin(2.0 * np.pi * q / self.cogging_period + self.cogging_phase)
        if self.spring:
            t += self.spring * (q - self.spring_rest)
        return float(t)


@dataclass(frozen=True)
class Payload:
    """A rigid payload in the last link's frame: mass (kg), centre of mass (m), inertia
    about the centre of mass (kg m^2, xx xy xz yy yz zz)."""

    mass: float
    com: tuple[float, float, float] = (0.0, 0.0, 0.0)
    inertia: tuple[float, float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class SimulationConfig:
    """What the simulated arm adds to its robot description."""

    joints: tuple[JointEffects, ...] = ()
    gravity_tilt_rad: tuple[float, float] = (0.0, 0.0)  # about base x, then base y
    current_noise_a: float = 0.0  # std of the measured current
    current_time_constant_s: float = 0.0  # first-order current loop
    substeps: int = 4
    parameters: tuple[float, ...] | None = None  # true Khosla parameters (default: modeled)
    initial_position: tuple[float, ...] | None = None

    def effects(self, joint: int) -> JointEffects:
        return self.joints[joint] if joint < len(self.joints) else JointEffects()


def simulation_config(data: dict[str, Any] | None, n_joints: int, where: str = "simulation") -> SimulationConfig:
    """Parse the ``simulation:`` mapping of a rig file (see ``config/rigs/sim.yaml``)."""
    from armid.identify.errors import RobotFileError

    data = dict(data or {})
    effects: list[dict[str, float]] = [dict() for _ in range(n_joints)]
    allowed = {f.name for f in fields(JointEffects)}
    for k, entry in enumerate(data.pop("effects", []) or []):
        if not isinstance(entry, dict) or "joint" not in entry:
            raise RobotFileError(where, f"effects[{k}]", "must be a mapping with a 1-based 'joint' and effect values")
        joints = range(n_joints) if entry["joint"] in (None, "all") else [int(entry["joint"]) - 1]
        for j in joints:
            if not 0 <= j < n_joints:
                raise RobotFileError(where, f"effects[{k}].joint", f"must be 1..{n_joints}, got {entry['joint']}")
            for name, value in entry.items():
                if name == "joint":
                    continue
                if name not in allowed:
                    raise RobotFileError(where, f"effects[{k}].{name}", f"unknown effect; known: {', '.join(sorted(allowed))}")
                effects[j][name] = float(value)
    tilt = data.pop("gravity_tilt_rad", (0.0, 0.0))
    cfg = SimulationConfig(
        joints=tuple(JointEffects(**e) for e in effects),
        gravity_tilt_rad=(float(tilt[0]), float(tilt[1])),
        current_noise_a=float(data.pop("current_noise_a", 0.0)),
        current_time_constant_s=float(data.pop("current_time_constant_s", 0.0)),
        substeps=int(data.pop("substeps", 4)),
        initial_position=tuple(float(x) for x in data["initial_position"]) if data.get("initial_position") is not None else None,
    )
    data.pop("initial_position", None)
    data.pop("seed", None)
    data.pop("sync_timeout_s", None)
    if data:
        raise RobotFileError(where, next(iter(data)), "unknown simulation setting")
    return cfg


@dataclass
class Measurement:
    """What the sensors show after a step, in SI joint units (not yet quantised)."""

    time_s: float
    position: Array
    velocity: Array
    current: Array  # measured, A
    true_position: Array
    true_velocity: Array
    true_acceleration: Array


@dataclass
class _State:
    q: Array
    qd: Array
    current: Array
    time_s: float = 0.0
    history: deque = field(default_factory=deque)  # type: ignore[type-arg]


class ArmPhysics:
    """Forward dynamics of ``robot`` stepped one period at a time by current commands.

    ``torque_constant`` (A -> N*m at the joint) is what the drives believe; the motor
    makes ``torque_gain`` times that.
    """

    def __init__(self, robot: Robot, config: SimulationConfig, period_s: float, seed: int = 0) -> None:
        import pinocchio as pin

        self._pin = pin
        self.robot = robot
        self.config = config
        self.period_s = period_s
        self.n = robot.n_joints
        phi = np.asarray(config.parameters, float) if config.parameters is not None else robot.modeled_parameters()
        self.model = to_pinocchio(robot, phi)
        self.model.armature = np.array([config.effects(j).rotor_inertia for j in range(self.n)])
        ax, ay = config.gravity_tilt_rad
        rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
        ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
        self.model.gravity = pin.Motion(ry @ rx @ np.asarray(robot.gravity, float), np.zeros(3))
        self._data = self.model.createData()
        self._last_inertia = self.model.inertias[self.n].copy()
        self.kt = np.array([j.torque_constant for j in robot.joints], float)
        self.gain = np.array([config.effects(j).torque_gain for j in range(self.n)])
        self.offset = np.array([config.effects(j).offset for j in range(self.n)])
        self.rng = np.random.default_rng(seed)
        q0 = np.asarray(config.initial_position, float) if config.initial_position is not None else np.zeros(self.n)
        self.dt = period_s / config.substeps
        self.delay_steps = np.array([int(round(config.effects(j).delay_s / self.dt)) for j in range(self.n)])
        self._state = _State(q0.copy(), np.zeros(self.n), np.zeros(self.n))
        self._last_acc = np.zeros(self.n)
        self._lock = threading.Lock()
        self._pending_payload: list[tuple[float, Payload | None]] = []
        self.payload_events: list[tuple[float, Payload | None]] = []
        self._effects = np.array([[getattr(config.effects(j), row) for j in range(self.n)] for row in EFFECT_ROWS], float)
        tau_c = config.current_time_constant_s
        self._alpha = 1.0 - np.exp(-self.dt / tau_c) if tau_c > 0 else 1.0  # the current loop's lag per sub-step
        self._motor_gain = self.gain * self.kt
        self._max_delay = int(self.delay_steps.max()) if self.n else 0
        self._all_free, self._zero = np.ones(self.n, bool), np.zeros(self.n)
        self._warm()
        self.payload: Payload | None = None

    # --- payload, settable from any thread; applied at the next step, or at a time of the arm's clock ---
    def attach_payload(self, payload: Payload | None, at_time_s: float | None = None) -> None:
        """Attach ``payload`` (None removes it) at the next step, or at the first step that
        starts at ``at_time_s`` or later: events on the arm's own clock, whatever the thread
        that asks. ``payload_events`` logs (time the step started, payload)."""
        with self._lock:
            self._pending_payload.append((-np.inf if at_time_s is None else at_time_s, payload))

    def _apply_payload(self, payload: Payload | None) -> None:
        pin = self._pin
        inertia = self._last_inertia.copy()
        if payload is not None:
            post = self.robot.joints[-1].post
            r, t = post[:3, :3], post[:3, 3]
            xx, xy, xz, yy, yz, zz = payload.inertia
            i_com = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
            inertia = inertia + pin.Inertia(payload.mass, r @ np.asarray(payload.com, float) + t, r @ i_com @ r.T)
        self.model.inertias[self.n] = inertia
        self.payload = payload

    @property
    def position(self) -> Array:
        return self._state.q.copy()

    @property
    def velocity(self) -> Array:
        return self._state.qd.copy()

    @property
    def time_s(self) -> float:
        return self._state.time_s

    def _warm(self) -> None:
        """Compile (or load from numba's cache) the sub-step kernel now: the first call holds
        the interpreter for seconds, which must not happen inside a bus thread's SYNC."""
        z = np.zeros(self.n)
        substep(np.eye(self.n), z, z.copy(), z.copy(), z.copy(), z, 1.0, z, z, np.ones(self.n, bool), self._effects, self.dt)

    def step(self, current_command: Array, braked: Array | None = None) -> Measurement:
        """Advance one period under ``current_command`` (A per joint); return the sensors.

        Joints with ``braked`` set are held by their brakes: their velocity and acceleration
        are zero and the others move with the constrained dynamics ``M_ff a_f = tau_f - b_f``.
        """
        with self._lock:
            due = [e for e in self._pending_payload if e[0] <= self._state.time_s + 1e-9]
            self._pending_payload = [e for e in self._pending_payload if e[0] > self._state.time_s + 1e-9]
            for _, payload in sorted(due, key=lambda e: e[0]):
                self._apply_payload(payload)
                self.payload_events.append((self._state.time_s, payload))
        s, pin = self._state, self._pin
        cmd = np.ascontiguousarray(current_command, float)  # the kernel is compiled for contiguous arrays
        free = self._all_free if braked is None else ~np.asarray(braked, bool)
        acc = self._last_acc
        max_delay = self._max_delay
        for _ in range(self.config.substeps):
            mass = pin.crba(self.model, self._data, s.q)
            bias = pin.rnea(self.model, self._data, s.q, s.qd if free is self._all_free else np.where(free, s.qd, 0.0), self._zero)
            acc = substep(mass, bias, s.q, s.qd, s.current, cmd, self._alpha, self._motor_gain, self.offset, free, self._effects, self.dt)
            s.time_s += self.dt
            if max_delay:
                s.history.append((s.q.copy(), s.qd.copy()))
                while len(s.history) > max_delay + 1:
                    s.history.popleft()
        self._last_acc = acc
        # semi-implicit Euler is leapfrog: its velocity belongs half a sub-step before its
        # position. The sensors see both at one instant, the velocity's (measured: with
        # positions half a sub-step ahead, friction identified from differentiated positions
        # came out 40 % high on the PUMA's joint 1; see test_physics_positions_match_velocities)
        lead = 0.5 * self.dt
        q_seen, qd_seen = s.q - lead * s.qd, s.qd.copy()
        if max_delay:
            for j, d in enumerate(self.delay_steps):
                if d:
                    old = s.history[max(0, len(s.history) - 1 - d)]
                    q_seen[j], qd_seen[j] = old[0][j] - lead * old[1][j], old[1][j]
        noise = self.rng.normal(0.0, self.config.current_noise_a, self.n) if self.config.current_noise_a else 0.0
        measured = s.current + noise
        return Measurement(s.time_s, q_seen, qd_seen, measured, s.q.copy(), s.qd.copy(), acc)

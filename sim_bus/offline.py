"""The simulated arm without a bus: same physics and drive quantisation, as fast as it runs.

What the drives would report, cycle by cycle, while a PD plus feed-forward controller
tracks a trajectory: encoder positions and velocities in whole increments, currents in
per mille of the rated current. Tests and ``armid demo`` use it to make recordings with
known effects in them in a fraction of real time; the bus path (:mod:`sim_bus.arm`) runs
the same :class:`ArmPhysics`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from armid.drivers.rig import DriveUnits, current_of, permille_of
from armid.identify.control import ComputedTorque
from armid.identify.recordings import Recording
from armid.identify.robot import Robot
from armid.schema import Array

from .physics import ArmPhysics, Payload, SimulationConfig


@dataclass
class OfflineRun:
    t: Array
    position: Array  # as the encoders report it
    velocity: Array
    current: Array  # measured, A
    torque: Array  # measured current times the believed torque constant
    true_position: Array
    reference: Array

    def recording(self, source: str = "<simulation>", with_velocity: bool = True) -> Recording:
        return Recording(source, self.t, self.position, self.torque, self.velocity if with_velocity else None)


def default_units(robot: Robot) -> list[DriveUnits]:
    """Drives for a robot without a rig: 4096-count encoders, gear 100, rated torque = limit."""
    out = []
    for j in robot.joints:
        limit = j.limits.torque or 50.0
        out.append(DriveUnits(4096, 100.0, max(limit / j.torque_constant, 1e-3), j.torque_constant))
    return out


def simulate(robot: Robot, config: SimulationConfig, reference, duration_s: float, period_s: float = 0.002,  # type: ignore[no-untyped-def]
             seed: int = 0, units: list[DriveUnits] | None = None, controller: ComputedTorque | None = None,
             payloads: list[tuple[float, Payload | None]] | None = None) -> OfflineRun:
    """Track ``reference(t) -> (q, qd, qdd)`` for ``duration_s``; return what the drives report.
    ``payloads`` attaches (or, with None, removes) a payload at the given times."""
    units = units or default_units(robot)
    q0 = np.asarray(reference(np.array([0.0]))[0][0], float)
    from dataclasses import replace

    config = replace(config, initial_position=tuple(q0))
    physics = ArmPhysics(robot, config, period_s, seed)
    # the lab tuned its gains on the real arm: rotor inertias included
    control = controller or ComputedTorque(robot, q_nominal=q0, armature=np.array([config.effects(j).rotor_inertia for j in range(robot.n_joints)]))
    counts = np.array([u.counts_per_rad for u in units])
    rated = np.array([u.rated_current_a for u in units])
    kt = np.array([u.torque_constant for u in units])
    n = int(round(duration_s / period_s))
    t = np.arange(n, dtype=np.float64) * period_s
    q_ref, qd_ref, qdd_ref = reference(t + period_s)  # the command for the period that ends at t + T
    out_q, out_qd, out_i, true_q = (np.zeros((n, robot.n_joints)) for _ in range(4))
    q_meas, qd_meas = q0.copy(), np.zeros(robot.n_joints)
    schedule = sorted(payloads or [], key=lambda x: x[0])
    for k in range(n):
        while schedule and schedule[0][0] <= t[k]:
            physics.attach_payload(schedule.pop(0)[1])
        tau = control(q_meas, qd_meas, q_ref[k], qd_ref[k], qdd_ref[k])
        permille = permille_of(tau / kt, rated)
        m = physics.step(current_of(permille, rated))
        q_meas = np.round(m.position * counts) / counts
        qd_meas = np.round(m.velocity * counts) / counts
        out_q[k], out_qd[k], true_q[k] = q_meas, qd_meas, m.true_position
        out_i[k] = np.round(m.current / rated * 1000.0) / 1000.0 * rated
    return OfflineRun(t + period_s, out_q, out_qd, out_i, out_i * kt, true_q, q_ref)

"""The 2 ms control law of excitation: PD plus feed-forward from the modeled parameters.

``tau = RNEA(q_r, qd_r, qdd_r) + Kp (q_r - q) + Kd (qd_r - qd)``: the feed-forward does the
work (computed from the parameters the robot file models, Pinocchio's RNEA on the same
model as :mod:`identify.pinocchio_bridge`), the PD only corrects the model's error. Default
gains put each joint at 5 Hz, critically damped, on the diagonal of its mass matrix at
the reference pose (rotor inertias included when given): stiff enough to track, slow enough for one cycle of delay at 2 ms.
"""

from __future__ import annotations

import numpy as np

from .pinocchio_bridge import to_pinocchio
from .robot import Robot
from .spatial import Array


class ComputedTorque:
    """PD plus feed-forward; with ``decoupled`` the PD acts through the mass matrix at the
    measured pose, ``tau = RNEA(ref) + M(q) (w^2 e + 2 w e')``, so that every mode of the
    coupled arm has the same bandwidth ``w`` at every pose (diagonal gains leave the
    lightest mode of strongly coupled joints, PUMA joints 1-3, much faster than designed,
    and without margin for delay)."""

    def __init__(self, robot: Robot, phi: Array | None = None, kp: Array | None = None, kd: Array | None = None,
                 bandwidth_hz: float = 5.0, q_nominal: Array | None = None, armature: Array | None = None,
                 decoupled: bool = False) -> None:
        import pinocchio as pin

        self._pin = pin
        self.model = to_pinocchio(robot, phi)
        n = robot.n_joints
        if armature is not None:
            self.model.armature = np.asarray(armature, float)  # rotor inertias, where known
        self.data = self.model.createData()
        q0 = np.zeros(n) if q_nominal is None else np.asarray(q_nominal, float)
        mass = pin.crba(self.model, self.data, q0)
        diag = np.maximum(np.diag(mass), 1e-3)
        w = 2.0 * np.pi * bandwidth_hz
        self.kp = w**2 * diag if kp is None else np.asarray(kp, float)
        self.kd = 2.0 * w * diag if kd is None else np.asarray(kd, float)
        self.decoupled = decoupled
        self.w = w
        self._upper = np.triu(np.ones((n, n), bool))

    def feed_forward(self, q_ref: Array, qd_ref: Array, qdd_ref: Array) -> Array:
        return np.asarray(self._pin.rnea(self.model, self.data, q_ref, qd_ref, qdd_ref)).copy()

    def __call__(self, q: Array, qd: Array, q_ref: Array, qd_ref: Array, qdd_ref: Array) -> Array:
        if self.decoupled:
            mass = self._pin.crba(self.model, self.data, q)
            mass = np.where(self._upper, mass, mass.T)  # crba fills the upper triangle
            correction = self.w**2 * (q_ref - q) + 2.0 * self.w * (qd_ref - qd)
            return self.feed_forward(q_ref, qd_ref, qdd_ref) + mass @ correction
        return self.feed_forward(q_ref, qd_ref, qdd_ref) + self.kp * (q_ref - q) + self.kd * (qd_ref - qd)

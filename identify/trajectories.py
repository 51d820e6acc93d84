"""Finite Fourier series joint trajectories (Swevers et al. 1997), analytic in q, qd, qdd.

.. math:: q_j(t) = q_{0j} + \\sum_{l=1}^{L} \\frac{a_{jl}}{\\omega_f l} \\sin(\\omega_f l t)
                 - \\frac{b_{jl}}{\\omega_f l} \\cos(\\omega_f l t)

Periodic, so that averaging periods and differentiating are exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .robot import Robot
from .spatial import Array


@dataclass(frozen=True)
class FourierTrajectory:
    """Coefficients ``a, b`` (N, L), offsets ``q0`` (N,), base frequency in Hz."""

    q0: Array
    a: Array
    b: Array
    base_frequency_hz: float

    def evaluate(self, t: Array) -> tuple[Array, Array, Array]:
        """``q, qd, qdd`` (n, N) at times ``t`` (n,)."""
        wf = 2.0 * np.pi * self.base_frequency_hz
        harmonics = np.arange(1, self.a.shape[1] + 1)
        phase = wf * np.outer(t, harmonics)  # (n, L)
        s, c = np.sin(phase), np.cos(phase)
        lw = wf * harmonics
        q = self.q0 + s @ (self.a / lw).T - c @ (self.b / lw).T
        qd = c @ self.a.T + s @ self.b.T
        qdd = -s @ (self.a * lw).T + c @ (self.b * lw).T
        return q, qd, qdd


def random_fourier_trajectory(robot: Robot, harmonics: int = 5, base_frequency_hz: float = 0.1, fill: float = 0.6, seed: int = 0) -> FourierTrajectory:
    """A random trajectory scaled to use ``fill`` of each joint's position and velocity range."""
    rng = np.random.default_rng(seed)
    n = robot.n_joints
    a = rng.normal(size=(n, harmonics))
    b = rng.normal(size=(n, harmonics))
    lo = np.array([j.limits.position[0] if j.limits.position else -np.pi for j in robot.joints])
    hi = np.array([j.limits.position[1] if j.limits.position else np.pi for j in robot.joints])
    vmax = np.array([j.limits.velocity if j.limits.velocity else 2.0 for j in robot.joints])
    traj = FourierTrajectory(np.zeros(n), a, b, base_frequency_hz)
    t = np.linspace(0.0, 1.0 / base_frequency_hz, 2000)
    q, qd, _ = traj.evaluate(t)
    span = np.ptp(q, axis=0)
    scale = np.minimum(fill * (hi - lo) / span, fill * vmax / np.abs(qd).max(axis=0))
    a, b = a * scale[:, None], b * scale[:, None]
    q = q * scale
    q0 = 0.5 * (lo + hi) - 0.5 * (q.max(axis=0) + q.min(axis=0))
    return FourierTrajectory(q0, a, b, base_frequency_hz)

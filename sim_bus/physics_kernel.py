"""The compiled part of one physics sub-step: the joints' effects and the implicit solve.

In numpy the effects (friction, cogging, spring, load friction) and their slope are dozens of
calls on six-element arrays, and with the solve they made a 2 ms step cost about 0.5 ms on a
2-core CI machine: a quarter of the simulated arm's process, which with its bus traffic needed
a whole core and lost cycles over ``udp_multicast`` (issue 31). Compiled, they cost a few
microseconds; Pinocchio's ``crba`` and ``rnea`` stay as they are. The compilation is paid when
:class:`~sim_bus.physics.ArmPhysics` is made, before any bus thread runs, and cached by numba.

``effects`` holds one column per joint, its rows the :class:`~sim_bus.physics.JointEffects`
fields named in :data:`EFFECT_ROWS`.
"""

from __future__ import annotations

import numba
import numpy as np

EFFECT_ROWS = ("coulomb", "viscous", "stribeck", "stribeck_velocity", "cogging", "cogging_period",
               "cogging_phase", "spring", "spring_rest", "load_friction")
SMOOTH_SIGN = 1e-3  # rad/s over which the sign of the velocity is smoothed (tanh)

_njit = numba.njit(cache=True, error_model="numpy", boundscheck=False)


@_njit
def substep(mass_upper: np.ndarray, bias: np.ndarray, q: np.ndarray, qd: np.ndarray, current: np.ndarray,
            command: np.ndarray, alpha: float, motor_gain: np.ndarray, offset: np.ndarray, free: np.ndarray,
            effects: np.ndarray, dt: float) -> np.ndarray:
    """One semi-implicit Euler sub-step, in place on ``q``, ``qd`` and ``current``; returns the
    acceleration. The current follows ``command`` through a first-order lag (``alpha`` per
    sub-step), the motors make ``motor_gain * current``. The acceleration solves
    ``(M + dt D) a = tau - b`` on the free joints (braked ones stay at rest): linearly implicit
    Euler for the effects, ``D`` their slope (>= 0, so that stiff friction stays stable) at the
    velocity with braked joints at rest, ``tau`` the motor's torque plus ``offset`` less the
    effects (friction, cogging, spring, and load friction: Coulomb friction in proportion to the
    motor's torque, :class:`~sim_bus.physics.JointEffects`). ``mass_upper`` is ``crba``'s upper
    triangle and ``bias`` ``rnea`` at that velocity, both at the sub-step's start."""
    n = q.shape[0]
    rows = np.zeros(n, np.int64)  # the free joints, in order
    m = 0
    for j in range(n):
        if free[j]:
            rows[m] = j
            m += 1
    a = np.zeros((m, m))
    rhs = np.zeros(m)
    for r in range(m):
        j = rows[r]
        current[j] = current[j] + alpha * (command[j] - current[j])
        fc, fv, fs, vs = effects[0, j], effects[1, j], effects[2, j], effects[3, j]
        th = np.tanh(qd[j] / SMOOTH_SIGN)
        decay = np.exp(-min(abs(qd[j] / vs), 30.0) ** 2)
        torque = (fc + fs * decay) * th + fv * qd[j]
        torque = torque + effects[4, j] * np.sin(2.0 * np.pi * q[j] / effects[5, j] + effects[6, j])
        torque = torque + effects[7, j] * (q[j] - effects[8, j])
        tau_motor = motor_gain[j] * current[j]
        load = effects[9, j] * abs(tau_motor)
        flat = 1.0 - th * th
        stribeck = fs * decay * (flat / SMOOTH_SIGN - 2.0 * (qd[j] / vs) / vs * th)
        slope = max(0.0, fv + fc * flat / SMOOTH_SIGN + stribeck) + load * flat / SMOOTH_SIGN
        rhs[r] = tau_motor + offset[j] - (torque + load * th) - bias[j]
        for c in range(m):
            k = rows[c]
            a[r, c] = mass_upper[min(j, k), max(j, k)]
        a[r, r] += dt * slope
    _cholesky_solve(a, rhs)
    acc = np.zeros(n)
    for r in range(m):
        acc[rows[r]] = rhs[r]
    for j in range(n):
        if not free[j]:
            current[j] = current[j] + alpha * (command[j] - current[j])
            qd[j] = 0.0
        else:
            qd[j] = qd[j] + acc[j] * dt
        q[j] = q[j] + qd[j] * dt
    return acc


@_njit
def _cholesky_solve(a: np.ndarray, rhs: np.ndarray) -> None:
    """Solve ``a x = rhs`` for a symmetric positive definite ``a``, in place: ``a``'s lower
    triangle becomes its Cholesky factor, ``rhs`` becomes ``x``."""
    m = rhs.shape[0]
    for j in range(m):
        for k in range(j):
            a[j, j] -= a[j, k] * a[j, k]
        a[j, j] = np.sqrt(a[j, j])
        for i in range(j + 1, m):
            for k in range(j):
                a[i, j] -= a[i, k] * a[j, k]
            a[i, j] /= a[j, j]
    for i in range(m):  # forward, then back substitution
        for k in range(i):
            rhs[i] -= a[i, k] * rhs[k]
        rhs[i] /= a[i, i]
    for i in range(m - 1, -1, -1):
        for k in range(i + 1, m):
            rhs[i] -= a[k, i] * rhs[k]
        rhs[i] /= a[i, i]

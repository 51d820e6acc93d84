"""On-line payload estimation: recursive least squares on what the arm model leaves over.

Khosla's on-line strategy: with the arm's own parameters known, a payload rigidly held by
the last link only adds to that link's ten parameters, so (eq. 18)

.. math:: \\tau - M(q, \\dot q, \\ddot q)\\,\\phi_{arm} = M_{:,N}(q, \\dot q, \\ddot q)\\,\\phi_p

with ``M_{:,N}`` the regressor columns of link N (every joint's row) and ``phi_p`` the
payload's ``m, m s, I`` about the last link's frame. Each 2 ms sample gives N equations;
RLS folds them in one sample at a time (:func:`rls_update`, a vector measurement with the
per-joint noise of the identification as its covariance).

- Velocity and acceleration come from positions by the causal 5-point filter applied twice
  (Khosla 5.1), so every equation refers to the sample four periods back: the estimator
  runs live.
- Exponential forgetting (``forgetting``) follows a payload that changes, but only while
  the arm moves: at rest the equations carry no new information about most directions
  and forgetting would inflate the covariance without bound (wind-up). The covariance is
  also never let grow past its prior.
- A change of payload shows as innovations far beyond their predicted spread: when the
  normalized innovation squared, averaged over ``change_window`` samples, exceeds
  ``change_threshold`` times its expected value, the covariance is reset to the prior so
  that the estimate moves to the new payload at once.
- The noise each joint's equation carries is tracked from the innovations (time constant
  ``noise_time_constant_s``, outliers clipped at 3 sigma), starting from the
  identification's per-joint sigma: the live derivatives are noisier than the filtered
  ones identification used, and a wrong noise level makes the innovation test fire on noise.
- Directions the motion does not excite keep their prior (a zero payload) and their prior
  standard deviation; :attr:`PayloadRLS.excited_` says which.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numba
import numpy as np

from .dynamics import regressor
from .effects import LinearEffect
from .robot import Robot, inertial_from_parameters
from .spatial import Array

MIN_SPEED = 0.02
REVERSAL_MARGIN_S = 0.025
PRIOR_STD = np.array([5.0, 0.5, 0.5, 0.5, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05])
"""Prior standard deviations of ``m, msx, msy, msz, Ixx..Izz`` (kg, kg m, kg m^2): a
payload of up to a few kg within half a metre of the flange."""


def rls_update(theta: Array, p: Array, h: Array, y: Array, r: Array, forgetting: float = 1.0) -> tuple[Array, Array, Array, float]:
    """One RLS step with a vector measurement ``y = h theta + v``, ``cov(v) = diag(r)``.

    Returns the new ``theta`` and ``P``, the innovation ``nu = y - h theta`` and its
    normalized square ``nu^T S^-1 nu`` with ``S = h P h^T + R`` (before the update).
    """
    innovation = y - h @ theta
    ph = p @ h.T
    s = h @ ph
    s[np.diag_indices_from(s)] += r
    s_inv = np.linalg.inv(s)
    gain = ph @ s_inv
    theta = theta + gain @ innovation
    a = np.eye(p.shape[0]) - gain @ h
    p = a @ p @ a.T + (gain * r) @ gain.T  # Joseph form: stays symmetric positive definite
    p = 0.5 * (p + p.T) / forgetting
    return theta, p, innovation, float(innovation @ s_inv @ innovation)


@numba.njit(cache=True)
def _fold_kernel(h_all, residual, sliding, moving, r, theta, p, prior_var, forgetting, nis, nis_state,
                 change_threshold, start, stop, noise_rate=0.0):  # type: ignore[no-untyped-def]
    """Rows ``start..stop`` folded in, compiled: the arithmetic of :func:`rls_update`, then
    the wind-up cap, the noise tracking and the innovation test. ``r`` (per joint) is
    updated in place when ``noise_rate`` > 0. ``nis`` is the window's ring buffer and
    ``nis_state`` holds [count, next slot, resets, updates]."""
    n_par = theta.shape[0]
    for i in range(start, stop):
        use = np.flatnonzero(sliding[i])
        if use.size == 0:
            continue
        h = h_all[i][use]
        y = residual[i][use]
        lam = forgetting if moving[i] else 1.0
        innovation = y - h @ theta
        ph = p @ h.T
        s = h @ ph
        for j in range(use.size):
            s[j, j] += r[use[j]]
        s_inv = np.linalg.inv(s)
        gain = ph @ s_inv
        theta = theta + gain @ innovation
        a = np.eye(n_par) - gain @ h
        p = a @ p @ a.T + (gain * r[use]) @ gain.T
        p = 0.5 * (p + p.T) / lam
        if lam != 1.0:
            for a in range(n_par):
                if p[a, a] > prior_var[a]:
                    sc = np.sqrt(prior_var[a] / p[a, a])
                    p[a, :] *= sc
                    p[:, a] *= sc
        value = (innovation @ s_inv @ innovation) / use.size
        if noise_rate > 0.0:
            for j in range(use.size):  # the noise this estimator sees, outliers clipped at 3 sigma
                k = use[j]
                r[k] += noise_rate * (min(innovation[j] ** 2, 9.0 * r[k]) - r[k])
        window = nis.shape[0]
        nis[nis_state[1]] = value
        nis_state[1] = (nis_state[1] + 1) % window
        nis_state[0] = min(nis_state[0] + 1, window)
        if nis_state[0] == window and nis.mean() > change_threshold:
            p = np.diag(prior_var)
            nis_state[0] = 0
            nis_state[1] = 0
            nis_state[2] += 1
        nis_state[3] += 1
    return theta, p


@dataclass(frozen=True)
class ArmModel:
    """The identified arm: ``tau = W(q, qd, qdd)[:, columns] @ beta`` (base parameters of an
    identification, with its effect columns); ``joint_sigma`` is each joint's noise."""

    robot: Robot
    effects: tuple[LinearEffect, ...]
    columns: Array
    beta: Array
    joint_sigma: Array

    def torque(self, q: Array, qd: Array, qdd: Array) -> Array:
        from .identification import stacked_regressor

        n, nj = q.shape
        w = stacked_regressor(self.robot, list(self.effects), q, qd, qdd).reshape(n, nj, -1)
        return w[:, :, self.columns] @ self.beta


@dataclass
class _Filter:
    """Causal 5-point derivatives of a stream: positions in, (q, qd, qdd) four samples back out."""

    period_s: float
    q: deque = field(default_factory=lambda: deque(maxlen=9))  # type: ignore[type-arg]
    qd: deque = field(default_factory=lambda: deque(maxlen=5))  # type: ignore[type-arg]
    tau: deque = field(default_factory=lambda: deque(maxlen=5))  # type: ignore[type-arg]

    def reset(self) -> None:
        self.q.clear()
        self.qd.clear()
        self.tau.clear()

    @staticmethod
    def _d(x: deque, period_s: float) -> Array:  # type: ignore[type-arg]
        return (-2.0 * x[-5] - x[-4] + x[-2] + 2.0 * x[-1]) / (10.0 * period_s)

    def push(self, q: Array, tau: Array) -> tuple[Array, Array, Array, Array] | None:
        self.q.append(q)
        self.tau.append(tau)
        if len(self.q) < 5:
            return None
        self.qd.append(self._d(self.q, self.period_s))  # at the sample 2 back
        if len(self.qd) < 5:
            return None
        qdd = self._d(self.qd, self.period_s)  # at the sample 4 back
        return self.q[-5], self.qd[-3], qdd, self.tau[-5]


class PayloadRLS:
    """Recursive least squares on the payload's parameters (scikit-learn style).

    Hyperparameters only here; ``fit`` starts over, ``partial_fit`` goes on; learned state
    ends in ``_``. See the module docstring for the method.
    """

    def __init__(self, arm: ArmModel, period_s: float, forgetting: float = 0.998, moving_rad_s: float = 0.05,
                 change_window: int = 25, change_threshold: float = 8.0, prior_std: Array | None = None,
                 noise_time_constant_s: float = 2.0) -> None:
        self.arm = arm
        self.period_s = period_s
        self.forgetting = forgetting
        self.moving_rad_s = moving_rad_s
        self.change_window = change_window
        self.change_threshold = change_threshold
        self.prior_std = PRIOR_STD if prior_std is None else np.asarray(prior_std, float)
        self.noise_time_constant_s = noise_time_constant_s

    def _start(self) -> None:
        self.theta_ = np.zeros(10)
        self.P_ = np.diag(self.prior_std**2)
        self.filter_ = _Filter(self.period_s)
        self.noise_var_ = np.maximum(np.asarray(self.arm.joint_sigma, float), 1e-6) ** 2
        self._nis = np.zeros(self.change_window)
        self._nis_count = 0
        self._nis_next = 0
        self.n_updates_ = 0
        self.resets_ = 0
        self.time_s_ = float("nan")

    def fit(self, t: Array, q: Array, tau: Array) -> PayloadRLS:
        self._start()
        return self.partial_fit(t, q, tau)

    def restart_filter(self) -> None:
        """Samples were skipped: the derivatives start again (the estimate is kept)."""
        self.filter_.reset()

    def partial_fit(self, t: Array, q: Array, tau: Array, checkpoints: Iterable[int] = (),
                    on_checkpoint: Callable[[int], None] | None = None) -> PayloadRLS:
        """Fold in consecutive samples: times (n,), positions and torques (n, N).

        ``on_checkpoint(k)`` is called once sample ``k`` of this batch has been folded in,
        for each ``k`` in ``checkpoints``: a stream publishes there, and a batch of any size
        gives the same estimates as one sample at a time.
        """
        if not hasattr(self, "theta_"):
            self._start()
        t, q, tau = np.atleast_1d(t), np.atleast_2d(q), np.atleast_2d(tau)
        rows: list[tuple[Any, ...]] = []
        produced = np.full(t.shape[0], -1)
        for k in range(t.shape[0]):
            out = self.filter_.push(q[k], tau[k])
            if out is not None:
                produced[k] = len(rows)
                rows.append((t[k] - 4 * self.period_s, *out))
        wanted = set(checkpoints)
        if rows:
            ts = np.array([r[0] for r in rows])
            qs, qds, qdds, taus = (np.array([r[i] for r in rows]) for i in range(1, 5))
            n = self.arm.robot.n_joints
            residual = taus - self.arm.torque(qs, qds, qdds)
            h_all = regressor(self.arm.robot, qs, qds, qdds)[:, :, 10 * (n - 1) : 10 * n]
            # a joint's equation is left out while it is near rest or reversing: sign(qd) is
            # wrong there (as in identification), and one wrong Coulomb step looks like a new payload
            sliding = np.abs(qds) >= np.maximum(MIN_SPEED, np.abs(qdds) * REVERSAL_MARGIN_S)
            moving = np.abs(qds).max(axis=1) > self.moving_rad_s
        r = self.noise_var_  # updated in place by the kernel
        stops = sorted(k for k in wanted if 0 <= k < t.shape[0]) + [t.shape[0] - 1]
        done_rows = 0
        for k in stops:
            upto = int(produced[: k + 1].max()) + 1 if (produced[: k + 1] >= 0).any() else 0
            if upto > done_rows:
                self._fold_rows(h_all, residual, sliding, moving, r, done_rows, upto)
                self.time_s_ = float(ts[upto - 1])
                done_rows = upto
            if k in wanted and on_checkpoint is not None:
                on_checkpoint(k)
        return self

    def _fold_rows(self, h_all: Array, residual: Array, sliding: Array, moving: Array, r: Array, start: int, stop: int) -> None:
        state = np.array([self._nis_count, self._nis_next, 0, 0], np.int64)
        self.theta_, self.P_ = _fold_kernel(h_all, residual, sliding, moving, self.noise_var_, self.theta_, self.P_, self.prior_std**2,
                                            self.forgetting, self._nis, state, self.change_threshold, start, stop,
                                            self.period_s / self.noise_time_constant_s)
        self._nis_count, self._nis_next = int(state[0]), int(state[1])
        self.resets_ += int(state[2])
        self.n_updates_ += int(state[3])

    # --- what the estimate means ---
    @property
    def std_(self) -> Array:
        return np.sqrt(np.maximum(np.diag(self.P_), 0.0))

    @property
    def excited_(self) -> Array:
        """Per parameter: the data have told more than the prior (std below half of it)."""
        return self.std_ < 0.5 * self.prior_std

    def estimate(self) -> dict[str, Any]:
        """Mass (kg), centre of mass (m) and inertia about it (kg m^2, xx xy xz yy yz zz) in
        the last link's frame, with standard deviations (delta method for the COM)."""
        th, p = self.theta_, self.P_
        m = float(th[0])
        std = self.std_
        if abs(m) > 1e-3:
            c = th[1:4] / m
            jac = np.zeros((3, 10))
            jac[:, 0] = -th[1:4] / m**2
            jac[:, 1:4] = np.eye(3) / m
            com_std = np.sqrt(np.maximum(np.diag(jac @ p @ jac.T), 0.0))
            i_com = np.array(inertial_from_parameters(th).inertia_kgm2)
        else:
            c, com_std, i_com = np.full(3, np.nan), np.full(3, np.nan), np.full(6, np.nan)
        converged = bool(std[0] < max(0.05 * abs(m), 0.05) and (abs(m) < 0.2 or np.all(com_std < 0.01)))
        return {"time": self.time_s_, "mass": m, "mass_std": float(std[0]), "com": c.tolist(), "com_std": com_std.tolist(),
                "inertia": i_com.tolist(), "inertia_std": std[4:].tolist(), "parameters": th.tolist(), "parameters_std": std.tolist(),
                "excited": self.excited_.tolist(), "converged": converged, "updates": self.n_updates_, "resets": self.resets_}


def arm_model_from_identification(robot: Robot, doc: dict[str, Any], seed: int = 0) -> ArmModel:
    """The arm model of an ``armid identify --json`` document, checked against the robot:
    the base parameters are rebuilt from the kinematics and must read as the document's."""
    from .errors import IdentificationError
    from .identification import declared_effects, structural_base

    effects = declared_effects(robot)
    base = structural_base(robot, effects, seed)
    exprs = base.expressions()
    got = [b["expression"] for b in doc.get("base_parameters", [])]
    if got != exprs:
        first = next((k for k, (a, b) in enumerate(zip(exprs, got)) if a != b), min(len(exprs), len(got)))
        raise IdentificationError(
            f"the identification's base parameters do not match {robot.name}'s model (declared effects included): "
            f"{len(got)} against {len(exprs)}; first difference at #{first + 1}: "
            f"{got[first] if first < len(got) else '(none)'!r} vs {exprs[first] if first < len(exprs) else '(none)'!r}")
    beta = np.array([b["value"] for b in doc["base_parameters"]], float)
    sigma = np.asarray(doc.get("joint_noise_sigma") or [1.0] * robot.n_joints, float)
    return ArmModel(robot, tuple(effects), base.independent, beta, sigma)

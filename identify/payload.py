"""On-line payload estimation: recursive least squares on what the arm model leaves over.

Khosla's on-line strategy: with the arm's own parameters known, a payload rigidly held by
the last link only adds to that link's ten parameters, so (eq. 18)

.. math:: \\tau - M(q, \\dot q, \\ddot q)\\,\\phi_{arm} = M_{:,N}(q, \\dot q, \\ddot q)\\,\\phi_p

with ``M_{:,N}`` the regressor columns of link N (every joint's row) and ``phi_p`` the
payload's ``m, m s, I`` about the last link's frame. Each sample gives N equations; RLS
folds them in one sample at a time (:func:`rls_update`).

- **The record's own clock.** Velocity and acceleration come from positions by the 5-point
  least-squares slope (Khosla 5.1) applied twice, computed on the records' time stamps
  (``sum((t - tbar) x) / sum((t - tbar)^2)``, which is the 5-point filter when the steps are
  equal): no configured period enters. Above 500 Hz the windows take every k-th record
  (points at least 2 ms apart). Each equation refers to the sample 4 k records back, so the
  estimator runs live. A step more than 1.5 times longer or shorter than the
  one before (a rate change, a gap) restarts the derivatives, counted in ``rate_changes_``.
- **Forgetting** is a factor per 2 ms of the arm's time (``forgetting ** (dt / 2 ms)``),
  and applies only while the arm moves: at rest the equations carry no new information
  about most directions and forgetting would inflate the covariance (wind-up). The
  covariance is never let grow past its prior.
- **Gross errors and payload changes.** Before an update the normalized innovation squared
  per equation is tested: beyond ``GROSS_NIS`` (5 sigma rms) the update is not taken (a
  stalled first cycle, a glitch). A change of payload shows as a window of
  ``change_window`` samples averaging over ``change_threshold``: the covariance is reset to
  the prior and the estimate moves to the new payload at once.
- **Noise** of each joint's equation is tracked from the innovations (time constant
  ``noise_time_constant_s`` of the arm's time, outliers clipped at 3 sigma), starting from
  the identification's per-joint sigma.
- **Physically possible estimates.** What is published is the projection of the estimate
  onto the payloads that can exist (mass >= 0 and the pseudo-inertia
  ``[[tr(I)/2 1 - I, m s], [m s^T, m]]`` positive semidefinite; Wensing et al. 2017), in the
  metric of the estimate's covariance: directions the data pin down move least. The
  unconstrained estimate is kept beside it.
- **Converged** means: the mass (and, with a mass, the centre of mass) excited, their
  standard deviations below ``MASS_STD_KG + MASS_STD_REL m`` and ``COM_STD_M``, and the
  whitened innovations of the last ``CONSISTENCY_WINDOW_S`` no larger than their covariance
  allows (a chi-square test at 0.1 %).
- **Reference mode** (:class:`ReferenceRun`): with a run of the same trajectory without the
  payload, each sample's residual has the unloaded run's residual at the same position
  taken off, so that arm-model and friction errors cancel.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .dynamics import forward_recursion, kinematic_matrix, pseudo_rotation, selection_vector
from .effects import LinearEffect, effect_columns
from .robot import Robot, inertia_entries, inertia_matrix, inertial_from_parameters
from .spatial import Array

MIN_SPEED = 0.02
REVERSAL_MARGIN_S = 0.025
PRIOR_STD = np.array([5.0, 0.5, 0.5, 0.5, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05])
"""Prior standard deviations of ``m, msx, msy, msz, Ixx..Izz`` (kg, kg m, kg m^2): a
payload of up to a few kg within half a metre of the flange."""
PARAMETER_NAMES = ("m", "msx", "msy", "msz", "Ixx", "Ixy", "Ixz", "Iyy", "Iyz", "Izz")
FORGETTING_STEP_S = 0.002
"""The forgetting factor is given per this much of the arm's time (0.998: a memory of 1 s)."""
RATE_CHANGE_RATIO = 1.5
"""A step this many times longer or shorter than the previous one restarts the derivatives."""
GROSS_NIS = 25.0
"""Normalized innovation squared per equation beyond which an update is not taken (5 sigma rms)."""
MASS_STD_KG, MASS_STD_REL, COM_STD_M = 0.02, 0.02, 0.005
"""Converged needs std(mass) <= 0.02 kg + 2 % of the mass and std(centre of mass) <= 5 mm per axis."""
MIN_MASS_FOR_COM_KG = 0.1
"""Below this mass no centre of mass or inertia is reported (they are divided by the mass)."""
CONSISTENCY_WINDOW_S = 1.0
FILTER_CORRELATION = 9
"""Records the twice-applied 5-point filter spans: innovations are correlated over about
this many updates, so a window of n equations counts n / 9 independent degrees of freedom."""


def rls_update(theta: Array, p: Array, h: Array, y: Array, r: Array, forgetting: float = 1.0) -> tuple[Array, Array, Array, float]:
    """One RLS step with a vector measurement ``y = h theta + v``, ``cov(v) = diag(r)``.

    Returns the new ``theta`` and ``P``, the innovation ``nu = y - h theta`` and its
    normalized square ``nu^T S^-1 nu`` with ``S = h P h^T + R`` (before the update). The
    Joseph form keeps ``P`` symmetric positive definite.
    """
    innovation = y - h @ theta
    ph = p @ h.T
    s = h @ ph
    s[np.diag_indices_from(s)] += r
    s_inv = np.linalg.inv(s)
    gain = ph @ s_inv
    theta = theta + gain @ innovation
    a = np.eye(p.shape[0]) - gain @ h
    p = a @ p @ a.T + (gain * r) @ gain.T
    p = 0.5 * (p + p.T) / forgetting
    return theta, p, innovation, float(innovation @ s_inv @ innovation)


# --- physical consistency ---
def pseudo_inertia(phi: Array) -> Array:
    """The 4x4 pseudo-inertia ``[[tr(I)/2 1 - I, h], [h^T, m]]`` of ``m, h = m s, I`` (about
    the frame origin): positive semidefinite exactly when some mass distribution has these
    parameters (Wensing, Kim, Slotine 2017)."""
    i3 = inertia_matrix(phi[4:10])
    j = np.empty((4, 4))
    j[:3, :3] = 0.5 * np.trace(i3) * np.eye(3) - i3
    j[:3, 3] = j[3, :3] = phi[1:4]
    j[3, 3] = phi[0]
    return j


def _phi_of_pseudo(j: Array) -> Array:
    sigma = j[:3, :3]
    i3 = np.trace(sigma) * np.eye(3) - sigma
    return np.concatenate([[j[3, 3]], j[:3, 3], inertia_entries(i3)])


_BASIS = np.stack([pseudo_inertia(e) for e in np.eye(10)])  # the linear map phi -> pseudo-inertia, (10, 4, 4)
_BASIS_FLAT = _BASIS.reshape(10, 16)


def project_feasible(theta: Array, cov: Array, gap: float = 1e-5, start: Array | None = None) -> Array:
    """The physically possible parameters nearest ``theta`` in the metric ``cov^-1``.

    Minimizes ``(x - theta)^T cov^-1 (x - theta) / 2`` subject to ``pseudo_inertia(x)``
    positive semidefinite (so mass >= 0 follows) by a log-barrier interior point method:
    Newton steps on ``f(x) - mu log det J(x)``, ``mu`` divided by 50 until the duality gap
    ``4 mu`` is below ``gap`` of ``f``. Every iterate is strictly feasible, so the result is
    physically possible even when the iterations stop early. ``theta`` is returned
    unchanged when it is feasible already. ``start``, a strictly feasible point near the
    answer (the last projection), starts the path late: a few Newton steps instead of tens.
    """
    theta = np.asarray(theta, float)
    w, v = np.linalg.eigh(pseudo_inertia(theta))
    scale = max(float(np.abs(w).max()), 1e-12)
    if w.min() >= 0.0:
        return theta.copy()
    cov = 0.5 * (cov + cov.T)
    weight = np.linalg.inv(cov + 1e-15 * np.trace(cov) * np.eye(10))
    weight = 0.5 * (weight + weight.T)
    d = 1.0 / np.sqrt(np.maximum(np.diag(weight), 1e-300))  # diagonal preconditioner for the Newton systems

    def pseudo(x: Array) -> Array:
        return (x @ _BASIS_FLAT).reshape(4, 4)

    x = _phi_of_pseudo((v * np.maximum(w, 1e-3 * scale)) @ v.T)  # strictly feasible start
    e = x - theta
    fx = 0.5 * float(e @ weight @ e)
    mu = max(fx, 1e-300) / 4.0
    if start is not None and np.linalg.eigvalsh(pseudo(start)).min() > 0:
        e_s = start - theta
        f_s = 0.5 * float(e_s @ weight @ e_s)
        if f_s < fx:  # the last answer: straight to the final barrier weight
            x, e, fx, mu = np.array(start, float), e_s, f_s, max(f_s, 1e-300) * gap / 4.0
    chol = np.linalg.cholesky(pseudo(x))
    for _ in range(40):
        for _ in range(30):
            ci = np.linalg.inv(chol)
            b = (ci.T @ ci) @ _BASIS  # (10, 4, 4): J^-1 A_k
            grad = weight @ e - mu * np.trace(b, axis1=1, axis2=2)
            hess = weight + mu * (b.reshape(10, 16) @ b.transpose(0, 2, 1).reshape(10, 16).T)
            try:
                step = -d * np.linalg.solve(hess * np.outer(d, d), d * grad)
            except np.linalg.LinAlgError:
                return x  # feasible, if not the last word
            decrement = -float(grad @ step)
            if not np.isfinite(decrement):
                return x
            if decrement <= 1e-10 * (fx + mu):
                break
            # the longest step that stays inside the cone, then backtracking (Armijo)
            lam = np.linalg.eigvalsh(ci @ pseudo(step) @ ci.T).min()
            t = 1.0 if lam >= -1.0 else min(1.0, -0.99 / lam)
            phi0 = fx - 2.0 * mu * float(np.log(np.diag(chol)).sum())
            while t > 1e-12:
                trial = x + t * step
                try:
                    chol_t = np.linalg.cholesky(pseudo(trial))
                except np.linalg.LinAlgError:
                    t *= 0.5
                    continue
                e_t = trial - theta
                f_t = 0.5 * float(e_t @ weight @ e_t)
                if f_t - 2.0 * mu * float(np.log(np.diag(chol_t)).sum()) <= phi0 - 0.25 * t * decrement:
                    break
                t *= 0.5
            else:
                break
            x, e, fx, chol = trial, e_t, f_t, chol_t
        if 4.0 * mu <= gap * max(fx, 1e-300):
            break
        mu /= 50.0
    return x


# --- the arm model, evaluated without compiled code (nothing to compile on a cold start) ---
@dataclass(frozen=True)
class ArmModel:
    """The identified arm: ``tau = W(q, qd, qdd)[:, columns] @ beta`` (base parameters of an
    identification, with its effect columns); ``joint_sigma`` is each joint's noise."""

    robot: Robot
    effects: tuple[LinearEffect, ...]
    columns: Array
    beta: Array
    joint_sigma: Array

    def _phi(self) -> Array:
        n_std = 10 * self.robot.n_joints
        phi = np.zeros(n_std + sum(len(e.parameter_names) for e in self.effects))
        phi[np.asarray(self.columns, int)] = self.beta
        return phi

    def torque_and_payload_columns(self, q: Array, qd: Array, qdd: Array) -> tuple[Array, Array]:
        """The arm's modeled torque (n, N) and the payload's regressor ``M_{:,N}`` (n, N, 10).

        One backward pass of eq. (16), ``g_{i-1} = R_i g_i + K_{i-1} phi_{i-1}`` and
        ``tau_i = s_i^T g_i`` (eq. 17), carrying ``R_{i+1} ... R_N K_N`` beside it for the
        last link's columns. Plain numpy: the estimator has nothing to compile before the
        arm moves (a cold compile of the batched kernel takes tens of seconds).
        """
        robot = self.robot
        nj = robot.n_joints
        motions = forward_recursion(robot, q, qd, qdd)
        phi = self._phi()
        n = motions[0].w.shape[0]
        tau, cols = np.empty((n, nj)), np.empty((n, nj, 10))
        g, c = np.zeros((n, 6)), np.zeros((n, 6, 10))
        for i in range(nj - 1, -1, -1):
            k = kinematic_matrix(motions[i])
            if i == nj - 1:
                c = k
            else:
                r = pseudo_rotation(motions[i + 1], motions[i].rho)
                g = np.einsum("nab,nb->na", r, g)
                c = r @ c
            g = g + k @ phi[10 * i : 10 * i + 10]
            s = selection_vector(motions[i])
            tau[:, i] = g @ s
            cols[:, i] = np.einsum("a,nab->nb", s, c)
        if self.effects:
            tau += effect_columns(list(self.effects), np.atleast_2d(q), np.atleast_2d(qd), np.atleast_2d(qdd)) @ phi[10 * nj :]
        return tau, cols

    def torque(self, q: Array, qd: Array, qdd: Array) -> Array:
        return self.torque_and_payload_columns(q, qd, qdd)[0]


def slope_on_times(t: Array, x: Array) -> Array:
    """Least-squares slope of ``x`` (k, ...) on its times ``t`` (k,): the 5-point filter of
    Khosla 5.1 when the steps are equal, and right when they are not. Both are centred
    first: time stamps are often seconds since 1970 (ulp 0.24 us), and ``sum(dt x)`` with
    an uncentred ``x`` turns that rounding into velocity errors of percent."""
    tr = t - t[0]
    dt = tr - tr.mean()
    return np.tensordot(dt, x - x.mean(axis=0), axes=(0, 0)) / float(dt @ dt)


def derivatives_on_times(t: Array, x: Array) -> tuple[Array, Array]:
    """Non-causal velocity and acceleration of a recording (n, N) on its own time stamps:
    the 5-point slope twice; the first and last 4 samples are NaN."""
    n = t.size
    qd, qdd = np.full(x.shape, np.nan), np.full(x.shape, np.nan)
    if n < 9:
        return qd, qdd
    t = t - t[0]  # centred windows below: see slope_on_times
    idx = np.arange(2, n - 2)[:, None] + np.arange(-2, 3)[None, :]
    tw = t[idx]
    dt = tw - tw.mean(axis=1, keepdims=True)
    den = (dt * dt).sum(axis=1)
    xw = x[idx]
    qd[2:-2] = np.einsum("kw,kwj->kj", dt, xw - xw.mean(axis=1, keepdims=True)) / den[:, None]
    tm = np.full(n, np.nan)
    tm[2:-2] = tw.mean(axis=1)  # each velocity belongs to its window's mean time (as in _Filter)
    idx2 = np.arange(4, n - 4)[:, None] + np.arange(-2, 3)[None, :]
    dt2 = tm[idx2] - tm[idx2].mean(axis=1, keepdims=True)
    vw = qd[idx2]
    qdd[4:-4] = np.einsum("kw,kwj->kj", dt2, vw - vw.mean(axis=1, keepdims=True)) / (dt2 * dt2).sum(axis=1)[:, None]
    return qd, qdd


MIN_STEP_S = 0.002
"""The 5-point windows take records at least this far apart (every k-th record at a higher
rate): on 1 ms data the plain filter's acceleration noise, in the regressor, biased the
mass low by 3 % (errors in variables)."""


@dataclass
class _Filter:
    """Causal 5-point derivatives of a stream on its time stamps: (t, positions, torques) in,
    (t, q, qd, qdd, tau) 4 k records back out, the windows taking every k-th record so that
    their points are at least ``MIN_STEP_S`` apart."""

    ratio: float = RATE_CHANGE_RATIO
    t: deque = field(default_factory=deque)  # type: ignore[type-arg]
    q: deque = field(default_factory=deque)  # type: ignore[type-arg]
    tau: deque = field(default_factory=deque)  # type: ignore[type-arg]
    qd: deque = field(default_factory=deque)  # type: ignore[type-arg]
    tqd: deque = field(default_factory=deque)  # type: ignore[type-arg]
    rate_changes: int = 0
    stride: int = 0

    def reset(self) -> None:
        for d in (self.t, self.q, self.tau, self.qd, self.tqd):
            d.clear()
        self.stride = 0

    def push(self, t: float, q: Array, tau: Array) -> tuple[float, Array, Array, Array, Array] | None:
        if len(self.t) >= 2:
            step, before = t - self.t[-1], self.t[-1] - self.t[-2]
            if step > self.ratio * before or step * self.ratio < before:
                self.rate_changes += 1
                self.reset()
        if self.stride == 0 and self.t:
            self.stride = max(1, int(round(MIN_STEP_S / (t - self.t[-1]))))
        self.t.append(t)
        self.q.append(q)
        self.tau.append(tau)
        k = self.stride
        if k == 0 or len(self.t) < 4 * k + 1:
            return None
        while len(self.t) > 4 * k + 1:
            self.t.popleft()
            self.q.popleft()
            self.tau.popleft()
        picks = range(-1 - 4 * k, 0, k)
        tw = np.array([self.t[i] for i in picks])
        self.qd.append(slope_on_times(tw, np.array([self.q[i] for i in picks])))
        self.tqd.append(tw.mean())
        if len(self.qd) < 4 * k + 1:
            return None
        while len(self.qd) > 4 * k + 1:
            self.qd.popleft()
            self.tqd.popleft()
        qdd = slope_on_times(np.array([self.tqd[i] for i in picks]), np.array([self.qd[i] for i in picks]))
        return self.t[0], self.q[0], self.qd[-1 - 2 * k], qdd, self.tau[0]


class ReferenceRun:
    """A run of the same trajectory without the payload, looked up by position.

    Its arm-model residual ``tau - M phi_arm`` (derivatives on its own time stamps) is
    taken off the loaded run's residual at the same point of the trajectory, so that what
    the arm model and friction get wrong cancels and the payload's torque remains. The
    point is found by position: the nearest reference sample within ``search_s`` of where
    the last match predicts (same speed), refined onto the segment to its neighbours. A
    sample further than ``tolerance_rad`` from the reference path gives no equation.
    """

    def __init__(self, arm: ArmModel, t: Array, q: Array, tau: Array, tolerance_rad: float = 0.05, search_s: float = 0.25) -> None:
        t, q, tau = np.asarray(t, float), np.asarray(q, float), np.asarray(tau, float)
        qd, qdd = derivatives_on_times(t, q)
        ok = np.isfinite(qdd).all(axis=1)
        if ok.sum() < 9:
            raise ValueError(f"the reference run has {t.size} samples: too few to differentiate")
        self.t, self.q = t[ok], q[ok]
        self.residual = tau[ok] - arm.torque(q[ok], qd[ok], qdd[ok])
        self.step_s = float(np.median(np.diff(self.t)))
        self.tolerance_rad = tolerance_rad
        self.window = max(2, int(round(search_s / self.step_s)))
        self.cursor: int | None = None
        self.last_t = 0.0
        self.first_t: float | None = None
        self.misses = 0
        self.matched = 0

    def restart(self) -> None:
        self.cursor = None

    def lookup(self, t: float, q: Array) -> tuple[Array, float]:
        """The reference residual at the pose ``q`` of time ``t`` and its distance (rad)."""
        n = self.t.size
        if self.first_t is None:
            self.first_t = t
        if self.cursor is None:  # both runs start together; afterwards, follow the matches
            guess = int(np.searchsorted(self.t, self.t[0] + (t - self.first_t)))
        else:
            guess = self.cursor + int(round((t - self.last_t) / self.step_s))
        lo, hi = max(0, guess - self.window), min(n, guess + self.window + 1)
        if lo >= hi:
            lo, hi = max(0, n - 2 * self.window), n
        d2 = ((self.q[lo:hi] - q) ** 2).sum(axis=1)
        k = lo + int(np.argmin(d2))
        if d2[k - lo] > self.tolerance_rad**2 and self.misses > 50:  # lost: search the whole run
            d2_all = ((self.q - q) ** 2).sum(axis=1)
            k = int(np.argmin(d2_all))
        best, best_d, res = k, float(((self.q[k] - q) ** 2).sum()), self.residual[k]
        for a, b in ((k - 1, k), (k, k + 1)):
            if 0 <= a and b < n:
                seg = self.q[b] - self.q[a]
                den = float(seg @ seg)
                if den > 0:
                    s = min(1.0, max(0.0, float((q - self.q[a]) @ seg) / den))
                    d = float(((self.q[a] + s * seg - q) ** 2).sum())
                    if d < best_d:
                        best_d, res = d, (1 - s) * self.residual[a] + s * self.residual[b]
        self.cursor, self.last_t = best, t
        dist = float(np.sqrt(best_d))
        if dist > self.tolerance_rad:
            self.misses += 1
        else:
            self.misses = 0
            self.matched += 1
        return res, dist


class PayloadRLS:
    """Recursive least squares on the payload's parameters (scikit-learn style).

    Hyperparameters only here; ``fit`` starts over, ``partial_fit`` goes on; learned state
    ends in ``_``. See the module docstring for the method. No sample period: every update
    uses the records' time stamps.
    """

    def __init__(self, arm: ArmModel, *, forgetting: float = 0.998, moving_rad_s: float = 0.05, change_window: int = 25,
                 change_threshold: float = 8.0, prior_std: Array | None = None, noise_time_constant_s: float = 2.0,
                 reference: ReferenceRun | None = None) -> None:
        self.arm = arm
        self.forgetting = forgetting
        self.moving_rad_s = moving_rad_s
        self.change_window = change_window
        self.change_threshold = change_threshold
        self.prior_std = PRIOR_STD if prior_std is None else np.asarray(prior_std, float)
        self.noise_time_constant_s = noise_time_constant_s
        self.reference = reference

    def _start(self) -> None:
        if not 0.0 < self.forgetting <= 1.0:
            raise ValueError(f"forgetting must be in (0, 1], got {self.forgetting}")
        self.theta_ = np.zeros(10)
        self.P_ = np.diag(self.prior_std**2)
        self.filter_ = _Filter()
        self.noise_var_ = np.maximum(np.asarray(self.arm.joint_sigma, float), 1e-6) ** 2
        self._change: deque[float] = deque(maxlen=self.change_window)
        self._window: deque[tuple[float, float, float, int]] = deque()  # (time, nis, dof, rejected)
        self._last_row_t: float | None = None
        self.n_updates_ = 0
        self.resets_ = 0
        self.rejected_ = 0
        self.time_s_ = float("nan")
        self.innovation_ = np.zeros(0)
        self._projected: tuple[Any, Array] | None = None

    @property
    def rate_changes_(self) -> int:
        return self.filter_.rate_changes

    def fit(self, t: Array, q: Array, tau: Array) -> PayloadRLS:
        self._start()
        return self.partial_fit(t, q, tau)

    def restart_filter(self) -> None:
        """Samples were skipped: the derivatives start again (the estimate is kept)."""
        if not hasattr(self, "theta_"):
            self._start()
        self.filter_.reset()
        self._last_row_t = None
        if self.reference is not None:
            self.reference.restart()

    def warm(self) -> None:
        """Run every code path once on a copy (imports, first-call costs) before the arm moves."""
        robot = self.arm.robot
        clone = PayloadRLS(self.arm, forgetting=self.forgetting, prior_std=self.prior_std)
        t = np.arange(12) * 0.002
        q = 0.1 * np.sin(np.outer(t, np.arange(1, robot.n_joints + 1)))
        clone.fit(t, q, np.zeros_like(q)).estimate()
        project_feasible(-np.ones(10) * 0.01, np.eye(10))

    def partial_fit(self, t: Array, q: Array, tau: Array, checkpoints: Iterable[int] = (),
                    on_checkpoint: Callable[[int], None] | None = None) -> PayloadRLS:
        """Fold in consecutive samples: times (n,) in s, strictly increasing, positions and
        torques (n, N).

        ``on_checkpoint(k)`` is called once sample ``k`` of this batch has been folded in,
        for each ``k`` in ``checkpoints``: a stream publishes there, and a batch of any size
        gives the same estimates as one sample at a time.
        """
        if not hasattr(self, "theta_"):
            self._start()
        t, q, tau = np.atleast_1d(np.asarray(t, float)), np.atleast_2d(q), np.atleast_2d(tau)
        rows: list[tuple[Any, ...]] = []
        produced = np.full(t.shape[0], -1)
        for k in range(t.shape[0]):
            if self.filter_.t and not t[k] > self.filter_.t[-1]:
                raise ValueError(f"time {t[k]:.6g} s is not after the previous record's {self.filter_.t[-1]:.6g} s")
            out = self.filter_.push(float(t[k]), q[k], tau[k])
            if out is not None:
                produced[k] = len(rows)
                rows.append(out)
        wanted = set(checkpoints)
        if rows:
            ts = np.array([r[0] for r in rows])
            qs, qds, qdds, taus = (np.array([r[i] for r in rows]) for i in range(1, 5))
            model, h_all = self.arm.torque_and_payload_columns(qs, qds, qdds)
            residual = taus - model
            # a joint's equation is left out while it is near rest or reversing: sign(qd) is
            # wrong there (as in identification), and one wrong Coulomb step looks like a new payload
            sliding = np.abs(qds) >= np.maximum(MIN_SPEED, np.abs(qdds) * REVERSAL_MARGIN_S)
            if self.reference is not None:
                for i in range(len(rows)):
                    ref, dist = self.reference.lookup(float(ts[i]), qs[i])
                    residual[i] -= ref
                    if dist > self.reference.tolerance_rad:
                        sliding[i] = False
            moving = np.abs(qds).max(axis=1) > self.moving_rad_s
            prev = np.concatenate([[ts[0] if self._last_row_t is None else self._last_row_t], ts[:-1]])
            dts = np.clip(ts - prev, 0.0, 0.1)
            self._last_row_t = float(ts[-1])
        stops = sorted(k for k in wanted if 0 <= k < t.shape[0]) + [t.shape[0] - 1]
        done_rows = 0
        for k in stops:
            upto = int(produced[: k + 1].max()) + 1 if (produced[: k + 1] >= 0).any() else 0
            if upto > done_rows:
                self._fold_rows(ts, h_all, residual, sliding, moving, dts, done_rows, upto)
                self.time_s_ = float(ts[upto - 1])
                done_rows = upto
            if k in wanted and on_checkpoint is not None:
                on_checkpoint(k)
        return self

    def _fold_rows(self, ts: Array, h_all: Array, residual: Array, sliding: Array, moving: Array, dts: Array, start: int, stop: int) -> None:
        theta, p, r = self.theta_, self.P_, self.noise_var_
        prior_var = self.prior_std**2
        eye = np.eye(10)
        for i in range(start, stop):
            use = sliding[i]
            if not use.any():
                continue
            h, y, rj = h_all[i][use], residual[i][use], r[use]
            innovation = y - h @ theta
            ph = p @ h.T
            s = h @ ph + np.diag(rj)
            s_inv = np.linalg.inv(s)
            dof = int(use.sum())
            nis = float(innovation @ s_inv @ innovation)
            self._change.append(nis / dof)
            if len(self._change) == self.change_window and sum(self._change) > self.change_threshold * self.change_window:
                p = np.diag(prior_var)  # a new payload: start over from the prior, keep the estimate
                self._change.clear()
                self.resets_ += 1
                continue
            if nis / dof > GROSS_NIS:
                self.rejected_ += 1
                self._window.append((float(ts[i]), nis, dof, 1))
                continue
            gain = ph @ s_inv
            theta = theta + gain @ innovation
            a = eye - gain @ h
            p = a @ p @ a.T + (gain * rj) @ gain.T
            p = 0.5 * (p + p.T)
            # the noise this estimator sees: E[e^2] = r - (h P+ h^T) for the residual e after
            # the update (unbiased whatever P is; innovation^2 - h P h^T is not when P is large)
            post = innovation - h @ (gain @ innovation)
            seen = np.minimum(post**2 + np.einsum("ij,jk,ik->i", h, p, h), 9.0 * rj)
            if moving[i]:
                p = p / self.forgetting ** (dts[i] / FORGETTING_STEP_S)
                d = np.diag(p)
                if (d > prior_var).any():  # never past the prior: no wind-up
                    sc = np.sqrt(np.minimum(1.0, prior_var / d))
                    p = p * np.outer(sc, sc)
            rate = dts[i] / self.noise_time_constant_s
            r[use] = rj + rate * (seen - rj)  # outliers clipped at 3 sigma
            self._window.append((float(ts[i]), nis, dof, 0))
            self.n_updates_ += 1
            self.innovation_ = innovation
        while self._window and self._window[0][0] < ts[stop - 1] - CONSISTENCY_WINDOW_S:
            self._window.popleft()
        self.theta_, self.P_ = theta, p

    # --- what the estimate means ---
    @property
    def std_(self) -> Array:
        return np.sqrt(np.maximum(np.diag(self.P_), 0.0))

    @property
    def excited_(self) -> Array:
        """Per parameter: the data have told more than the prior (std below half of it)."""
        return self.std_ < 0.5 * self.prior_std

    def consistency(self) -> dict[str, Any]:
        """Chi-square test of the whitened innovations over the last second of the arm's time:
        ``sum(nis) / c`` against the 99.9 % point of chi-square with ``sum(dof) / c`` degrees of
        freedom, ``c`` the filter's correlation length. One-sided: innovations larger than their
        covariance allows (a model error, a wrong clock) fail it; smaller ones mean the stated
        std is cautious. More than 2 % gross errors in the window fail it too."""
        taken = [w for w in self._window if not w[3]]
        rejected = len(self._window) - len(taken)
        dof = sum(w[2] for w in taken)
        if dof < 5 * FILTER_CORRELATION:
            return {"consistent": False, "nis_per_dof": None, "equations": dof, "rejected": rejected}
        nis = sum(w[1] for w in taken)
        k = dof / FILTER_CORRELATION
        stat = nis / FILTER_CORRELATION
        ok = bool(stat <= _chi2_upper(k)) and rejected <= 0.02 * len(self._window)
        return {"consistent": ok, "nis_per_dof": nis / dof, "equations": dof, "rejected": rejected}

    def feasible_(self) -> Array:
        """The published parameters: :func:`project_feasible` of ``theta_`` (cached per update)."""
        key = (self.n_updates_ + self.resets_ + self.rejected_, self.theta_.tobytes())
        if self._projected is None or self._projected[0] != key:
            last = self._projected[1] if self._projected is not None else None
            self._projected = (key, project_feasible(self.theta_, self.P_, start=last))
        return self._projected[1]

    def estimate(self) -> dict[str, Any]:
        """Mass (kg), centre of mass (m) and inertia about it (kg m^2, xx xy xz yy yz zz) in
        the last link's frame, physically possible, with standard deviations (delta method for
        the centre of mass); ``null`` for what the motion so far does not determine."""
        if not hasattr(self, "theta_"):
            self._start()
        th_u, p = self.theta_, self.P_
        th = self.feasible_()
        std = self.std_
        excited = self.excited_
        m = float(th[0])
        mass_known = bool(excited[0])
        com = com_std = inertia = None
        if mass_known and m >= MIN_MASS_FOR_COM_KG:
            c = th[1:4] / m
            jac = np.zeros((3, 10))
            jac[:, 0] = -th[1:4] / m**2
            jac[:, 1:4] = np.eye(3) / m
            cs = np.sqrt(np.maximum(np.diag(jac @ p @ jac.T), 0.0))
            com, com_std = c.tolist(), cs.tolist()
            inertia = list(inertial_from_parameters(th).inertia_kgm2)
        cons = self.consistency()
        mass_ok = mass_known and std[0] <= MASS_STD_KG + MASS_STD_REL * m
        com_ok = m < MIN_MASS_FOR_COM_KG or (com_std is not None and bool(excited[1:4].all()) and max(com_std) <= COM_STD_M)
        converged = bool(mass_ok and com_ok and cons["consistent"])
        if not mass_known:
            status = "not excited"
        elif converged:
            status = "converged"
        elif not cons["consistent"] and cons["nis_per_dof"] is not None:
            status = "inconsistent"
        else:
            status = "converging"
        doc = {"time": self.time_s_, "mass": m if mass_known else None, "mass_std": float(std[0]), "com": com, "com_std": com_std,
               "inertia": inertia, "inertia_std": std[4:].tolist(), "parameters": th.tolist(), "parameters_std": std.tolist(),
               "excited": excited.tolist(), "excited_parameters": [n for n, e in zip(PARAMETER_NAMES, excited) if e],
               "converged": converged, "status": status, "consistency": cons,
               "unconstrained": {"mass": float(th_u[0]), "parameters": th_u.tolist(), "feasible": bool(np.allclose(th, th_u))},
               "updates": self.n_updates_, "resets": self.resets_, "rejected": self.rejected_, "rate_changes": self.rate_changes_}
        return json_safe(doc)


def _chi2_upper(k: float, z: float = 3.0902) -> float:
    """The 99.9 % point of chi-square with ``k`` degrees of freedom (Wilson-Hilferty; within
    1.2 % of scipy's for k >= 5, 0.1 % for k >= 50)."""
    a = 2.0 / (9.0 * k)
    return float(k * (1.0 - a + z * np.sqrt(a)) ** 3)


def json_safe(x: Any) -> Any:
    """``x`` with every non-finite float replaced by None: valid JSON (``null``, never ``NaN``)."""
    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [json_safe(v) for v in x]
    if isinstance(x, float | np.floating):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


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

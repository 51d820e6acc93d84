"""Exciting trajectories (Khosla 5.2): designed, checked against every limit, then run.

A design is a finite Fourier series per moving joint (Swevers et al. 1997,
:class:`~identify.trajectories.FourierTrajectory`) that starts and ends at rest: with
``qd(0) = sum_l a_l = 0`` and ``qdd(0) = w_f sum_l l b_l = 0`` built into the
parameterisation (the last harmonic's coefficients are fixed by the others), so every
candidate the optimiser sees satisfies them exactly. Each joint's amplitude is then scaled
so that its position stays inside its range and its velocity and acceleration inside their
limits, all with a margin; the modeled rigid-body torque (eq. 18 with the robot file's
parameters) is held under its margin by shrinking the amplitudes further.

Criterion: **D-optimality**, the log-determinant of the information matrix ``W_b^T W_b``
of the experiment's base regressor. Unlike the condition number it is smooth in the
coefficients (the condition number jumps when the weakest direction changes) and
invariant to the units of the parameters (a fixed column scaling only adds a constant), and
it is the volume of the estimates' confidence ellipsoid, the quantity identification cares
about. The condition number is reported beside it.

A plan wraps a design for the drives: a quintic lead-in from where the arm is to the
trajectory's start, whole periods of the trajectory, and rest. :func:`check_plan` samples
it at the control period and refuses it, naming the first violation, before any drive is
enabled.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
from scipy.optimize import minimize
from threadpoolctl import threadpool_limits

from .dynamics import regressor
from .effects import effect_columns
from .errors import TrajectoryLimitError
from .identifiability import BaseParameters, base_parameters, preferred_order
from .identification import declared_effects, stacked_regressor
from .kernels.regressor_lanes import SERIAL_BELOW
from .robot import Robot
from .spatial import Array
from .trajectories import FourierTrajectory

_F = TypeVar("_F", bound=Callable[..., Any])


def _one_blas_thread(fn: _F) -> _F:
    """Run ``fn`` with BLAS and LAPACK on one thread. Designing is many small products and
    factorisations, which two OpenBLAS threads do no faster, and on a loaded machine far
    slower: measured at load average 10 on 2 cores, the identifiability QR of one design
    (1,872 x 78) took 1.35 s on two threads, a (25, 74,880) matrix-vector product 25 ms
    against 0.9 ms on one. (The limit is process-wide while it holds.)"""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with threadpool_limits(1, "blas"):
            return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]


@dataclass(frozen=True)
class Limits:
    """Per-joint limits as arrays (N,); ``inf`` where the robot file gives none."""

    position_low: Array
    position_high: Array
    velocity: Array
    acceleration: Array
    torque: Array

    @staticmethod
    def of(robot: Robot, default_acceleration: float = 10.0) -> Limits:
        lo = np.array([j.limits.position[0] if j.limits.position else -np.inf for j in robot.joints])
        hi = np.array([j.limits.position[1] if j.limits.position else np.inf for j in robot.joints])
        vel = np.array([j.limits.velocity or np.inf for j in robot.joints])
        acc = np.array([j.limits.acceleration or default_acceleration for j in robot.joints])
        tau = np.array([j.limits.torque or np.inf for j in robot.joints])
        return Limits(lo, hi, vel, acc, tau)


@dataclass(frozen=True)
class Design:
    """An exciting trajectory and what it excites.

    ``moving`` are the joints that move (0-based); the others hold ``trajectory.q0``.
    ``base`` are the readable base parameters the experiment identifies, ``unidentifiable``
    the parameters it leaves out, ``condition_number`` that of its column-scaled base
    regressor, ``log_det`` the D-criterion, ``peak`` the largest |value| / limit per kind.
    """

    trajectory: FourierTrajectory
    moving: tuple[int, ...]
    rows: tuple[int, ...]
    base: list[str]
    unidentifiable: list[str]
    rank: int
    condition_number: float
    log_det: float
    peak: dict[str, list[float]]
    criterion: str = "D-optimal: log det(W_b^T W_b)"

    def to_json(self) -> dict[str, object]:
        t = self.trajectory
        return {
            "moving_joints": [j + 1 for j in self.moving],
            "torque_rows": [j + 1 for j in self.rows],
            "criterion": self.criterion,
            "rank": self.rank,
            "condition_number": self.condition_number,
            "log_det": self.log_det,
            "base_parameters": self.base,
            "unidentifiable": self.unidentifiable,
            "peak_fraction_of_limit": self.peak,
            "fourier": {"base_frequency_hz": t.base_frequency_hz, "q0": t.q0.tolist(), "a": t.a.tolist(), "b": t.b.tolist()},
        }


def _rest_to_rest(free_a: Array, free_b: Array) -> tuple[Array, Array]:
    """Append the last harmonic so that ``qd(0) = qdd(0) = 0``: (k, L-1) -> (k, L)."""
    L = free_a.shape[1] + 1
    last_a = -free_a.sum(axis=1)
    last_b = -(free_b * np.arange(1, L)).sum(axis=1) / L
    return np.hstack([free_a, last_a[:, None]]), np.hstack([free_b, last_b[:, None]])


def experiment_columns(robot: Robot, rows: tuple[int, ...]) -> tuple[list[int], list[str]]:
    """The regressor columns that the torque rows ``rows`` can involve: the links from the
    first row's on (eq. 17: row i holds links i..N) and the declared effects of those joints."""
    effects = declared_effects(robot)
    first = min(rows)
    cols = list(range(10 * first, 10 * robot.n_joints))
    names = robot.parameter_names + [label for e in effects for label in e.labels()]
    offset = robot.n_parameters
    for e in effects:
        k = len(e.parameter_names)
        if e.joint in rows:
            cols += list(range(offset, offset + k))
        offset += k
    return cols, names


def experiment_regressor(robot: Robot, rows: tuple[int, ...], q: Array, qd: Array, qdd: Array) -> Array:
    """(n len(rows), P) rows of eq. (18) with effect columns: every column, so that one
    index space serves every experiment."""
    n, nj = q.shape
    w = stacked_regressor(robot, declared_effects(robot), q, qd, qdd).reshape(n, nj, -1)
    return w[:, list(rows), :].reshape(-1, w.shape[2])


class _Candidates:
    """Many candidate designs of one experiment, evaluated together.

    The optimiser's gradient needs the regressor at ``k + 1`` nearby coefficient vectors.
    One at a time (L-BFGS-B's own finite differences), each paid the Python overhead of the
    scaling and of a regressor call on a few hundred samples, then a Gram matrix and a
    determinant: about 8 ms, 4,000 times for a whole-arm design. Here the candidates share
    one pass: their Fourier series, their scaling into the limits, one regressor call over
    all their samples into a buffer kept for the design (reused for the torque check and for
    the information matrix), and one contraction with the criterion's differential
    (:meth:`cost_and_gradient`). Each candidate goes through the arithmetic of the scaling
    it went through on its own.
    """

    def __init__(self, robot: Robot, limits: Limits, q_hold: Array, moving: tuple[int, ...], f_hz: float, margin: float,
                 t: Array, phi: Array, rows: tuple[int, ...], indep: list[int]) -> None:
        self.robot, self.limits, self.moving, self.f_hz, self.margin, self.phi = robot, limits, list(moving), f_hz, margin, phi
        self.q_hold, self.rows, self.indep, self.t = np.asarray(q_hold, float), list(rows), indep, t
        self.effects = declared_effects(robot)
        self.scale: Array | None = None
        lo, hi = limits.position_low, limits.position_high
        finite = np.isfinite(lo) & np.isfinite(hi)
        self.half_range = np.where(finite, 0.5 * (hi - lo), np.pi)
        self.centre = np.where(finite, 0.5 * (hi + lo), self.q_hold)
        self.per_call = max(1, SERIAL_BELOW // t.size)  # candidates per regressor call: one thread, a few MB at a time
        n = robot.n_joints
        self._width = 10 * n + sum(len(e.parameter_names) for e in self.effects)
        self._buffer = np.empty((self.per_call * t.size, n, self._width))

    def _evaluate(self, q0: Array, a: Array, b: Array) -> tuple[Array, Array, Array]:
        """``q, qd, qdd`` (m, T, N) of the series ``q0`` (m, N), ``a, b`` (m, N, L), as
        :meth:`FourierTrajectory.evaluate` does for one."""
        wf = 2.0 * np.pi * self.f_hz
        harmonics = np.arange(1, a.shape[2] + 1)
        phase = wf * np.outer(self.t, harmonics)
        s, c = np.sin(phase), np.cos(phase)
        lw = wf * harmonics
        q = q0[:, None, :] + s @ (a / lw).transpose(0, 2, 1) - c @ (b / lw).transpose(0, 2, 1)
        qd = c @ a.transpose(0, 2, 1) + s @ b.transpose(0, 2, 1)
        qdd = -s @ (a * lw).transpose(0, 2, 1) + c @ (b * lw).transpose(0, 2, 1)
        return q, qd, qdd

    def _regressor(self, q: Array, qd: Array, qdd: Array) -> Array:
        """(m, T, N, P) stacked regressor (rigid body and declared effects) of every sample, as
        :func:`~identify.identification.stacked_regressor`; a view of the buffer, for
        m < ``per_call``, valid until the next call."""
        m, T, n = q.shape
        q, qd, qdd = q.reshape(-1, n), qd.reshape(-1, n), qdd.reshape(-1, n)
        if m > self.per_call:
            return stacked_regressor(self.robot, self.effects, q, qd, qdd).reshape(m, T, n, -1)
        w = self._buffer[: m * T]
        regressor(self.robot, q, qd, qdd, out=w[:, :, : 10 * n])
        if self.effects:
            w[:, :, 10 * n :] = effect_columns(self.effects, q, qd, qdd, rigid=w[:, :, : 10 * n])
        return w.reshape(m, T, n, -1)

    def scaled(self, a: Array, b: Array, reduce: Callable[[Array], Array]) -> tuple[Array, Array, Array, Array]:
        """The moving joints' series ``a, b`` (m, k, L) scaled into the limits: ``q0`` (m, N),
        ``A, B`` (m, N, L), and ``reduce`` of the (m, T, N, P) regressor of the final
        trajectories (the torque check's, or computed anew for a candidate still over after 30
        shrinks), which keeps the whole regressor of only a few candidates at a time."""
        m, L, n, lim, margin = a.shape[0], a.shape[2], self.robot.n_joints, self.limits, self.margin
        A, B = np.zeros((m, n, L)), np.zeros((m, n, L))
        A[:, self.moving], B[:, self.moving] = a, b
        q, qd, qdd = self._evaluate(np.zeros((m, n)), A, B)
        span = 0.5 * np.ptp(q, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.minimum.reduce([margin * self.half_range / span, margin * lim.velocity / np.abs(qd).max(axis=1),
                                   margin * lim.acceleration / np.abs(qdd).max(axis=1)])
        s = np.where(np.isfinite(s), s, 0.0)
        mid = 0.5 * (q.max(axis=1) + q.min(axis=1))
        q0 = np.tile(self.q_hold, (m, 1))
        q0[:, self.moving] = self.centre[self.moving] - s[:, self.moving] * mid[:, self.moving]
        A, B = A * s[:, :, None], B * s[:, :, None]
        reduced: Array | None = None
        active = np.arange(m)
        for _ in range(30):  # torque: shrink the motion until the modeled torque fits
            motion = self._evaluate(q0[active], A[active], B[active])
            w = self._regressor(*motion)
            tau = np.einsum("mtnp,p->mtn", w[..., : 10 * n], self.phi)  # not BLAS: its threads stall on a loaded machine
            with np.errstate(invalid="ignore"):
                ratio = (np.abs(tau).max(axis=1) / (margin * lim.torque)).max(axis=1)
                over = ~(ratio <= 1.0)
                r = 0.97 / np.sqrt(ratio[over])
                shrink = np.where(r > 0.5, r, 0.5)  # as max(0.5, r), which takes 0.5 for a NaN ratio
            if not over.all():
                part = reduce(w if not over.any() else w[~over])
                reduced = np.empty((m, *part.shape[1:])) if reduced is None else reduced
                reduced[active[~over]] = part
            active = active[over]
            if not active.size:
                break
            q_now = motion[0][over]
            mid_q = 0.5 * (q_now.max(axis=1) + q_now.min(axis=1))
            q0[active] = mid_q - shrink[:, None] * (mid_q - q0[active])
            A[active] *= shrink[:, None, None]
            B[active] *= shrink[:, None, None]
        else:
            part = reduce(self._regressor(*self._evaluate(q0[active], A[active], B[active])))
            reduced = np.empty((m, *part.shape[1:])) if reduced is None else reduced
            reduced[active] = part
        assert reduced is not None
        return q0, A, B, reduced

    def _flat_columns(self, n: int, p: int) -> Array:
        """Indices into a sample's (N P) stacked row of the experiment's rows and base columns."""
        return (np.asarray(self.rows)[:, None] * p + np.asarray(self.indep, dtype=int)[None, :]).ravel()

    def information(self, w: Array) -> Array:
        """The experiment's base regressors (m, T len(rows), n_b) from the (m, T, N, P) stacked ones."""
        m, T, n, p = w.shape
        return np.take(w.reshape(m, T, n * p), self._flat_columns(n, p), axis=2).reshape(m, T * len(self.rows), len(self.indep))

    def cost_and_gradient(self, a: Array, b: Array, dx: Array) -> tuple[float, Array]:
        """Minus the D-criterion at the design ``a[0], b[0]`` and its gradient, from the
        designs ``a[1:], b[1:]`` whose coefficient vectors are that one's moved by ``dx``
        (k,) each along one coordinate.

        The criterion is ``f = -log det G`` of the column-scaled (``S``), sample-normalised
        information matrix ``G = S W^T W S / n``, whose differential is
        ``df = -(2/n) <W S G^-1 S, dW>``: one matrix, the lever, weighs each candidate's
        change of regressor in one pass over it, where the finite difference of ``f`` itself
        needed a Gram matrix and a determinant per candidate, the largest cost once the
        candidates were batched. So the gradient is finite differences of the regressor, to
        first order in the step as finite differences of ``f`` were."""
        assert self.scale is not None
        full = self.scaled(a[:1], b[:1], lambda w: w.copy())[3][0]
        ws = self.information(full[None])[0] / self.scale
        g = ws.T @ ws / ws.shape[0]
        sign, ld = np.linalg.slogdet(g)
        if sign <= 0:
            return 1e6, np.zeros(dx.size)
        lever = np.zeros(full.size)  # on the whole stacked regressor, zero off the experiment's rows and columns
        flat = self._flat_columns(full.shape[1], full.shape[2])
        lever.reshape(full.shape[0], -1)[:, flat] = ((-2.0 / ws.shape[0]) * np.linalg.solve(g, ws.T).T / self.scale).reshape(full.shape[0], -1)
        at = np.einsum("k,k->", full.reshape(-1), lever)
        change = np.empty(dx.size)
        for k in range(1, a.shape[0], self.per_call):
            change[k - 1 : k - 1 + self.per_call] = self.scaled(a[k : k + self.per_call], b[k : k + self.per_call],
                                                                lambda w: np.einsum("mk,k->m", w.reshape(w.shape[0], -1), lever) - at)[3]
        return float(-ld), change / dx


def _model_torque(robot: Robot, traj: FourierTrajectory, t: Array, phi: Array) -> Array:
    q, qd, qdd = traj.evaluate(t)
    return regressor(robot, q, qd, qdd) @ phi


def _experiment_base(robot: Robot, rows: tuple[int, ...], moving: tuple[int, ...], q_hold: Array, lim: Limits,
                     rng: np.random.Generator) -> tuple[list[int], list[str], BaseParameters, Array]:
    """The experiment's own base set: random motion of the moving joints about ``q_hold``."""
    n = robot.n_joints
    cols, names = experiment_columns(robot, rows)
    qr_ = np.tile(q_hold, (max(200, 4 * len(cols)), 1))
    qdr, qddr = np.zeros_like(qr_), np.zeros_like(qr_)
    for j in moving:
        lo = lim.position_low[j] if np.isfinite(lim.position_low[j]) else -np.pi
        hi = lim.position_high[j] if np.isfinite(lim.position_high[j]) else np.pi
        qr_[:, j] = rng.uniform(lo, hi, qr_.shape[0])
        qdr[:, j], qddr[:, j] = rng.normal(size=qr_.shape[0]), rng.normal(size=qr_.shape[0])
    w_rand = experiment_regressor(robot, rows, qr_, qdr, qddr)[:, cols]
    order_all = preferred_order(n, len(names) - robot.n_parameters)
    position = {c: k for k, c in enumerate(cols)}
    base = base_parameters(w_rand, [names[c] for c in cols], [position[c] for c in order_all if c in position])
    return cols, names, base, w_rand


@_one_blas_thread
def choose_hold(robot: Robot, joint: int, q_hold: Array, candidates: int = 12, margin: float = 0.7, seed: int = 0,
                gravity_fraction: float = 0.4) -> Array:
    """A pose of the joints before ``joint`` (the others keep ``q_hold``) at which moving
    ``joint`` alone identifies the most of its link: the rank of the experiment's base set
    first (a vertical axis hides the gravity terms), then the conditioning. Poses whose
    modeled gravity torque exceeds ``gravity_fraction`` of a torque limit are passed over."""
    lim = Limits.of(robot)
    rng = np.random.default_rng(seed)
    lo = np.where(np.isfinite(lim.position_low), lim.position_low, -np.pi)
    hi = np.where(np.isfinite(lim.position_high), lim.position_high, np.pi)
    mid, half = 0.5 * (lo + hi), 0.5 * margin * (hi - lo)
    best, best_key = np.asarray(q_hold, float), (-1, -np.inf)
    for c in range(candidates + 1):
        pose = np.asarray(q_hold, float).copy()
        if c:
            pose[:joint] = np.clip(np.round((q_hold[:joint] + rng.normal(0, 1.0, joint)) / (np.pi / 4)) * (np.pi / 4), mid[:joint] - half[:joint], mid[:joint] + half[:joint])
        z = np.zeros((1, robot.n_joints))
        gravity = (regressor(robot, pose[None], z, z) @ robot.modeled_parameters())[0]
        if c and (np.abs(gravity) > gravity_fraction * lim.torque).any():
            continue  # holding there would leave too little torque for the motion
        _, _, base, w = _experiment_base(robot, (joint,), (joint,), pose, lim, np.random.default_rng(seed))
        wb = w[:, base.independent]
        norms = np.linalg.norm(wb, axis=0)
        sv = np.linalg.svd(wb / np.where(norms > 0, norms, 1.0), compute_uv=False)
        key = (base.n_base, float(np.log(sv[-1] / sv[0])) if sv.size and sv[0] > 0 else -np.inf)
        if key > best_key:
            best, best_key = pose, key
    return best


@_one_blas_thread
def design(robot: Robot, moving: tuple[int, ...] | None = None, q_hold: Array | None = None, harmonics: int = 5,
           base_frequency_hz: float = 0.1, margin: float = 0.8, samples: int = 160, seed: int = 0, iterations: int = 30,
           starts: int = 2, rows: tuple[int, ...] | None = None) -> Design:
    """An exciting trajectory for the joints ``moving`` (default all), the others holding
    ``q_hold`` (default: mid-range).

    ``rows`` are the torque equations the experiment will use (default: every joint for a
    whole-arm run; the moving joint alone for a single-link run, Khosla's property 4). The
    base set is the experiment's own: computed on random motion of the moving joints only.
    The optimiser (L-BFGS-B, ``starts`` random starts, ``iterations`` each) works on
    ``samples`` points of one period.
    """
    n = robot.n_joints
    lim = Limits.of(robot)
    moving = tuple(range(n)) if moving is None else tuple(sorted(moving))
    if not moving or min(moving) < 0 or max(moving) >= n:
        raise ValueError(f"moving joints must be within 1..{n}, got {[j + 1 for j in moving]}")
    rows = (tuple(range(n)) if len(moving) == n else (min(moving),)) if rows is None else rows
    if q_hold is None:
        finite = np.isfinite(lim.position_low) & np.isfinite(lim.position_high)
        q_hold = np.where(finite, 0.5 * (lim.position_low + lim.position_high), 0.0)
    q_hold = np.asarray(q_hold, float)
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0 / base_frequency_hz, samples, endpoint=False)
    phi = robot.modeled_parameters()
    cols, names, base, _ = _experiment_base(robot, rows, moving, q_hold, lim, rng)
    indep = [cols[k] for k in base.independent]
    k_free = len(moving) * (harmonics - 1)

    space = _Candidates(robot, lim, q_hold, moving, base_frequency_hz, margin, t, phi, rows, indep)

    def split(x: Array) -> tuple[Array, Array]:
        """Coefficient vectors (m, 2 k_free) -> the moving joints' rest-to-rest ``a, b`` (m, k, L)."""
        m = x.shape[0]
        fa, fb = x[:, :k_free].reshape(m * len(moving), -1), x[:, k_free:].reshape(m * len(moving), -1)
        a, b = _rest_to_rest(fa, fb)
        return a.reshape(m, len(moving), -1), b.reshape(m, len(moving), -1)

    def trajectory_of(x: Array) -> tuple[FourierTrajectory, Array]:
        q0, a, b, w = space.scaled(*split(x[None]), space.information)
        return FourierTrajectory(q0[0], a[0], b[0], base_frequency_hz), w[0]

    def cost_and_gradient(x: Array) -> tuple[float, Array]:
        """The criterion and its gradient, the regressor's differences over a step of 1e-4
        (L-BFGS-B's own finite differences took that step) evaluated as one batch."""
        h = np.full_like(x, 1e-4)
        return space.cost_and_gradient(*split(np.vstack([x, x + np.diag(h)])), (x + h) - x)

    best_x, best_cost = None, np.inf
    for start in range(starts):
        x0 = rng.normal(size=2 * k_free)
        if space.scale is None:
            w0 = trajectory_of(x0)[1]
            norms = np.linalg.norm(w0, axis=0)
            space.scale = np.where(norms > 0, norms / np.sqrt(w0.shape[0]), 1.0)
        res = minimize(cost_and_gradient, x0, jac=True, method="L-BFGS-B", options={"maxiter": iterations // 3 if start else iterations})
        if res.fun < best_cost:
            best_x, best_cost = res.x, float(res.fun)
    assert best_x is not None
    traj, w = trajectory_of(best_x)
    ld = float(np.linalg.slogdet(w.T @ w)[1]) if w.size else 0.0
    norms = np.linalg.norm(w, axis=0)
    sv = np.linalg.svd(w / np.where(norms > 0, norms, 1.0), compute_uv=False)
    rank = int(np.sum(sv > 1e-7 * sv[0])) if sv.size and sv[0] > 0 else 0
    cond = float(sv[0] / sv[-1]) if sv.size and sv[-1] > 0 else float("inf")
    q, qd, qdd = traj.evaluate(t)
    tau = _model_torque(robot, traj, t, phi)
    lo, hi = lim.position_low, lim.position_high
    with np.errstate(divide="ignore", invalid="ignore"):
        pos = np.where(np.isfinite(hi - lo), np.maximum((q.max(0) - 0.5 * (hi + lo)), (0.5 * (hi + lo) - q.min(0))) / (0.5 * (hi - lo)), 0.0)
        peak = {"position": pos, "velocity": np.abs(qd).max(0) / lim.velocity, "acceleration": np.abs(qdd).max(0) / lim.acceleration,
                "torque": np.abs(tau).max(0) / lim.torque}
    used = set(indep) | {cols[k] for k in base.dependent if np.abs(base.regrouping[:, list(base.dependent).index(k)]).max() > 1e-9}
    unidentifiable = [names[c] for c in cols if c not in used]
    return Design(traj, moving, rows, base.expressions(), unidentifiable, rank, cond, ld,
                  {k: [float(x) for x in np.nan_to_num(v)] for k, v in peak.items()})


@dataclass(frozen=True)
class Plan:
    """What the drives are asked to do: lead-in from ``start`` to the trajectory's start
    (quintic, at rest at both ends), ``periods`` periods of it, then ``settle_s`` at rest."""

    start: Array
    trajectory: FourierTrajectory
    periods: int = 1
    lead_in_s: float = 1.0
    settle_s: float = 0.5
    metadata: dict[str, object] = field(default_factory=dict)

    @property
    def period_s(self) -> float:
        return 1.0 / self.trajectory.base_frequency_hz

    @property
    def duration_s(self) -> float:
        return self.lead_in_s + self.periods * self.period_s + self.settle_s

    @property
    def excitation_window(self) -> tuple[float, float]:
        return self.lead_in_s, self.lead_in_s + self.periods * self.period_s

    def evaluate(self, t: Array) -> tuple[Array, Array, Array]:
        """Reference ``q, qd, qdd`` (n, N) at times ``t`` (n,) from the plan's start."""
        t = np.atleast_1d(np.asarray(t, float))
        n = self.start.shape[0]
        q, qd, qdd = np.zeros((t.size, n)), np.zeros((t.size, n)), np.zeros((t.size, n))
        goal = self.trajectory.evaluate(np.zeros(1))[0][0]
        lead = t < self.lead_in_s
        if lead.any():
            s = t[lead] / self.lead_in_s
            d = goal - self.start
            p = 10 * s**3 - 15 * s**4 + 6 * s**5
            dp = (30 * s**2 - 60 * s**3 + 30 * s**4) / self.lead_in_s
            ddp = (60 * s - 180 * s**2 + 120 * s**3) / self.lead_in_s**2
            q[lead], qd[lead], qdd[lead] = self.start + np.outer(p, d), np.outer(dp, d), np.outer(ddp, d)
        t0, t1 = self.excitation_window
        run = (t >= t0) & (t < t1)
        if run.any():
            q[run], qd[run], qdd[run] = self.trajectory.evaluate(t[run] - t0)
        after = t >= t1
        q[after] = goal  # whole periods end where they began, at rest
        return q, qd, qdd


def plan(design_or_trajectory: Design | FourierTrajectory, start: Array, limits: Limits, periods: int = 1,
         lead_fraction: float = 0.5, settle_s: float = 0.5) -> Plan:
    """A plan whose lead-in stays within ``lead_fraction`` of the velocity and acceleration limits."""
    traj = design_or_trajectory.trajectory if isinstance(design_or_trajectory, Design) else design_or_trajectory
    start = np.asarray(start, float)
    d = np.abs(traj.evaluate(np.zeros(1))[0][0] - start)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_v = np.nan_to_num(1.875 * d / (lead_fraction * limits.velocity))
        t_a = np.nan_to_num(np.sqrt(5.7735 * d / (lead_fraction * limits.acceleration)))
    lead = float(max(1.0, t_v.max(), t_a.max()))
    return Plan(start, traj, periods, lead, settle_s)


def check_plan(robot: Robot, p: Plan, period_s: float, limits: Limits | None = None, phi: Array | None = None,
               torque_margin: float = 1.0) -> dict[str, list[float]]:
    """Every sample at the control period against every limit; raise on the first violation.

    Returns the peak fraction of each limit per joint. The torque is the modeled
    rigid-body torque (``phi``: default the robot file's values).
    """
    limits = limits or Limits.of(robot)
    t = np.arange(0.0, p.duration_s + 1e-12, period_s)
    q, qd, qdd = p.evaluate(t)
    bad = ~np.isfinite(q).all(axis=1) | ~np.isfinite(qd).all(axis=1) | ~np.isfinite(qdd).all(axis=1)
    if bad.any():
        raise TrajectoryLimitError(int(np.flatnonzero(~np.isfinite(q[bad][0]))[0]) if (~np.isfinite(q[bad][0])).any() else 0,
                                   "non-finite reference", float("nan"), 0.0, float(t[bad][0]), "")
    phi = robot.modeled_parameters() if phi is None else phi
    tau = regressor(robot, q, qd, qdd) @ phi
    checks = [
        ("position", q, limits.position_low, limits.position_high, "rad"),
        ("velocity", qd, -limits.velocity, limits.velocity, "rad/s"),
        ("acceleration", qdd, -limits.acceleration, limits.acceleration, "rad/s^2"),
        ("modeled torque", tau, -torque_margin * limits.torque, torque_margin * limits.torque, "N*m"),
    ]
    first: tuple[int, int, str, float, float, str] | None = None
    for kind, x, lo, hi, unit in checks:
        over = (x < lo - 1e-9) | (x > hi + 1e-9)
        if over.any():
            k, j = np.argwhere(over)[0]
            limit = hi[j] if x[k, j] > hi[j] else lo[j]
            if first is None or k < first[0]:
                first = (int(k), int(j), kind, float(x[k, j]), float(limit), unit if robot.joints[j].revolute else unit.replace("rad", "m").replace("N*m", "N"))
    if first is not None:
        k, j, kind, value, limit, unit = first
        raise TrajectoryLimitError(j, kind, value, limit, float(t[k]), unit)
    with np.errstate(divide="ignore", invalid="ignore"):
        return {"velocity": (np.abs(qd).max(0) / limits.velocity).tolist(), "acceleration": (np.abs(qdd).max(0) / limits.acceleration).tolist(),
                "torque": (np.abs(tau).max(0) / limits.torque).tolist()}

"""Least squares for ``tau = M phi`` (eq. 18): ordinary and weighted, with standard deviations.

Weighted least squares whitens each joint's equations by that joint's noise level,
estimated from the ordinary fit (Gautier and Poignet's per-joint weighting): joints differ
in torque scale and sensor noise by orders of magnitude, and an unweighted fit lets the
large ones drown the small. Standard deviations come from
``cov = s^2 (W^T W)^{-1}`` of the (whitened) problem. Both fits, the residuals and the
covariance come from one QR pass over the data, per joint (:class:`JointFactors`).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_triangular
from scipy.linalg.lapack import dgeqrf, dgeqrf_lwork

from .errors import IdentificationError
from .spatial import Array

WEIGHTINGS = ("ols", "wls")


@dataclass(frozen=True)
class LeastSquares:
    """Estimate ``beta`` (p,), its covariance (p, p), std (p,), per-joint noise sigma (N,)."""

    beta: Array
    covariance: Array
    std: Array
    joint_sigma: Array
    weighting: str

    @property
    def relative_std(self) -> Array:
        """Std in percent of the value (infinite where the value is 0)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return 100.0 * self.std / np.abs(self.beta)


@dataclass(frozen=True)
class JointFactors:
    """Per joint ``j``, the R factor of ``[W_j | y_j]`` (its rows of the regressor, its torques).

    Everything least squares needs is in these small triangles: the fit of any per-joint
    weighting, each joint's residual, the covariance and the excitation. One pass over the
    data makes them; no tall matrix is copied, weighted or factored again.
    """

    r: list[Array]
    counts: Array

    @property
    def n_parameters(self) -> int:
        return self.r[0].shape[1] - 1

    def combined(self, weights: Array | None = None) -> Array:
        """The (p+1, p+1) R factor of the whole (row-weighted) augmented system."""
        weights = np.ones(len(self.r)) if weights is None else weights
        stacked = np.vstack([wt * r for wt, r in zip(weights, self.r)])
        return _r_factor(stacked)

    def select(self, columns: Array) -> JointFactors:
        """The factors of ``[W_j[:, columns] | y_j]``: a column subset of ``W = QR`` is ``Q R[:, columns]``."""
        keep = np.append(np.asarray(columns), self.n_parameters)
        return JointFactors([_r_factor(r[:, keep]) for r in self.r], self.counts)

    def residual_squares(self, beta: Array) -> Array:
        """``|y_j - W_j beta|^2`` per joint, from the triangles alone."""
        x = np.append(beta, -1.0)
        return np.array([float(np.sum((r @ x) ** 2)) for r in self.r])


def _r_factor(a: Array) -> Array:
    """Upper-triangular R of ``a = QR`` (LAPACK geqrf; Q is never formed)."""
    m, p = a.shape
    lwork = int(dgeqrf_lwork(m, p)[0])
    qr_raw, _, _, info = dgeqrf(np.asfortranarray(a), lwork=max(lwork, 1), overwrite_a=True)
    if info != 0:
        raise IdentificationError(f"QR factorisation failed (LAPACK info {info})")
    r = np.triu(qr_raw[: min(m, p)])
    return r if m >= p else np.vstack([r, np.zeros((p - m, p))])


class ColumnTrials:
    """One joint's ``[W | y]`` (equations x columns) tried with a few of its columns replaced,
    many times over (a nonlinear setting's search): the other columns are factored once,
    ``F = Q R``, and each try only projects its own columns on ``Q``. The rows returned have
    the same Gram matrix as the replaced system (``F^T F = R^T R``, ``F^T Z = R^T Q^T Z``,
    ``Z^T Z = (Q^T Z)^T Q^T Z + E^T E`` with ``E = Z - Q Q^T Z``), so every least-squares figure
    of a stack with them is exact; a try costs a projection instead of a QR of the whole."""

    def __init__(self, rows: Array, changed: list[int]) -> None:
        self.n_columns = rows.shape[1]
        self.changed = list(changed) + [self.n_columns - 1]  # the measured torque goes with them
        self.fixed = [c for c in range(self.n_columns) if c not in self.changed]
        self.q, self.r = np.linalg.qr(rows[:, self.fixed])
        self.y = rows[:, -1]

    def rows(self, columns: Array) -> Array:
        """Rows equivalent to the system with ``changed`` set to ``columns`` (equations x k)."""
        z = np.column_stack([columns, self.y])
        along = self.q.T @ z
        f, k = self.r.shape[0], z.shape[1]
        out = np.zeros((f + k, self.n_columns))
        out[np.ix_(range(f), self.fixed)] = self.r
        out[np.ix_(range(f), self.changed)] = along
        out[np.ix_(range(f, f + k), self.changed)] = _r_factor(z - self.q @ along)[:k]
        return out


def joint_factors(w: Array, y: Array, joint_of_row: Array, n_joints: int) -> JointFactors:
    """Factor each joint's rows of ``[w | y]`` (see :class:`JointFactors`)."""
    columns = []
    for j in range(n_joints):
        idx = np.flatnonzero(joint_of_row == j)
        columns.append(np.vstack([w[idx].T, y[idx][None]]))
    return factor_columns(columns)


def factor_columns(columns: Array | Iterable[Array]) -> JointFactors:
    """:class:`JointFactors` from each joint's ``[W_j | y_j]`` stored column by column.

    ``columns[j]`` is (p+1, n_j) in C order, i.e. the Fortran-ordered matrix LAPACK factors
    in place; it is overwritten.
    """
    factors, counts = [], []
    for j, cols in enumerate(columns):
        if not np.isfinite(cols).all():
            bad = int(np.flatnonzero(~np.isfinite(cols).all(axis=0))[0])
            raise IdentificationError(f"joint {j + 1}, sample {bad}: the regressor or the torque is NaN or infinite")
        factors.append(_r_factor(cols.T))
        counts.append(cols.shape[1])
    return JointFactors(factors, np.array(counts, dtype=float))


def _solve(r_aug: Array) -> tuple[Array, Array]:
    """``beta`` and ``(W^T W)^{-1}`` from the R factor of ``[W | y]``."""
    p = r_aug.shape[1] - 1
    r = r_aug[:p, :p]
    diag = np.abs(np.diag(r))
    if diag.size and diag.min() <= 1e-13 * diag.max():
        raise IdentificationError("the regressor is rank deficient: some base parameter is not excited by the data")
    beta = solve_triangular(r, r_aug[:p, p])
    rinv = solve_triangular(r, np.eye(p))
    return beta, rinv @ rinv.T


def least_squares(w: Array, y: Array, joint_of_row: Array, n_joints: int, weighting: str = "wls") -> LeastSquares:
    """Solve ``w beta ~ y``; ``joint_of_row`` (rows,) tells which joint each equation is."""
    return solve_factors(joint_factors(w, y, joint_of_row, n_joints), weighting)


def solve_factors(factors: JointFactors, weighting: str = "wls") -> LeastSquares:
    """Ordinary or per-joint weighted least squares from :func:`joint_factors`."""
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {weighting!r}")
    p = factors.n_parameters
    counts = factors.counts
    rows = float(counts.sum())
    if rows <= p:
        raise IdentificationError(f"{int(rows)} equations for {p} base parameters: record more samples")
    beta, unscaled = _solve(factors.combined())
    sq = factors.residual_squares(beta)
    dof = np.maximum(counts - p * counts / rows, 1.0)
    sigma = np.sqrt(sq / dof)
    s2 = float(sq.sum()) / (rows - p)
    if weighting == "wls":
        floor = max(float(sigma.max()) * 1e-6, 1e-300)
        weights = 1.0 / np.maximum(sigma, floor)
        beta, unscaled = _solve(factors.combined(weights))
        sq = factors.residual_squares(beta)
        s2 = float(np.sum(sq * weights**2)) / (rows - p)
        sigma = np.sqrt(sq / dof)
    cov = s2 * unscaled
    return LeastSquares(beta, cov, np.sqrt(np.maximum(np.diag(cov), 0.0)), sigma, weighting)


def with_prior(factors: JointFactors, est: LeastSquares, mean: Array, precision: Array, correlation: int) -> tuple[LeastSquares, Array]:
    """The maximum a posteriori estimate with a Gaussian prior ``N(mean, precision^-1)`` on
    ``beta`` (identify.prior), the data weighed as ``n / correlation`` independent equations
    of ``est``'s weighting; and the penalty matrix it adds to ``R^T R`` of that weighting.
    The covariance is the posterior's."""
    weights = 1.0 / np.maximum(est.joint_sigma, 1e-300) if est.weighting == "wls" else np.ones(len(factors.r))
    r = factors.combined(weights)
    rr, z = r[:-1, :-1], r[:-1, -1]
    p = rr.shape[1]
    rows = float(factors.counts.sum())
    s2 = float(np.sum(factors.residual_squares(est.beta) * weights**2)) / max(rows - p, 1.0)
    penalty = max(s2, 1e-300) * max(int(correlation), 1) * np.asarray(precision, float)
    a = rr.T @ rr + penalty
    beta = np.linalg.solve(a, rr.T @ z + penalty @ mean)
    cov = max(s2, 1e-300) * max(int(correlation), 1) * np.linalg.inv(a)
    cov = 0.5 * (cov + cov.T)
    return LeastSquares(beta, cov, np.sqrt(np.maximum(np.diag(cov), 0.0)), est.joint_sigma, est.weighting), penalty


def correlation_length(residual: Array, threshold: float = 0.05) -> int:
    """Samples until the residual's autocorrelation (averaged over columns) first falls
    below ``threshold``: how far apart two samples must be to count as independent."""
    r = np.asarray(residual, float)
    r = r[:, None] if r.ndim == 1 else r
    n = r.shape[0]
    if n < 4:
        return 1
    r = r - r.mean(axis=0)
    spec = np.fft.rfft(r, 2 * n, axis=0)
    acf = np.fft.irfft(np.abs(spec) ** 2, axis=0)[:n].sum(axis=1)
    if acf[0] <= 0:
        return 1
    below = np.flatnonzero(acf / acf[0] < threshold)
    return int(below[0]) if below.size else n


def batch_means_covariance(bread: Array, scores: Array, block: int) -> Array:
    """Sandwich covariance ``B (sum_b U_b U_b^T) B`` with ``U_b`` the sum of the per-sample
    scores ``a_t r_t`` (n, p) over consecutive blocks of ``block`` samples.

    The white-noise formula ``s^2 (W^T W)^{-1}`` assumes independent equations; filtered
    and differentiated signals at 2 ms are correlated over tens of samples, which makes
    that formula several times too optimistic. Summing scores over blocks longer than the
    correlation length gives a covariance that holds for correlated (and heteroscedastic)
    residuals, and includes what model error the residual carries (batch means; Newey and
    West 1987 with a flat kernel).
    """
    n, p = scores.shape
    block = max(1, min(int(block), n))
    m = n // block
    head = scores[: m * block].reshape(m, block, p).sum(axis=1)
    tail = scores[m * block :].sum(axis=0, keepdims=True)
    sums = np.vstack([head, tail]) if n % block else head
    meat = sums.T @ sums
    return bread @ meat @ bread.T


def effective_batches(scores: Array, block: int) -> float:
    """How many independent batches the batch-means meat is worth: ``p^2 / sum_b h_b^2`` with
    ``h_b = U_b^T (sum U U^T)^-1 U_b`` each batch's share of it (``sum_b h_b = p``). Equal shares
    give the batch count; a few batches that carry a direction alone give fewer (Kish's effective
    sample size of the meat). A joint test with this covariance is Hotelling's with that many."""
    n, p = scores.shape
    block = max(1, min(int(block), n))
    m = n // block
    sums = scores[: m * block].reshape(m, block, p).sum(axis=1)
    if n % block:
        sums = np.vstack([sums, scores[m * block :].sum(axis=0, keepdims=True)])
    meat = sums.T @ sums
    h = np.einsum("bi,bi->b", sums @ np.linalg.pinv(meat), sums)
    return float(np.sum(h)) ** 2 / max(float(np.sum(h**2)), 1e-300)


def lag_window_covariance(bread: Array, regressor: Array, residual: Array, lag: int) -> Array:
    """Sandwich covariance of ordinary least squares ``regressor @ beta ~ y`` (``bread`` is
    ``(A^T A)^{-1}``) for residuals correlated over at most ``lag`` samples: the meat sums
    ``s_u s_t^T`` (scores ``s_t = a_t r_t``) over every pair within ``lag`` of each other (a flat
    lag window: no pair inside the correlation is cut off, as a block boundary cuts it), and
    adds back what the fit took out of the residuals.

    Residuals are the noise projected, ``r = (I - H) e`` (``H = A bread A^T``), so a meat of
    residual products has expectation ``A^T K o [(I - H) Omega (I - H)] A`` (``K`` the window,
    ``Omega`` the noise covariance), short of ``A^T Omega A`` by ``A^T K o (H Omega + Omega H -
    H Omega H) A``; with smooth regressors ``H`` is nearly constant over the window and this is
    about ``p (2 lag + 1) / n`` of the whole, not the ``p / n`` that ``n / (n - p)`` restores.
    That shortfall is added back with ``Omega`` estimated by the window's residual products
    (first order in ``H``). Batch means of ``block`` samples (:func:`batch_means_covariance`)
    lose both the projection (about ``p block / n``) and the pairs across block boundaries
    (``1 / (2 block)`` of the variance of a moving average of two samples, as re-timed held
    torques are): 10 % of the variance at ``block = 8`` on the simulated PUMA's single-link
    steps."""
    a = np.asarray(regressor, float)
    r = np.asarray(residual, float)
    n, p = a.shape
    lag = max(0, min(int(lag), n - 1))
    idx = np.arange(n)
    hi, lo = np.minimum(idx + lag + 1, n), np.maximum(idx - lag, 0)

    def window_sum(x: Array) -> Array:  # sum of x_u over |u - t| <= lag, for every t
        c = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0)])
        return c[hi] - c[lo]

    s = a * r[:, None]
    c = window_sum(s)
    raw = s.T @ c
    raw = 0.5 * (raw + raw.T)
    g = np.asarray(bread, float)
    gram = window_sum(a[:, :, None] * a[:, None, :])  # sum of a_u a_u^T over the window
    h_omega = np.einsum("tij,jk,tk,tl->il", gram, g, c, s, optimize=True)  # A^T K o (H Omega) A
    h_omega_h = np.einsum("tij,jk,tk,tl->il", gram, g @ raw @ g, a, a, optimize=True)
    meat = raw + h_omega + h_omega.T - h_omega_h
    w, v = np.linalg.eigh(0.5 * (meat + meat.T))
    if w.min() < -1e-9 * max(float(np.abs(w).max()), 1e-300):
        meat = bartlett_meat(s, lag)  # residual correlations that sum below zero within the window
    else:
        meat = (v * np.maximum(w, 0.0)) @ v.T
    return bread @ meat @ bread.T


def bartlett_meat(scores: Array, lag: int) -> Array:
    """``sum_k (1 - |k| / (lag + 1)) sum_t s_t s_{t+k}^T`` over ``|k| <= lag`` (Newey and West
    1987), positive semi-definite by construction: the outer products of the scores summed
    over every window of ``lag + 1`` samples, divided by ``lag + 1``.

    A flat window is indefinite when the residual's correlations within it sum below zero, as
    a twice-differentiated quantised position makes them (-0.3 and -0.6 at lags 1 and 2 on the
    simulated KUKA, whose torques are nearly noise-free): clipped, its meat was zero and every
    standard deviation of the step with it."""
    s = np.asarray(scores, float)
    lag = max(0, int(lag))
    padded = np.concatenate([np.zeros((lag + 1, s.shape[1])), s, np.zeros((lag, s.shape[1]))])
    c = np.cumsum(padded, axis=0)
    windows = c[lag + 1 :] - c[: -(lag + 1)]
    return np.asarray(windows.T @ windows / (lag + 1))


def bounded_quadratic(h: Array, g: Array, lower: Array) -> Array:
    """``argmin x^T H x - 2 g^T x`` subject to ``x >= lower`` (``-inf``: free), ``H`` symmetric
    positive (semi)definite: least squares with bounds, its normal equations given.

    The unbounded solution when it is admissible (one solve); otherwise bounded least squares
    (``scipy.optimize.lsq_linear``, trust-region reflective) on ``A x ~ b`` with
    ``A = diag(sqrt w) V^T``, ``b = diag(1/sqrt w) V^T g`` (``H = V diag(w) V^T``), whose
    residual is the quadratic up to a constant. Friction is dissipative and an inertia
    positive: bounding them in the fit, not after it, lets the other parameters take up
    what the bounded ones cannot (issue 33)."""
    from scipy.optimize import lsq_linear

    h = 0.5 * (np.asarray(h, float) + np.asarray(h, float).T)
    g, lower = np.asarray(g, float), np.asarray(lower, float)
    try:
        x = np.linalg.solve(h, g)
    except np.linalg.LinAlgError:
        x = np.linalg.lstsq(h, g, rcond=None)[0]
    if np.all(x >= lower):
        return x
    exact = _by_active_sets(h, g, lower)
    if exact is not None:
        return exact
    w, v = np.linalg.eigh(h)
    keep = w > 1e-12 * max(float(w.max()), 1e-300)
    a = np.sqrt(w[keep])[:, None] * v[:, keep].T
    b = (v[:, keep].T @ g) / np.sqrt(w[keep])
    upper = np.full_like(lower, np.inf)
    start = np.where(np.isfinite(lower), np.maximum(x, lower), x)
    res = lsq_linear(a, b, bounds=(lower, upper), method="trf", tol=1e-12, lsmr_tol="auto", max_iter=500)
    out = np.asarray(res.x, float)
    # exactly on the bound where the solver stopped within its tolerance of it
    near = np.isfinite(lower) & (out - lower <= 1e-9 * max(1.0, float(np.max(np.abs(start)))))
    out[near] = lower[near]
    return _on_the_bounds(h, g, lower, out)


ENUMERATED_BOUNDS = 4
"""Up to this many bounded parameters, :func:`bounded_quadratic` tries every set of them held
at their bounds (at most 16 small solves) before an iterative solver: a diagnosis bounds
hundreds of candidates of one to three parameters, and ``lsq_linear`` took a fifth of it."""


def _by_active_sets(h: Array, g: Array, lower: Array) -> Array | None:
    """The exact bounded minimum by enumeration (fewest parameters held first): the first set
    held at its bounds whose solution is admissible and meets the KKT conditions
    (:func:`_held_at`) is the minimum of a strictly convex quadratic. None when more than
    ``ENUMERATED_BOUNDS`` parameters are bounded or none passes (``H`` singular)."""
    bounded = np.flatnonzero(np.isfinite(lower))
    if bounded.size > ENUMERATED_BOUNDS:
        return None
    for size in range(1, bounded.size + 1):
        for held_idx in itertools.combinations(bounded, size):
            held = np.zeros(lower.size, bool)
            held[list(held_idx)] = True
            x = _held_at(h, g, lower, held)
            if x is not None:
                return x
    return None


def _held_at(h: Array, g: Array, lower: Array, held: Array) -> Array | None:
    """The minimum with the parameters ``held`` at their bounds and the others solved for,
    when it is admissible and optimal (each held parameter's gradient pushes it against its
    bound: the KKT conditions); None otherwise, or when the free block is singular."""
    free = ~held
    x = np.where(held, lower, 0.0)
    if free.any():
        try:
            x[free] = np.linalg.solve(h[np.ix_(free, free)], g[free] - h[np.ix_(free, held)] @ x[held])
        except np.linalg.LinAlgError:
            return None
    pushes = (h @ x - g)[held]  # half the gradient: >= 0 where the bound holds the parameter back
    tol = 1e-9 * max(1.0, float(np.max(np.abs(h @ x))), float(np.max(np.abs(g))))
    return x if np.all(x[free] >= lower[free]) and np.all(pushes >= -tol) else None


def _on_the_bounds(h: Array, g: Array, lower: Array, x: Array) -> Array:
    """``x`` (an iterative solver's answer) made exact where it can be: the parameters it left
    at or near their bounds held there, the others solved for (:func:`_held_at`); kept when
    that answer is admissible and optimal, so a friction the data do not support is 0, not
    1e-6 of its scale."""
    scale = max(1.0, float(np.max(np.abs(x))))
    held = np.isfinite(lower) & (x - lower <= 1e-5 * scale)
    if not held.any():
        return x
    exact = _held_at(h, g, lower, held)
    return x if exact is None else exact

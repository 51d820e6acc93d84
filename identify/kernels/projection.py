"""The compiled barrier method of :func:`identify.payload_projection.project_feasible`.

One projection is a sequence of Newton steps on 10 unknowns and a 4x4 pseudo-inertia: in
numpy each step is dozens of calls on tiny arrays, 2.8 ms a projection, which made the
projection over 40 % of the live payload estimator's work and left it behind the stream on a
loaded 2-core machine (issue 31). Compiled, a projection takes 0.35 ms with its set-up in
numpy. The compilation (8 s on a quiet 2-core machine, cached by numba after the first run) is
paid in :meth:`~identify.payload.PayloadRLS.warm`, before a service says it is alive.

The 4x4 and 10x10 factorisations are written out (a Cholesky factor with a flag, not an
exception): a trial point outside the cone is an ordinary outcome of the line search.
"""

from __future__ import annotations

import numba
import numpy as np

_njit = numba.njit(cache=True, error_model="numpy", boundscheck=False)


@_njit
def _cholesky(a: np.ndarray, out: np.ndarray) -> bool:
    """Lower Cholesky factor of the symmetric ``a`` into ``out``; False unless positive definite."""
    n = a.shape[0]
    for j in range(n):
        s = a[j, j]
        for k in range(j):
            s -= out[j, k] * out[j, k]
        if not s > 0.0:
            return False
        d = np.sqrt(s)
        out[j, j] = d
        for i in range(j + 1, n):
            s = a[i, j]
            for k in range(j):
                s -= out[i, k] * out[j, k]
            out[i, j] = s / d
        for i in range(j):
            out[i, j] = 0.0
    return True


@_njit
def _lower_inverse(c: np.ndarray) -> np.ndarray:
    """The inverse of a lower-triangular matrix with a positive diagonal."""
    n = c.shape[0]
    inv = np.zeros((n, n))
    for j in range(n):
        inv[j, j] = 1.0 / c[j, j]
        for i in range(j + 1, n):
            s = 0.0
            for k in range(j, i):
                s -= c[i, k] * inv[k, j]
            inv[i, j] = s / c[i, i]
    return inv


@_njit
def _sandwich(ci: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``ci a ci^T`` for 4x4 matrices (written out: no BLAS call to bind and compile)."""
    n4 = ci.shape[0]
    t = np.zeros((4, 4))
    for i in range(n4):
        for j in range(n4):
            s = 0.0
            for k in range(n4):
                s += ci[i, k] * a[k, j]
            t[i, j] = s
    out = np.zeros((4, 4))
    for i in range(n4):
        for j in range(n4):
            s = 0.0
            for k in range(n4):
                s += t[i, k] * ci[j, k]
            out[i, j] = s
    return out


@_njit
def _least_eigenvalue(a: np.ndarray) -> float:
    """The least eigenvalue of a symmetric 4x4 matrix by cyclic Jacobi rotations (to rounding)."""
    n4 = a.shape[0]
    m = a.copy()
    for _ in range(50):
        off = 0.0
        for i in range(n4):
            for j in range(i + 1, n4):
                off += m[i, j] * m[i, j]
        if off <= 1e-30 * (m[0, 0] ** 2 + m[1, 1] ** 2 + m[2, 2] ** 2 + m[3, 3] ** 2) or off == 0.0:
            break
        for p in range(n4):
            for q in range(p + 1, n4):
                if m[p, q] == 0.0:
                    continue
                theta = (m[q, q] - m[p, p]) / (2.0 * m[p, q])
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
                c = 1.0 / np.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n4):  # columns p, q
                    mkp, mkq = m[k, p], m[k, q]
                    m[k, p], m[k, q] = c * mkp - s * mkq, s * mkp + c * mkq
                for k in range(n4):  # rows p, q
                    mpk, mqk = m[p, k], m[q, k]
                    m[p, k], m[q, k] = c * mpk - s * mqk, s * mpk + c * mqk
    return min(min(m[0, 0], m[1, 1]), min(m[2, 2], m[3, 3]))


@_njit
def _pseudo(x: np.ndarray, basis: np.ndarray) -> np.ndarray:
    n10 = basis.shape[0]
    j = np.zeros((4, 4))
    for k in range(n10):
        for r in range(4):
            for c in range(4):
                j[r, c] += x[k] * basis[k, r, c]
    return j


@_njit
def _barrier(mu: float, fx: float, chol: np.ndarray) -> float:
    """The barrier function ``f - mu log det J`` from ``J``'s Cholesky factor."""
    n4 = chol.shape[0]
    s = 0.0
    for i in range(n4):
        s += np.log(chol[i, i])
    return fx - 2.0 * mu * s


@_njit
def _distance(x: np.ndarray, theta: np.ndarray, weight: np.ndarray) -> float:
    """``(x - theta)^T W (x - theta) / 2``."""
    n10 = x.shape[0]
    s = 0.0
    for i in range(n10):
        ei = x[i] - theta[i]
        for j in range(n10):
            s += ei * weight[i, j] * (x[j] - theta[j])
    return 0.5 * s


@_njit
def _newton_step(x: np.ndarray, theta: np.ndarray, weight: np.ndarray, d: np.ndarray, mu: float, ci: np.ndarray,
                 basis: np.ndarray, step: np.ndarray) -> float:
    """The preconditioned Newton step of the barrier problem into ``step``; its decrement
    (NaN when the Newton system is not positive definite)."""
    n4, n10 = ci.shape[0], x.shape[0]
    jinv = np.zeros((4, 4))  # J^-1 = ci^T ci
    for i in range(n4):
        for j in range(n4):
            s = 0.0
            for k in range(n4):
                s += ci[k, i] * ci[k, j]
            jinv[i, j] = s
    b = np.zeros((10, 4, 4))  # J^-1 A_k
    for k in range(n10):
        for i in range(n4):
            for j in range(n4):
                s = 0.0
                for m in range(n4):
                    s += jinv[i, m] * basis[k, m, j]
                b[k, i, j] = s
    grad = np.zeros(10)
    for i in range(n10):
        s = 0.0
        for j in range(n10):
            s += weight[i, j] * (x[j] - theta[j])
        grad[i] = s
    hess = weight.copy()
    for k in range(n10):
        grad[k] -= mu * (b[k, 0, 0] + b[k, 1, 1] + b[k, 2, 2] + b[k, 3, 3])
        for m in range(k + 1):
            s = 0.0
            for i in range(n4):
                for j in range(n4):
                    s += b[k, i, j] * b[m, j, i]
            hess[k, m] += mu * s
            if m != k:
                hess[m, k] += mu * s
    a = np.empty((10, 10))
    for k in range(n10):
        for m in range(n10):
            a[k, m] = hess[k, m] * d[k] * d[m]
    c = np.zeros((10, 10))
    if not _cholesky(a, c):
        return np.nan
    rhs = d * grad
    y = np.empty(10)
    for i in range(n10):  # c y = rhs, c^T z = y
        s = rhs[i]
        for k in range(i):
            s -= c[i, k] * y[k]
        y[i] = s / c[i, i]
    for i in range(n10 - 1, -1, -1):
        s = y[i]
        for k in range(i + 1, n10):
            s -= c[k, i] * step[k]
        step[i] = s / c[i, i]
    decrement = 0.0
    for i in range(n10):
        step[i] *= -d[i]
        decrement -= grad[i] * step[i]
    return decrement


@_njit
def project_one(theta: np.ndarray, weight: np.ndarray, x: np.ndarray, basis: np.ndarray, gap: float, atol: float,
                max_steps: int) -> np.ndarray:
    """Newton steps on ``f(x) - mu log det J(x)`` from the strictly feasible ``x``, ``mu``
    divided by 50 until the duality gap ``4 mu`` is below ``gap`` of ``f`` or below ``atol``;
    each step the longest that stays inside the cone, then backtracking (Armijo). ``x`` is
    overwritten with the answer, which is returned."""
    n10 = x.shape[0]
    d = np.empty(10)  # diagonal preconditioner
    for i in range(n10):
        d[i] = 1.0 / np.sqrt(max(weight[i, i], 1e-300))
    fx = _distance(x, theta, weight)
    mu = max(fx, 1e-300) / 4.0
    chol = np.zeros((4, 4))
    chol_t = np.zeros((4, 4))
    if not _cholesky(_pseudo(x, basis), chol):
        return x
    step = np.empty(10)
    trial = np.empty(10)
    steps = 0
    for _ in range(40):
        for _ in range(30):
            steps += 1
            if steps > max_steps:
                return x
            ci = _lower_inverse(chol)
            decrement = _newton_step(x, theta, weight, d, mu, ci, basis, step)
            if not np.isfinite(decrement):
                return x  # feasible, if not the last word
            if decrement <= max(1e-10 * (fx + mu), 0.5 * atol):
                break
            lam = _least_eigenvalue(_sandwich(ci, _pseudo(step, basis)))
            t = 1.0 if lam >= -1.0 else min(1.0, -0.99 / lam)
            phi0 = _barrier(mu, fx, chol)
            accepted, f_t = False, fx
            while t > 1e-12:
                for i in range(n10):
                    trial[i] = x[i] + t * step[i]
                if _cholesky(_pseudo(trial, basis), chol_t):
                    f_t = _distance(trial, theta, weight)
                    if _barrier(mu, f_t, chol_t) <= phi0 - 0.25 * t * decrement:
                        accepted = True
                        break
                t *= 0.5
            if not accepted:
                break  # no progress at this mu: as good as it gets
            fx = f_t
            for i in range(n10):
                x[i] = trial[i]
            for r in range(4):
                for c in range(4):
                    chol[r, c] = chol_t[r, c]
        if 4.0 * mu <= max(max(gap * fx, atol), 1e-300):
            break
        mu /= 50.0
    return x

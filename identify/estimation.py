"""Least squares for ``tau = M phi`` (eq. 18): ordinary and weighted, with standard deviations.

Weighted least squares whitens each joint's equations by that joint's noise level,
estimated from the ordinary fit (Gautier and Poignet's per-joint weighting): joints differ
in torque scale and sensor noise by orders of magnitude, and an unweighted fit lets the
large ones drown the small. Standard deviations come from
``cov = s^2 (W^T W)^{-1}`` of the (whitened) problem.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import qr, solve_triangular

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


def _qr_solve(w: Array, y: Array) -> tuple[Array, Array, Array]:
    """``beta``, residual and ``(W^T W)^{-1}`` from the R factor of a QR of ``w``.

    Only R is formed (no Q: the tall factor costs more than the fit); ``beta`` comes from
    the corrected semi-normal equations ``R^T R beta = W^T y`` with one step of refinement
    (Bjorck), as accurate as a full QR solve for these well-posed problems.
    """
    r = qr(w, mode="r", check_finite=False)[0][: w.shape[1]]
    diag = np.abs(np.diag(r))
    if diag.size and diag.min() <= 1e-13 * diag.max():
        raise IdentificationError("the regressor is rank deficient: some base parameter is not excited by the data")

    def normal_solve(rhs: Array) -> Array:
        return solve_triangular(r, solve_triangular(r, rhs, trans="T"))

    beta = normal_solve(w.T @ y)
    res = y - w @ beta
    beta = beta + normal_solve(w.T @ res)
    rinv = solve_triangular(r, np.eye(r.shape[0]))
    return beta, y - w @ beta, rinv @ rinv.T


def least_squares(w: Array, y: Array, joint_of_row: Array, n_joints: int, weighting: str = "wls") -> LeastSquares:
    """Solve ``w beta ~ y``; ``joint_of_row`` (rows,) tells which joint each equation is."""
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {weighting!r}")
    rows, p = w.shape
    if rows <= p:
        raise IdentificationError(f"{rows} equations for {p} base parameters: record more samples")
    beta, res, unscaled = _qr_solve(w, y)
    counts = np.bincount(joint_of_row, minlength=n_joints).astype(float)
    sq = np.bincount(joint_of_row, weights=res**2, minlength=n_joints)
    dof = np.maximum(counts - p * counts / rows, 1.0)
    sigma = np.sqrt(sq / dof)
    if weighting == "wls":
        floor = max(float(sigma.max()) * 1e-6, 1e-300)
        weights = 1.0 / np.maximum(sigma, floor)
        wr = weights[joint_of_row]
        beta, res_w, unscaled = _qr_solve(w * wr[:, None], y * wr)
        s2 = float(res_w @ res_w) / (rows - p)
        res = res_w / wr
        sq = np.bincount(joint_of_row, weights=res**2, minlength=n_joints)
        sigma = np.sqrt(sq / dof)
    else:
        s2 = float(res @ res) / (rows - p)
    cov = s2 * unscaled
    return LeastSquares(beta, cov, np.sqrt(np.maximum(np.diag(cov), 0.0)), sigma, weighting)

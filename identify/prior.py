"""The modeled values as a prior: what a trajectory leaves unexcited stays near the model.

Least squares (eq. 18) fixes every base parameter from the data alone. Where a trajectory
barely excites a direction of the parameter space, the estimate along it is noise, and a
prediction on another trajectory (other poses, other speeds) pays for it: on the KUKA
LWR4+ recordings, identified on one trajectory and validated on another, that is most of
the held-out error. The maximum a posteriori estimate with the robot file's modeled values
as a Gaussian prior keeps the data's answer wherever the data speak and the model's where
they do not (Bayesian identification; the same role the entropic term plays in
``identify.feasible``)::

    min_beta  sum_j |W_j beta - tau_j|^2 / (sigma_j^2 L)  +  (beta - beta_0)^T Lambda (beta - beta_0)

- ``sigma_j``: each joint's noise level (the weighting of least squares), and ``L`` the
  whitened residual's correlation length in equations: filtered samples are not
  independent, and counting each as one observation would make the data look ``L`` times
  surer than they are, and the prior vanish.
- ``beta_0 = P phi_0`` and ``Lambda = (P S P^T)^{-1}``: the prior on the standard parameters
  ``phi`` carried to the base parameters (5.4; a Gaussian's marginal), over the base
  parameters all of whose terms have a prior.
- ``S``, diagonal: each modeled parameter trusted to within its own size (a CAD value that
  is off by 100 % is still inside one sigma), and never tighter than the link's own scale:
  its mass, mass times its radius of gyration ``l`` for a first moment, mass times ``l^2``
  for an inertia. An effect's parameters (friction, offset, rotor inertia) have mean zero
  and a standard deviation that lets the effect alone carry the joint's whole torque.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .identifiability import BaseParameters
from .spatial import Array

RELATIVE_STD = 1.0
"""The modeled values' standard deviation, as a fraction of their own size."""

SMALL_LINK = 0.05
"""A link modeled (almost) massless gets this fraction of the heaviest link's scale."""


@dataclass(frozen=True)
class Prior:
    """Gaussian prior on the base parameters: mean ``mean`` (p,), precision ``precision`` (p, p)."""

    mean: Array
    precision: Array
    covered: int  # base parameters the prior speaks about
    widening: float = 1.0  # the factor its covariance was widened by to agree with the data (:func:`widened`)

    def to_json(self, correlation: int) -> dict[str, Any]:
        return {
            "kind": "Gaussian, the robot file's modeled values as mean (maximum a posteriori estimate)",
            "relative_std": RELATIVE_STD,
            "widened_by": self.widening if np.isfinite(self.widening) else None,
            "used": self.covered > 0,
            "base_parameters_with_prior": self.covered,
            "base_parameters": int(self.mean.size),
            "correlation_length_equations": int(correlation),
            "why": "keeps the modeled values along what the trajectory does not excite; "
                   f"each modeled parameter trusted to within {100 * RELATIVE_STD:g} % of itself, "
                   "effects to within the joint's whole torque; the data weigh as n/L independent equations",
        }


def link_scales(phi_links: Array) -> Array:
    """(10 N,) standard deviations of the modeled link parameters (Khosla's order, about
    the link frame); ``inf`` for a link without modeled values."""
    n = phi_links.size // 10
    links = phi_links.reshape(n, 10)
    known = np.isfinite(links).all(axis=1)
    mass = np.where(known, np.abs(links[:, 0]), 0.0)
    trace = np.where(known, np.abs(links[:, 4]) + np.abs(links[:, 7]) + np.abs(links[:, 9]), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        gyration = np.where(mass > 0, np.sqrt(trace / np.where(mass > 0, mass, 1.0)), 0.0)
    heavy = float(mass.max()) if known.any() else 0.0
    far = float(gyration.max()) if known.any() else 0.0
    m_ref = np.maximum(mass, SMALL_LINK * heavy)
    l_ref = np.maximum(gyration, SMALL_LINK * far)
    floor = np.column_stack([m_ref, *(3 * [m_ref * l_ref]), *(6 * [m_ref * l_ref**2])])
    std = np.maximum(RELATIVE_STD * np.abs(np.nan_to_num(links)), floor)
    std[~known] = np.inf
    std[known & (floor.max(axis=1) <= 0)] = np.inf  # nothing modeled there at all
    return std.reshape(-1)


def base_prior(base: BaseParameters, mean: Array, std: Array) -> Prior | None:
    """The prior ``N(mean, diag(std^2))`` on the standard parameters, on the base
    parameters: ``N(P mean, P S P^T)`` over the base parameters whose every term is finite."""
    p = base.projection()
    finite = np.isfinite(std) & np.isfinite(mean)
    touches = np.abs(p) > 0
    covered = np.flatnonzero(~(touches & ~finite[None, :]).any(axis=1))
    if covered.size == 0:
        return None
    ps = p[np.ix_(covered, np.flatnonzero(finite))]
    s = std[finite]
    cov = (ps * s**2) @ ps.T
    precision = np.zeros((base.n_base, base.n_base))
    precision[np.ix_(covered, covered)] = np.linalg.pinv(cov, rcond=1e-12, hermitian=True)
    beta0 = np.zeros(base.n_base)
    beta0[covered] = ps @ mean[finite]
    return Prior(beta0, precision, int(covered.size))


def widened(prior: Prior, beta: Array, covariance: Array, limit: float = 1e12) -> Prior:
    """The prior with its covariance scaled by the least ``s^2 >= 1`` for which the data's
    estimate ``beta`` (covariance ``covariance``) lies no farther from the prior's mean than
    expected: ``d^T (C + s^2 S_0)^-1 d <= k`` over the ``k`` base parameters it covers (the
    method of moments of empirical Bayes). A model the data contradict (a URDF's placeholder
    inertias) loses its weight instead of pulling the estimate; a model they agree with
    keeps what the robot file says. Beyond ``limit`` the prior is dropped (zero precision)."""
    idx = np.flatnonzero(np.abs(prior.precision).sum(axis=1) > 0)
    if idx.size == 0:
        return prior
    s0 = np.linalg.pinv(prior.precision[np.ix_(idx, idx)], hermitian=True)
    c = np.asarray(covariance, float)[np.ix_(idx, idx)]
    d = (np.asarray(beta, float) - prior.mean)[idx]

    def excess(scale: float) -> float:
        return float(d @ np.linalg.lstsq(c + scale * s0, d, rcond=None)[0]) / idx.size - 1.0

    if excess(1.0) <= 0.0:
        return prior
    if excess(limit) > 0.0:
        return scaled(prior, np.inf)
    lo, hi = 0.0, float(np.log(limit))
    for _ in range(60):  # bisection on log s^2: excess falls as the prior widens
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if excess(float(np.exp(mid))) > 0.0 else (lo, mid)
    return scaled(prior, float(np.exp(hi)))


def scaled(prior: Prior, scale: float) -> Prior:
    """The prior with its covariance scaled by ``scale`` (a widening found on other data);
    ``inf``: no prior at all."""
    if not np.isfinite(scale):
        return Prior(prior.mean, np.zeros_like(prior.precision), 0, np.inf)
    return Prior(prior.mean, prior.precision / scale, prior.covered, float(scale))


__all__ = ["Prior", "RELATIVE_STD", "base_prior", "link_scales", "scaled", "widened"]

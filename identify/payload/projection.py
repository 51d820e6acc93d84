"""Physically possible payloads: the parameters a rigid body can have, and the projection of
an estimate onto them (the published estimate of :class:`~identify.payload.PayloadRLS`).

A body's ``m, m s, I`` exist exactly when its 4x4 pseudo-inertia is positive semidefinite
(Wensing, Kim, Slotine 2017: :func:`pseudo_inertia`). :func:`project_feasible` finds the
nearest such parameters in the metric of the estimate's covariance by a log-barrier interior
point method (compiled: :mod:`identify.kernels.projection`); :func:`project_feasible_many` does it for many.
"""

from __future__ import annotations

import numpy as np

from ..robot import inertia_entries, inertia_matrix
from ..spatial import Array


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


def phi_of_pseudo(j: Array) -> Array:
    sigma = j[:3, :3]
    i3 = np.trace(sigma) * np.eye(3) - sigma
    return np.concatenate([[j[3, 3]], j[:3, 3], inertia_entries(i3)])


_BASIS = np.ascontiguousarray(np.stack([pseudo_inertia(e) for e in np.eye(10)]))  # the linear map phi -> pseudo-inertia, (10, 4, 4)


def project_feasible(theta: Array, cov: Array, gap: float = 1e-5, atol: float = 0.0, max_steps: int = 1200) -> Array:
    """The physically possible parameters nearest ``theta`` in the metric ``cov^-1``.

    Minimizes ``(x - theta)^T cov^-1 (x - theta) / 2`` subject to ``pseudo_inertia(x)``
    positive semidefinite (so mass >= 0 follows) by a log-barrier interior point method
    (:func:`~identify.kernels.projection.project_one`, compiled): Newton steps on
    ``f(x) - mu log det J(x)``, ``mu`` divided by 50 until the duality gap ``4 mu`` is below
    ``gap`` of ``f`` or below ``atol``, and each centring stops once its Newton decrement is
    below ``atol / 2`` (the estimator publishes with ``atol = 1e-3``: half the Newton steps,
    the distance ``f`` within 0.01 of the tight answer's on a replay of the simulated arm,
    and as feasible); at most ``max_steps`` Newton steps in all. Every iterate is strictly
    feasible, so the result is physically possible even when the iterations stop early.
    ``theta`` is returned unchanged when it is feasible already.

    Every projection starts cold, from ``theta``'s pseudo-inertia with its negative
    eigenvalues lifted: the last answer lies on the boundary (the least eigenvalue of its
    pseudo-inertia ~1e-13), where the Newton steps stall; started there, 249 of 328 published
    projections of a live run were worse than the cold start's (2.054 kg against 2.011 kg).
    """
    from ..kernels.projection import project_one

    theta = np.asarray(theta, float)
    w, v = np.linalg.eigh(pseudo_inertia(theta))
    if w.min() >= 0.0:
        return theta.copy()
    scale = max(float(np.abs(w).max()), 1e-12)
    cov = 0.5 * (cov + cov.T)
    weight = np.linalg.inv(cov + 1e-15 * np.trace(cov) * np.eye(10))
    weight = np.ascontiguousarray(0.5 * (weight + weight.T))
    x = phi_of_pseudo((v * np.maximum(w, 1e-3 * scale)) @ v.T)  # strictly feasible start
    return project_one(np.ascontiguousarray(theta), weight, x, _BASIS, float(gap), float(atol), int(max_steps))


def project_feasible_many(thetas: Array, covs: Array, gap: float = 1e-5, atol: float = 0.0) -> Array:
    """:func:`project_feasible` of many estimates (K, 10) with their covariances (K, 10, 10):
    each problem on its own, so an answer does not depend on which others share the batch
    (a replay and the live service publish the same projections)."""
    thetas = np.atleast_2d(np.asarray(thetas, float))
    covs = np.asarray(covs, float).reshape(-1, 10, 10)
    return np.array([project_feasible(t, c, gap=gap, atol=atol) for t, c in zip(thetas, covs)]).reshape(thetas.shape)

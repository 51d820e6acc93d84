"""Physically consistent parameters: the rigid bodies closest to the least-squares estimate.

Least squares (eq. 18) gives base parameters ``beta`` that predict torque well but need not
belong to any set of rigid bodies. Link ``i``'s ten parameters (Khosla eq. 10, about the
link frame) are those of a body with a non-negative mass density exactly when its
pseudo-inertia is positive semidefinite (Wensing, Kim and Slotine 2017):

.. math:: J_i = \\begin{bmatrix} \\tfrac12 \\mathrm{tr}(I_i) E - I_i & h_i \\\\ h_i^T & m_i \\end{bmatrix} \\succeq 0,
          \\qquad h_i = m_i s_i

which holds the triangle inequalities of the inertia about the centre of mass and
``m_i >= 0``. :func:`feasible_fit` solves

.. math:: \\min_\\phi \\; \\| R (P \\phi - \\beta_{LS}) \\|^2
          + \\lambda \\sum_i d(J_i(\\phi) \\,\\|\\, J_{0,i}),
          \\quad J_i \\succ 0, \\; f_v, f_c, I_a \\ge 0

with ``P`` the base projection (``beta = P phi``, 5.4), ``R`` the triangular factor of the
weighted regressor (the data's own metric: the first term is the rise of the whitened
residual sum of squares over the least-squares one) and ``d`` the entropic (log-det,
Bregman) divergence to the modeled pseudo-inertia ``J_0`` (Lee, Wensing and Park 2019):

.. math:: d(J \\| J_0) = \\mathrm{tr}(J_0^{-1} J) - \\log\\det(J_0^{-1} J) - 4 .

Why the entropic regulariser and not a Euclidean one: it has no units to weigh against each
other (kg, kg m, kg m^2: a Euclidean distance needs a weight per parameter, which is a
choice), it is invariant to the frame the link is described in, and it is a barrier:
``J`` stays strictly positive definite, so every mass is strictly positive. It only decides
what the data cannot see; the data term dominates every excited direction.

Optionally (``boxes``: ``armid --bounding-box`` takes them from the URDF's collision
geometry) each link's mass also stays inside an axis-aligned box of its link frame, three
linear constraints on ``J`` (:func:`box_matrices`): the centre of mass inside the box and
the second moments, hence the inertia, bounded by the box's.

Solver: cvxpy with Clarabel (an open interior-point solver for SDP and exponential cones),
both wheels on every platform from the package registry. The problem is convex: one 4x4
PSD cone per link, the log-det terms as exponential cones, a second-order cone for the
data term; about 100 unknowns, solved to its global optimum in about 0.2 s. A
log-Cholesky parametrisation (Rucker and Wensing 2022) with ``scipy.optimize.least_squares``
needs no new package and agreed on the PUMA 560 example (same distance to 4 digits), but
on the KUKA LWR4+ recordings, whose least-squares estimate is far outside the feasible set,
the optimum sits near the cone's boundary and the log-parametrised trust region had not
converged after 20,000 evaluations (2 minutes) while Clarabel takes 18 iterations.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import IdentificationError
from .estimation import JointFactors
from .identifiability import BaseParameters
from .robot import inertia_matrix
from .spatial import Array

SIGNED_EFFECTS = ("viscous_friction", "coulomb_friction", "rotor_inertia", "load_dependent_coulomb")
"""Declared effects whose parameter cannot be negative (dissipation, an inertia)."""


def link_list(links: list[int]) -> str:
    """``link 4`` or ``links 1, 3, 4``: the links a sentence names, in one grammar."""
    return ("link " if len(links) == 1 else "links ") + ", ".join(map(str, links))


PRIOR_FLOOR = 1e-2
"""A modeled pseudo-inertia that is not positive definite is replaced, for the prior only,
by the nearest one with every eigenvalue at least this fraction of its largest."""


# ---------------------------------------------------------------------------------------
# pseudo-inertia <-> Khosla's ten parameters


def pseudo_inertia(phi_link: Array) -> Array:
    """(4, 4) pseudo-inertia of one link's ``m, msx, msy, msz, Ixx, Ixy, Ixz, Iyy, Iyz, Izz``.

    .. math:: J = [[\\tfrac12 \\mathrm{tr}(I) E - I, h], [h^T, m]]
    """
    m, hx, hy, hz, ixx, ixy, ixz, iyy, iyz, izz = np.asarray(phi_link, dtype=float)
    inertia = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    out = np.empty((4, 4))
    out[:3, :3] = 0.5 * np.trace(inertia) * np.eye(3) - inertia
    out[:3, 3] = out[3, :3] = (hx, hy, hz)
    out[3, 3] = m
    return out


def link_from_pseudo_inertia(j: Array) -> Array:
    """Inverse of :func:`pseudo_inertia`: ``I = tr(Sigma) E - Sigma``."""
    sigma = j[:3, :3]
    inertia = np.trace(sigma) * np.eye(3) - sigma
    return np.array([j[3, 3], j[0, 3], j[1, 3], j[2, 3], inertia[0, 0], inertia[0, 1], inertia[0, 2], inertia[1, 1], inertia[1, 2], inertia[2, 2]])


def _pseudo_inertia_map() -> Array:
    """(10, 16) ``G`` with ``phi_link = G vec(J)`` (row-major vec), for the Jacobian."""
    g = np.zeros((10, 16))
    for k in range(16):
        e = np.zeros(16)
        e[k] = 1.0
        g[:, k] = link_from_pseudo_inertia(e.reshape(4, 4))
    return g


_G = _pseudo_inertia_map()


@dataclass(frozen=True)
class LinkCheck:
    """Physical consistency of one link's ten parameters (each condition, by how much)."""

    link: int  # 1-based
    mass: float
    min_eigenvalue: float  # of the pseudo-inertia (kg m^2); >= 0 is consistent
    violations: list[str]

    @property
    def consistent(self) -> bool:
        return not self.violations

    def to_json(self) -> dict[str, Any]:
        return {"link": self.link, "mass": self.mass, "pseudo_inertia_min_eigenvalue": self.min_eigenvalue,
                "consistent": self.consistent, "violations": self.violations}


def check_link(phi_link: Array, link: int) -> LinkCheck:
    """Which conditions of a physical body the parameters break (to rounding): mass > 0,
    pseudo-inertia positive semidefinite, and (when the mass is positive) the inertia about the centre of
    mass positive semidefinite with its principal moments obeying the triangle inequalities."""
    phi_link = np.asarray(phi_link, dtype=float)
    j = pseudo_inertia(phi_link)
    eigs = np.linalg.eigvalsh(j)
    eig = float(eigs[0])
    # rounding: a body on the boundary (a point mass, a rod) computes a few ulps either side
    tol = 1e-12 * float(np.abs(eigs).max())
    out = []
    m = float(phi_link[0])
    if not m > -tol:  # a massless link's completion computes -4e-18 kg as readily as +4e-18 (the PUMA 560's first)
        out.append(f"mass {m:.4g} kg is not positive")
    if eig < -tol:
        out.append(f"pseudo-inertia not positive semidefinite (smallest eigenvalue {eig:.3g} kg m^2)")
    if m > 0:
        s = phi_link[1:4] / m
        i_link = inertia_matrix(phi_link[4:10])
        i_com = i_link - m * (s @ s * np.eye(3) - np.outer(s, s))
        p = np.linalg.eigvalsh(i_com)
        if p[0] < -tol:
            out.append(f"inertia about the centre of mass has a negative principal moment {p[0]:.3g} kg m^2")
        gap = float(p[0] + p[1] - p[2])
        if gap < -tol:
            out.append(f"principal moments break the triangle inequality: {p[0]:.3g} + {p[1]:.3g} < {p[2]:.3g} kg m^2 (by {-gap:.3g})")
    return LinkCheck(link, m, eig, out)


Box = tuple[Array, Array]
"""Lower and upper corners (3,) each, m, in the link frame, of a box that holds a link."""


def box_matrices(box: Box) -> Array:
    """(3, 4, 4) ``B_k`` with ``tr(B_k J) = E[(u_k - x_k)(x_k - l_k)]``, integrated over the
    link's mass (Wensing, Kim and Slotine 2017, the box as three slabs): non-negative when
    all the mass lies in ``l <= x <= u``. With ``J >= 0`` it keeps the centre of mass in the
    box and bounds the second moment, hence the inertia, by the box's.

    .. math:: \\mathrm{tr}(B_k J) = -\\Sigma_{kk} + (u_k + l_k) h_k - u_k l_k m \\ge 0
    """
    lo, hi = (np.asarray(x, dtype=float) for x in box)
    out = np.zeros((3, 4, 4))
    for k in range(3):
        out[k, k, k] = -1.0
        out[k, k, 3] = out[k, 3, k] = 0.5 * (hi[k] + lo[k])
        out[k, 3, 3] = -hi[k] * lo[k]
    return out


def check_box(phi_link: Array, box: Box) -> list[str]:
    """Which slab of the box the link's mass leaves (:func:`box_matrices`), by how much."""
    j = pseudo_inertia(phi_link)
    tol = 1e-8 * float(np.abs(np.linalg.eigvalsh(j)).max())
    out = []
    lo, hi = box
    for k, b in enumerate(box_matrices(box)):
        value = float(np.sum(b * j))
        if value < -tol:
            com = j[k, 3] / j[3, 3] if j[3, 3] > 0 else float("nan")
            out.append(f"mass outside its bounding box along {'xyz'[k]} (E[(u - x)(x - l)] = {value:.3g} kg m^2; "
                       f"centre of mass {com:.3g} m, box {lo[k]:.3g} to {hi[k]:.3g} m)")
    return out


def check_parameters(phi: Array, n_links: int, boxes: list[Box | None] | None = None) -> list[LinkCheck]:
    """:func:`check_link` for every link of a standard parameter vector (10 N + k,), and
    :func:`check_box` where a link has a box."""
    checks = [check_link(phi[10 * i : 10 * i + 10], i + 1) for i in range(n_links)]
    for i, box in enumerate(boxes or []):
        if box is not None:
            checks[i].violations.extend(check_box(phi[10 * i : 10 * i + 10], box))
    return checks


def feasible_prior(phi0_link: Array, floor: float = PRIOR_FLOOR, fallback: Array | None = None) -> tuple[Array, str | None]:
    """The modeled pseudo-inertia, made positive definite if it is not (and why). A link
    modeled as nothing at all (a URDF link without ``<inertial>``) takes ``fallback``
    (default: 1 kg spread over a 0.1 m sphere at the link origin): a vanishing prior would
    make the divergence, which measures ratios, pin the link to nothing."""
    j0 = pseudo_inertia(phi0_link)
    w, v = np.linalg.eigh(j0)
    if w[-1] > 0 and w[0] > 1e-6 * w[-1]:
        return j0, None
    if w[-1] <= 1e-12:
        default = np.diag([0.004, 0.004, 0.004, 1.0]) if fallback is None else fallback
        return default, "modeled as massless; the prior is " + ("the other links' mean" if fallback is not None else "1 kg in a 0.1 m sphere")
    scale = float(w[-1])
    w2 = np.maximum(w, floor * scale)
    note = (f"modeled values are not a physical body (pseudo-inertia eigenvalue {w[0]:.3g} kg m^2); "
            f"the prior is the nearest one with eigenvalues >= {floor:g} of the largest")
    return (v * w2) @ v.T, note


# ---------------------------------------------------------------------------------------
# the fit


def base_projection(base: BaseParameters, n_columns: int) -> Array:
    """``P`` (p, n_columns) with ``beta = P phi`` (``phi_b + K phi_d``, 5.4)."""
    p = base.projection()
    if p.shape[1] != n_columns:
        raise ValueError(f"the base parameters have {p.shape[1]} columns, not {n_columns}")
    return p


@dataclass(frozen=True)
class FeasibleOptions:
    # weight of the entropic divergence against the whitened residual sum of squares: one
    # unit of divergence costs what a one-sigma move of one base parameter costs
    regularization: float = 1.0
    tolerance: float = 1e-9


@dataclass
class FeasibleFit:
    """The physically consistent standard parameters and what the fit cost."""

    phi: Array  # (n_columns,) standard parameters: 10 per link (about the link frame), then effects
    beta: Array  # (p,) their base projection
    distance: float  # ||R (beta - beta_ls)||: whitened distance from the least-squares estimate
    divergence: Array  # (N,) entropic divergence of each link from its prior
    checks: list[LinkCheck]
    prior_notes: list[str]
    iterations: int
    seconds: float
    converged: bool
    message: str

    @property
    def consistent(self) -> bool:
        return all(c.consistent for c in self.checks)


def divergence(j: Array, j0: Array) -> float:
    """Entropic (log-det) divergence ``tr(J0^-1 J) - log det(J0^-1 J) - 4`` (inf if J is not PD)."""
    a = np.linalg.solve(j0, j)
    sign, logdet = np.linalg.slogdet(a)
    return float(np.trace(a) - logdet - 4) if sign > 0 else float("inf")


def feasible_fit(r: Array, beta_ls: Array, projection: Array, phi_prior: Array, n_links: int,
                 signed: Array | None = None, options: FeasibleOptions | None = None, boxes: list[Box | None] | None = None) -> FeasibleFit:
    """Physically consistent ``phi`` whose base projection is closest to ``beta_ls`` in the
    metric ``r`` (module docstring).

    Parameters
    ----------
    r : (p, p) triangular factor of the weighted base regressor (``W_b = Q r``).
    beta_ls : (p,) least-squares base estimate.
    projection : (p, n) base projection ``P``; columns ``10 N..n`` are effects.
    phi_prior : (n,) modeled standard parameters (links' values are the prior).
    signed : (n - 10 N,) boolean, effect parameters that must be >= 0.
    boxes : per link, None or the box that must hold its mass (:func:`box_matrices`).
    """
    import cvxpy as cp

    options = options or FeasibleOptions()
    start = time.perf_counter()
    n = projection.shape[1]
    n_inertial = 10 * n_links
    n_eff = n - n_inertial
    signed = np.zeros(n_eff, bool) if signed is None else np.asarray(signed, bool)
    if not np.isfinite(phi_prior[:n_inertial]).all():
        bad = int(np.flatnonzero(~np.isfinite(phi_prior[:n_inertial]))[0]) // 10 + 1
        raise IdentificationError(f"link {bad} has no modeled inertial values: the physically consistent fit needs them as its prior")
    priors, notes = [], []
    solid = [pseudo_inertia(phi_prior[10 * i : 10 * i + 10]) for i in range(n_links)]
    solid = [j for j in solid if np.linalg.eigvalsh(j)[-1] > 1e-12]
    fallback = feasible_prior(link_from_pseudo_inertia(np.mean(solid, axis=0)))[0] if solid else None
    for i in range(n_links):
        j0, note = feasible_prior(phi_prior[10 * i : 10 * i + 10], fallback=fallback)
        if note:
            notes.append(f"link {i + 1}: {note}")
        priors.append(j0)
    # unknowns: each link's pseudo-inertia (symmetric 4x4) and the effects' parameters;
    # phi is linear in them (I = tr(Sigma) E - Sigma)
    js = [cp.Variable((4, 4), symmetric=True) for _ in range(n_links)]
    eff = cp.Variable(n_eff) if n_eff else None
    parts = [_G @ cp.reshape(j, 16, order="C") for j in js] + ([eff] if eff is not None else [])
    phi = cp.hstack(parts)
    # the data term, scaled to order one for the solver's tolerances
    a = r @ projection
    target = r @ beta_ls
    scale = max(float(np.linalg.norm(a @ np.nan_to_num(phi_prior) - target)) ** 2, 1.0)
    data = cp.sum_squares(a @ phi - target) / scale
    reg = 0
    for j, j0 in zip(js, priors):
        reg += cp.trace(np.linalg.inv(j0) @ j) - cp.log_det(j)
    constraints = [j >> 0 for j in js]
    for j, box in zip(js, boxes or []):
        if box is not None:
            constraints += [cp.trace(b @ j) >= 0 for b in box_matrices(box)]
    if eff is not None and signed.any():
        constraints.append(eff[np.flatnonzero(signed)] >= 0)
    problem = cp.Problem(cp.Minimize(data + options.regularization / scale * reg), constraints)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "may be inaccurate": the status says so, and the checks decide
            problem.solve(solver=cp.CLARABEL, tol_gap_abs=options.tolerance, tol_gap_rel=options.tolerance, tol_feas=options.tolerance)
    except cp.error.SolverError as err:
        raise IdentificationError(f"the physically consistent fit failed in the solver ({err})") from err
    if problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or phi.value is None:
        raise IdentificationError(f"the physically consistent fit found no solution (solver status {problem.status})")
    value = np.asarray(phi.value, dtype=float)
    value = _strictly_feasible(value, priors)
    if n_eff:
        value[n_inertial:][signed] = np.maximum(value[n_inertial:][signed], 0.0)
    beta = projection @ value
    div = np.array([divergence(pseudo_inertia(value[10 * i : 10 * i + 10]), j0) for i, j0 in enumerate(priors)])
    stats = problem.solver_stats
    return FeasibleFit(value, beta, float(np.linalg.norm(r @ (beta - beta_ls))), div, check_parameters(value, n_links, boxes), notes,
                       int(stats.num_iters or 0), time.perf_counter() - start, problem.status == cp.OPTIMAL, str(problem.status))


def _strictly_feasible(phi: Array, priors: list[Array]) -> Array:
    """An interior-point solution may leave a pseudo-inertia a rounding error below the cone;
    the convex combination ``(1 - e) J + e J0`` with the (positive definite) prior lifts it
    back with the least ``e`` (linear in phi, so the base projection moves by as little)."""
    out = phi.copy()
    for i, j0 in enumerate(priors):
        j = pseudo_inertia(out[10 * i : 10 * i + 10])
        low = float(np.linalg.eigvalsh(j)[0])
        floor = 1e-12 * float(np.linalg.eigvalsh(j0)[-1])
        if low >= floor:
            continue
        # (1 - e) low + e min(eig J0) >= floor, with a factor 2 to spare
        e = min(1.0, 2 * (floor - low) / (float(np.linalg.eigvalsh(j0)[0]) - low))
        out[10 * i : 10 * i + 10] = link_from_pseudo_inertia((1 - e) * j + e * j0)
    return out


def weighted_factor(factors: JointFactors, joint_sigma: Array, weighting: str) -> Array:
    """(p, p) R of the per-joint whitened base regressor (the weighting least squares used)."""
    weights = 1.0 / np.maximum(joint_sigma, 1e-300) if weighting == "wls" else np.ones(len(factors.r))
    return factors.combined(weights)[:-1, :-1]


def completed_least_squares(beta_ls: Array, projection: Array, phi_prior: Array) -> Array:
    """The least-squares estimate as standard parameters: the modeled values moved by the
    least (Euclidean) change that reproduces ``beta_ls`` (what a user who fills the
    unidentifiable parameters from the model would get)."""
    phi0 = np.nan_to_num(np.asarray(phi_prior, float))
    return phi0 + np.linalg.lstsq(projection, beta_ls - projection @ phi0, rcond=None)[0]


__all__ = ["Box", "FeasibleFit", "FeasibleOptions", "FeasibleResult", "LinkCheck", "factor_summary", "feasible_estimate", "predict", "base_projection",
           "box_matrices", "check_box", "check_link", "check_parameters",
           "completed_least_squares", "feasible_fit", "feasible_prior", "link_from_pseudo_inertia", "pseudo_inertia", "weighted_factor"]


# ---------------------------------------------------------------------------------------
# on an identification result (what `armid identify --feasible` and the demo call)


def factor_summary(factors: JointFactors, beta: Array) -> dict[str, Any]:
    """INTERFACES.md metrics of ``beta`` on the identification data, from the triangles alone
    (``|tau_j|^2`` is the residual of ``beta = 0``)."""
    sq = factors.residual_squares(beta)
    norm = factors.residual_squares(np.zeros_like(beta))
    return {"relative_error": float(np.sqrt(sq.sum() / norm.sum())), "rms": [float(x) for x in np.sqrt(sq / factors.counts)],
            "relative": [float(x) for x in np.sqrt(sq / np.maximum(norm, 1e-300))]}


@dataclass
class FeasibleResult:
    """The physically consistent estimate beside the least-squares one it came from."""

    robot_name: str
    names: list[str]
    expressions: list[str]
    effect_labels: list[tuple[str, int, str, str]]  # (effect, 1-based joint, parameter, column name)
    n_links: int
    fit: FeasibleFit
    options: FeasibleOptions
    least_squares_checks: list[LinkCheck]
    least_squares_fit: dict[str, Any]
    feasible_fit_error: dict[str, Any]
    metric: Array  # (p, p) R of the weighted base regressor: ||R (beta - beta_ls)|| is the fit's distance
    least_squares_validation: dict[str, Any] | None = None
    validation: dict[str, Any] | None = None
    boxes: list[Box | None] | None = None

    @property
    def phi(self) -> Array:
        return self.fit.phi

    @property
    def consistent(self) -> bool:
        return self.fit.consistent

    def to_json(self) -> dict[str, Any]:
        """The consistency report and the feasible parameters (``"feasible"`` in the identify JSON)."""
        phi = self.fit.phi
        ls_links = [c.to_json() for c in self.least_squares_checks]
        ratio = None
        if self.validation and self.least_squares_validation:
            ratio = self.validation["relative_error"] / self.least_squares_validation["relative_error"]
        return {
            "regularization": {"kind": "entropic: log-det divergence of each link's pseudo-inertia from the modeled one "
                                       "(Lee, Wensing and Park 2019)", "weight": self.options.regularization},
            "solver": "cvxpy with Clarabel (SDP: pseudo-inertia PSD cones, log-det as exponential cones)",
            "bounding_boxes": None if self.boxes is None else [None if b is None else {"lower": [float(x) for x in b[0]], "upper": [float(x) for x in b[1]]}
                                                                for b in self.boxes],
            "status": self.fit.message, "converged": self.fit.converged, "iterations": self.fit.iterations, "seconds": self.fit.seconds,
            "prior_notes": self.fit.prior_notes,
            "distance_from_least_squares": self.fit.distance,
            "least_squares": {
                "consistent": all(c.consistent for c in self.least_squares_checks),
                "note": "base estimate completed with the modeled values by the least change (what the data cannot see stays modeled)",
                "links": ls_links, "fit": self.least_squares_fit, "validation": self.least_squares_validation,
            },
            "feasible": {"consistent": self.consistent, "links": [c.to_json() for c in self.fit.checks], "fit": self.feasible_fit_error,
                         "validation": self.validation, "validation_ratio": ratio},
            "parameters": [{"name": self.names[k], "link": k // 10 + 1, "value": float(phi[k])} for k in range(10 * self.n_links)],
            "effects": [{"effect": e, "joint": j, "parameter": p, "value": float(phi[self.names.index(c)])} for e, j, p, c in self.effect_labels],
            "base_parameters": [{"expression": x, "value": float(v)} for x, v in zip(self.expressions, self.fit.beta)],
            "divergence": [float(x) for x in self.fit.divergence],
        }

    def summary_line(self, errors: bool = True) -> str:
        """One line: which models are physical, and (``errors``) their validation errors as
        ``armid identify`` gives its own (fractions, on the fitted equations)."""
        bad = [c.link for c in self.least_squares_checks if not c.consistent]
        text = "least squares (completed with the modeled values): " + (f"{link_list(bad)} not physical" if bad else "physically consistent")
        text += f"; feasible: {'consistent' if self.consistent else 'NOT consistent'}, {self.fit.distance:.3g} sigma from least squares"
        if errors and self.validation and self.least_squares_validation:
            text += (f", validation error {self.validation['relative_error']:.4g} "
                     f"(least squares {self.least_squares_validation['relative_error']:.4g})")
        return text


def feasible_estimate(result: Any, validation: list[Any] | None = None, options: FeasibleOptions | None = None,
                      boxes: list[Box | None] | None = None) -> FeasibleResult:
    """The physically consistent estimate of an :class:`~identify.identification.IdentificationResult`
    (``identify(...)``'s return), with its held-out error on ``validation`` (``Prepared`` list);
    with ``boxes`` (per link, None or lower and upper corners in the link frame), each link's
    mass also stays in its box."""
    if result.factors is None:
        raise IdentificationError("this identification result carries no regressor factors; run identify() again")
    options = options or FeasibleOptions()
    robot = result.robot
    n_links = robot.n_joints
    names = list(result.names)
    projection = base_projection(result.base, len(names))
    prior = np.concatenate([robot.modeled_parameters(), np.zeros(len(names) - robot.n_parameters)])
    labels = [(e.effect, e.joint + 1, p, c) for e in result.effects for p, c in zip(e.parameter_names, e.labels())]
    signed = np.array([e in SIGNED_EFFECTS for e, _, _, _ in labels], bool)
    r = weighted_factor(result.factors, result.estimate.joint_sigma, result.estimate.weighting)
    beta_ls = result.estimate.beta
    if boxes is not None and len(boxes) != n_links:
        raise IdentificationError(f"{len(boxes)} bounding boxes for {n_links} links")
    fit = feasible_fit(r, beta_ls, projection, prior, n_links, signed, options, boxes)
    ls_checks = check_parameters(completed_least_squares(beta_ls, projection, prior), n_links, boxes)
    out = FeasibleResult(robot.name, names, result.base.expressions(), labels, n_links, fit, options, ls_checks,
                         factor_summary(result.factors, beta_ls), factor_summary(result.factors, fit.beta), r, boxes=boxes)
    if validation:
        from .metrics import summary

        segs = [s for p in validation for s in p.segments]
        tau = np.concatenate([s.tau for s in segs])
        out.least_squares_validation = summary(tau, np.concatenate([predict(result, beta_ls, s) for s in segs]))
        out.validation = summary(tau, np.concatenate([predict(result, fit.beta, s) for s in segs]))
    return out


def predict(result: Any, beta: Array, segment: Any) -> Array:
    """Torques (n, N) of base parameters ``beta`` on a segment's motion (the result's model)."""
    from .identification import base_torque

    return base_torque(result.robot, result.effects, result.base.independent, beta, segment.q, segment.qd, segment.qdd)

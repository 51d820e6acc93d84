"""A load on the last link, read out of the steps of the base parameters (issue 62). Arrays in,
arrays out.

A body fixed to the last link ``N`` (a tool, a payload) adds its own parameters about that
link's frame, in Khosla's order (eq. 10),

.. math:: \\Delta\\phi_N = [m, \\; m c, \\; I_c + m (c^T c \\, E - c c^T)]

(``c`` its centre of mass in the frame, ``I_c`` its inertia about its centre), to the link's
standard parameters. The base parameters are linear in the standard ones (5.4,
:meth:`~identify.identifiability.BaseParameters.projection`: ``beta = P phi``), so the base
parameters step by

.. math:: \\Delta\\beta = P_N \\, \\Delta\\phi_N

with ``P_N`` the last link's ten columns of ``P`` (:func:`last_link_rows`). Given each base
parameter's step and its standard error (:func:`identify.changes.step_at`: those that did not
change count as 0 +- their std), :func:`fit_load` fits ``Delta phi_N`` by weighted least
squares, checks that it explains the steps (its chi-square), and reads off the mass and the
centre of mass.

Joint torques do not always see the load's mass: on an arm whose last joints share an axis
through the last link's origin and whose first axis is vertical, ``m_N`` appears in one base
parameter only, together with ``msz_N`` and ``Iyy_N``. Where the least-squares fit leaves the
mass undetermined (not in the row space of the weighted ``P_N``), the load is taken to be
*compact*: a point mass (``I_c = 0``) at ``c``, four unknowns ``(m, c)`` fitted by Gauss-Newton
on the same equations; the moments it moved (``m c``, ``m c c^T``) then determine it. A tool's
own inertia about its centre is small beside ``m c^T c`` when it sits a few centimetres off,
and what it leaves unexplained is in the fit's chi-square.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from ..identifiability import BaseParameters
from ..robot import inertia_entries
from ..spatial import Array

FIT_ALPHA = 0.001
"""A load is named when the chance of a misfit as large as its fit's, were it the load, is at
least this (:attr:`LoadFit.p_value`): below, the steps are something else."""

DETERMINED = 5.0
"""The mass is well determined when it is at least this many of its standard deviations from
0: only then is ``m c / m`` a centre of mass."""

RANK_RTOL = 1e-9
ESTIMABLE_TOL = 1e-6
MIN_DISPERSION_ROWS = 3


def last_link_rows(base: BaseParameters, n_links: int) -> Array:
    """``P_N`` (p, 10): the columns of the base parameters' projection ``beta = P phi`` (5.4) on the
    last link's ten standard parameters ``m, msx, msy, msz, Ixx, Ixy, Ixz, Iyy, Iyz, Izz``."""
    return np.asarray(base.projection()[:, 10 * (n_links - 1) : 10 * n_links], float)


def load_parameters(mass: float, com: Array, inertia_at_com: Array | None = None) -> Array:
    """``Delta phi_N`` (10,) of a body of ``mass`` (kg) centred at ``com`` (3,) m in the link frame,
    its inertia about its centre ``inertia_at_com`` (3, 3) kg m^2 (default 0: a point mass), by
    Steiner's law (Khosla eq. 10).

    .. math:: \\Delta\\phi = [m, m c, I_c + m (c^T c E - c c^T)]
    """
    c = np.asarray(com, float)
    i_c = np.zeros((3, 3)) if inertia_at_com is None else np.asarray(inertia_at_com, float)
    return np.concatenate([[mass], mass * c, inertia_entries(i_c + mass * (c @ c * np.eye(3) - np.outer(c, c)))])


def _point_jacobian(mass: float, c: Array) -> Array:
    """d Delta phi / d (m, c) (10, 4) of a point mass (:func:`load_parameters` without ``I_c``)."""
    jac = np.zeros((10, 4))
    jac[:, 0] = load_parameters(1.0, c)
    for j in range(3):
        e = np.eye(3)[j]
        jac[1 + j, 1 + j] = mass
        jac[4:, 1 + j] = mass * inertia_entries(2 * c[j] * np.eye(3) - np.outer(e, c) - np.outer(c, e))
    return jac


@dataclass(frozen=True)
class LoadFit:
    """What :func:`fit_load` found. ``model``: ``rigid body`` (the ten parameters by linear least
    squares) or ``point mass`` (the mass left open by them: ``(m, c)`` of a compact load);
    ``phi`` (10,) the fitted ``Delta phi_N``; ``mass``, ``mass_std`` kg; ``com``, ``com_std``
    (3,) m in the last link's frame, NaN where not determined (``note`` says why); ``chi2`` over
    ``dof`` of the steps the load moves and of those flagged that it cannot move, ``dispersion`` the mean squared standardized step of
    those it cannot move (the arm's own excess scatter, at least 1), ``p_value`` the chance of
    so large a misfit were it this load (F test against that scatter; 1 when the fit is exact);
    ``explains`` whether ``p_value >= FIT_ALPHA``; ``moved`` (p,) the rows the load can move."""

    model: str
    phi: Array
    mass: float
    mass_std: float
    com: Array
    com_std: Array
    chi2: float
    dof: int
    dispersion: float
    p_value: float
    explains: bool
    moved: Array
    note: str


def _dispersion(z2: Array) -> tuple[float, float]:
    """(the arm's excess scatter of standardized steps, its degrees of freedom; inf when too few)."""
    z2 = z2[np.isfinite(z2)]
    if z2.size < MIN_DISPERSION_ROWS:
        return 1.0, np.inf
    return max(1.0, float(z2.mean())), float(z2.size)


def _point_fit(aw: Array, yw: Array, start_h: Array) -> tuple[Array, Array, Array]:
    """``(m, c)``, their covariance per unit scatter and ``Delta phi`` of the point mass whose
    weighted steps ``aw @ phi`` best match ``yw``: Gauss-Newton from masses 0.01-100 kg
    (``start_h``: the first moment the linear fit gave, its undetermined entries 0)."""
    best: tuple[float, Array] | None = None
    for m0 in np.geomspace(0.01, 100.0, 9):
        theta = np.concatenate([[m0], start_h / m0])
        for _ in range(60):
            phi = load_parameters(theta[0], theta[1:])
            jac = aw @ _point_jacobian(theta[0], theta[1:])
            step = np.linalg.lstsq(jac, yw - aw @ phi, rcond=None)[0]
            theta = theta + step
            if not np.all(np.isfinite(theta)):
                break
            if np.max(np.abs(step) / np.maximum(np.abs(theta), 1e-6)) < 1e-10:
                break
        if not np.all(np.isfinite(theta)):
            continue
        r = yw - aw @ load_parameters(theta[0], theta[1:])
        if best is None or float(r @ r) < best[0]:
            best = (float(r @ r), theta)
    if best is None:
        return np.full(4, np.nan), np.full((4, 4), np.nan), np.full(10, np.nan)
    theta = best[1]
    jac = aw @ _point_jacobian(theta[0], theta[1:])
    return theta, np.linalg.pinv(jac.T @ jac), load_parameters(theta[0], theta[1:])


def fit_load(rows: Array, steps: Array, stds: Array, changed: Array | None = None) -> LoadFit:
    """The last-link load that best explains the base parameters' steps.

    ``rows`` (p, 10) ``P_N`` (:func:`last_link_rows`); ``steps``, ``stds`` (p,) each base
    parameter's step at one recording and its standard error (every base parameter, changed or
    not); ``changed`` (p,) those the change test flagged: left out of the arm's scatter (the
    mean squared ``steps / stds`` of the others no load moves, the chi-square's yardstick), and
    in the chi-square when no load moves them.
    Weighted least squares of ``steps = P_N Delta phi`` (weights ``1/stds^2``) on the steps a
    load moves; where its mass is not in the row space, the point mass of the module's
    docstring. The standard deviations are scaled by the scatter of the steps no load moves
    and by the fit's own chi-square per degree of freedom when larger (Birge's ratio)."""
    rows, steps, stds = (np.asarray(a, float) for a in (rows, steps, stds))
    changed = np.zeros(steps.size, bool) if changed is None else np.asarray(changed, bool)
    ok = np.isfinite(steps) & np.isfinite(stds) & (stds > 0)
    scale = float(np.abs(rows).max()) if rows.size else 0.0
    moved = ok & (np.abs(rows).max(axis=1) > 1e-9 * max(scale, 1e-300)) if rows.size else np.zeros(steps.size, bool)
    z2 = np.where(ok & ~moved & ~changed, (steps / np.where(ok, stds, 1.0)) ** 2, np.nan)
    dispersion, disp_df = _dispersion(z2)
    nan3 = np.full(3, np.nan)
    if not moved.any():
        return LoadFit("rigid body", np.full(10, np.nan), np.nan, np.nan, nan3, nan3, np.nan, 0, dispersion, 0.0, False, moved,
                       "no base parameter contains the last link's parameters")
    aw, yw = rows[moved] / stds[moved, None], steps[moved] / stds[moved]
    u, s, vt = np.linalg.svd(aw, full_matrices=False)
    rank = int(np.sum(s > RANK_RTOL * s[0]))
    v = vt[:rank].T
    phi = v @ ((u[:, :rank].T @ yw) / s[:rank])
    estimable = np.linalg.norm(np.eye(10) - v @ v.T, axis=0) < ESTIMABLE_TOL
    notes = []
    if estimable[0]:
        model, npar = "rigid body", rank
        cov = (v / s[:rank] ** 2) @ v.T
        mass, h = float(phi[0]), phi[1:4]
        cov_mh = cov[:4, :4]
    else:
        model, npar = "point mass", 4
        theta, cov_theta, phi = _point_fit(aw, yw, np.where(estimable[1:4], phi[1:4], 0.0))
        mass, h = float(theta[0]), theta[0] * theta[1:]
        jac = np.zeros((4, 4))  # (m, h) from (m, c): h = m c
        jac[0, 0], jac[1:, 0], jac[1:, 1:] = 1.0, theta[1:], theta[0] * np.eye(3)
        cov_mh = jac @ cov_theta @ jac.T
        estimable = np.ones(10, bool)
        notes.append(f"the steps leave the mass open (the last link's parameters reach the base parameters in {rank} "
                     "independent combinations, its mass alone not among them): a compact load, a point mass at its centre")
    resid = yw - aw @ phi
    # a flagged step no load on the last link moves (another link's) counts against the load
    elsewhere = ok & ~moved & changed
    chi2 = float(resid @ resid) + float(np.sum((steps[elsewhere] / stds[elsewhere]) ** 2))
    dof = int(moved.sum()) - npar + int(elsewhere.sum())
    if elsewhere.any():
        notes.append(f"{int(elsewhere.sum())} base parameter(s) without the last link's parameters changed there too")
    if dof > 0:
        ratio = chi2 / dof / dispersion
        p_value = float(stats.f.sf(ratio, dof, disp_df)) if np.isfinite(disp_df) else float(stats.chi2.sf(ratio * dof, dof))
    else:
        ratio, p_value = 1.0, 1.0
        notes.append("the fit is exact (as many load parameters as steps it moves): any change of the last link is a load")
    cov_mh = cov_mh * dispersion * max(1.0, ratio)
    mass_std = float(np.sqrt(max(cov_mh[0, 0], 0.0)))
    com, com_std = nan3.copy(), nan3.copy()
    if not np.isfinite(mass) or abs(mass) < DETERMINED * mass_std:
        notes.append(f"centre of mass not given: the mass is not well determined ({mass:.3g} +- {mass_std:.2g} kg)")
    else:
        for j in range(3):
            if not estimable[1 + j]:
                continue
            com[j] = h[j] / mass
            grad = np.zeros(4)
            grad[0], grad[1 + j] = -h[j] / mass**2, 1.0 / mass
            com_std[j] = float(np.sqrt(max(grad @ cov_mh @ grad, 0.0)))
        missing = [a for j, a in enumerate("xyz") if not estimable[1 + j]]
        if missing:
            notes.append(f"centre of mass along {', '.join(missing)} not given: the steps do not determine the load's "
                         f"first moment there ({', '.join('ms' + a for a in missing)} of the last link)")
    return LoadFit(model, phi, mass, mass_std, com, com_std, chi2, dof, dispersion, p_value, p_value >= FIT_ALPHA, moved,
                   "; ".join(notes))

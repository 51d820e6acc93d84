"""One round of the diagnosis's search: the model so far fitted on the identification
data's even tenths, and every candidate scored against it by its odd tenths.

The rows are whitened by each joint's noise level. The model's columns are factored once a
round (QR); a candidate's columns are projected off them (Frisch-Waugh), so that the refit
with it, its F-test on the fit and its held-out residual cost a solve of the candidate's own
size (:func:`score_candidate`). A drive gain is fitted exactly instead, profiled over its scale
(:class:`_GainProfile`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import special

from ..estimation import bounded_quadratic
from ..kernels.threads import each_shared
from ..robot import Robot
from ..spatial import Array
from .candidates import Candidate, defining, lower_bounds
from .data import StackedData


def full_parameters(robot: Robot, base: Any, beta_base: Array, n_cols: int) -> Array:
    """Standard parameters that reproduce the base estimate and otherwise stay modeled (min-norm)."""
    p = robot.n_parameters
    phi0 = robot.modeled_parameters()
    b = np.array([base.base_values(np.eye(n_cols)[k]) for k in range(p)]).T  # (n_base, p)
    return phi0 + np.linalg.lstsq(b, beta_base - b @ phi0, rcond=None)[0]


class _GainProfile:
    """A drive gain on one joint fitted exactly: the joint measures ``s`` times the model's
    rigid-body torque, so that joint's rows of the base columns are scaled by ``s``, the
    linear parameters refitted, and ``s`` chosen by the identification fit's residual (a
    profile over ``s``: a log grid over 0.1-10, then Brent's method between the best point's
    neighbours). A gain linearised about the current fit (the prediction as one more column)
    is biased by that fit: the rigid-body parameters the joint's rows share with the rest of
    the arm were fitted to the scaled torque, and a large gain on a distal joint came out
    wrong, even of the wrong sign.

    The normal equations are split into the joint's rows and the others' (columns equilibrated),
    so that each value of ``s`` costs one small solve."""

    GRID = np.geomspace(0.1, 10.0, 41)

    def __init__(self, a_i: Array, y_i: Array, a_v: Array, y_v: Array, wt_v: Array, n_joints: int, p_base: int) -> None:
        self.norms = np.linalg.norm(a_i, axis=0)
        self.norms[self.norms == 0.0] = 1.0
        self.a = a_i / self.norms  # weighted identification rows, equilibrated
        self.y = y_i
        self.yy = float(y_i @ y_i)
        self.g_all, self.b_all = self.a.T @ self.a, self.a.T @ y_i
        self.a_v, self.y_v, self.wt_v = a_v, y_v, wt_v
        self.nj, self.p_base = n_joints, p_base

    def best(self, j: int) -> tuple[float, float, float, Array] | None:
        """(scale, identification RSS, held-out RSS, held-out prediction) at the best scale of
        joint j, or None when the best lies at the edge of 0.1-10 (not a drive's gain)."""
        from scipy.optimize import minimize_scalar

        aj = self.a[j :: self.nj]
        g_j, b_j = aj.T @ aj, aj.T @ self.y[j :: self.nj]
        g_o, b_o = self.g_all - g_j, self.b_all - b_j
        d = np.ones(self.a.shape[1])

        def fit(log_s: float) -> tuple[float, Array]:
            d[: self.p_base] = np.exp(log_s)
            g, b = g_o + d[:, None] * g_j * d[None, :], b_o + d * b_j
            try:
                x = np.linalg.solve(g, b)
            except np.linalg.LinAlgError:
                x = np.linalg.lstsq(g, b, rcond=None)[0]
            return self.yy - float(b @ x), x

        logs = np.log(self.GRID)
        rss = np.array([fit(v)[0] for v in logs])
        k = int(np.argmin(rss))
        if k in (0, len(logs) - 1):
            return None
        res = minimize_scalar(lambda v: fit(v)[0], bounds=(logs[k - 1], logs[k + 1]), method="bounded", options={"xatol": 1e-4})
        log_s = float(res.x) if res.fun <= rss[k] else float(logs[k])
        rss1, x = fit(log_s)
        scale = float(np.exp(log_s))
        coef = x / self.norms
        pred = self.a_v @ coef
        pred[j :: self.nj] += (scale - 1.0) * (self.a_v[j :: self.nj, : self.p_base] @ coef[: self.p_base])
        r_v = (self.y_v - pred) * self.wt_v
        return scale, max(rss1, 0.0), float(r_v @ r_v), pred


@dataclass
class RoundModel:
    """The model so far (base columns and the findings' columns) fitted on the whitened rows
    of the even tenths, ``A = QR`` with residual ``r``, and what scoring a candidate against it
    reuses: the held-out residual ``res_v`` and ``G = A_v R^-1`` (Frisch-Waugh, :func:`score_candidate`)."""

    n_joints: int
    a_i: Array  # the whitened identification rows of the model's columns
    q_mat: Array
    r_mat: Array
    beta: Array  # the model's parameters: base parameters first (p_base), then the findings'
    r: Array  # the whitened identification residual, orthogonal to Q
    rss: float
    a_v: Array  # the held-out rows of the model's columns (not whitened)
    res_v: Array  # the whitened held-out residual
    rss_v: float
    p_base: int
    g_mat: Array
    h_vec: Array
    h_mat: Array
    gain_fit: _GainProfile
    joint_of_row: Array
    power_before: Array  # the held-out residual power per joint
    rows_of_joint: list[_JointRows]  # the same, joint by joint (a one-joint candidate's own rows)


def f_sf(f_stat: float, dfn: float, dfd: float) -> float:
    """The F distribution's survival function, ``scipy.stats.f.sf`` to the bit (its own
    kernel, ``special.fdtrc``) without its argument checks: 0.14 ms a call, thousands of
    candidates a diagnosis."""
    return float(special.fdtrc(dfn, dfd, f_stat if np.isnan(f_stat) else max(f_stat, 0.0)))


@dataclass
class _JointRows:
    """One joint's rows of the round's ``Q`` and ``G``, transposed and contiguous: a one-joint
    candidate's products read only these, and ``Q[j::N].T @ B`` on the strided view cost about
    ten times the same product on this copy (hundreds of candidates a round, most of them
    cogging periods)."""

    q_t: Array
    g_t: Array


def _joint_rows(q_mat: Array, g_mat: Array, n_joints: int) -> list[_JointRows]:
    """Each joint's rows (:class:`_JointRows`), copied once a round."""
    return [_JointRows(np.ascontiguousarray(q_mat[j::n_joints].T), np.ascontiguousarray(g_mat[j::n_joints].T)) for j in range(n_joints)]


def fit_round(wi: Array, wv: Array, extra_i: Array, extra_v: Array, yi: Array, yv: Array, wt_i: Array, wt_v: Array,
               n_joints: int) -> RoundModel:
    """The model's columns (base ``wi``/``wv`` and findings ``extra_i``/``extra_v``, on the fit
    and the held-out rows) fitted by QR on the whitened fit rows (weights ``wt_i``), and its
    held-out residual (weights ``wt_v``)."""
    nj = n_joints
    a_i = np.column_stack([wi, extra_i]) * wt_i[:, None]
    q_mat, r_mat = np.linalg.qr(a_i)
    yw = yi * wt_i
    beta = np.linalg.solve(r_mat, q_mat.T @ yw)
    r = yw - q_mat @ (q_mat.T @ yw)
    rss = float(r @ r)
    a_v = np.column_stack([wv, extra_v])
    res_v = (yv - a_v @ beta) * wt_v
    rss_v = float(res_v @ res_v)
    p_base = wi.shape[1]
    # Frisch-Waugh on the whitened system A = QR with residual r (r is orthogonal to Q):
    # for columns C, P = Q^T C, gamma = (C^T C - P^T P)^-1 C^T r, the refit's beta is
    # beta - R^-1 P gamma, and the held-out residual is res_v + G P gamma - Cv gamma with
    # G = A_v R^-1. Only a candidate's own rows enter, so a round costs little.
    g_mat = np.linalg.solve(r_mat.T, (a_v * wt_v[:, None]).T).T
    h_vec, h_mat = g_mat.T @ res_v, g_mat.T @ g_mat
    gain_fit = _GainProfile(a_i, yw, a_v, yv, wt_v, nj, p_base)
    joint_of_row = np.arange(yv.size) % nj
    power_before = np.bincount(joint_of_row, res_v**2, nj)  # the held-out residual power per joint
    return RoundModel(nj, a_i, q_mat, r_mat, beta, r, rss, a_v, res_v, rss_v, p_base, g_mat, h_vec, h_mat, gain_fit, joint_of_row,
                  power_before, _joint_rows(q_mat, g_mat, nj))


@dataclass(eq=False)
class ScoredCandidate:
    """A candidate scored against a round: the held-out RSS of the refit with it, the F-test's
    p-value on the fit (and the fit's RSS), its parameters ``gamma``, and what rebuilding the refit needs: its
    columns' projection on the model (None when fitted exactly), the held-out prediction of an
    exactly fitted one, the per-joint held-out residual power an arm-wide one leaves."""

    rss_v: float
    p_value: float
    candidate: Candidate
    gamma: Array
    projection: Array | None
    exact_prediction: Array | None
    power_after: Array | None
    rss: float = float("nan")  # the whitened identification RSS of the refit with it (a nested pair's F-test)


@dataclass(eq=False)
class AbsorbedCandidate:
    """A candidate whose columns lie in the span of the model: its projection on the model."""

    projection: Array


def score_candidate(c: Candidate, rnd: RoundModel, ident: StackedData, held: StackedData, wt_i: Array, wt_v: Array, n_used: int,
           sample_period: float, moments: Moments | None = None) -> ScoredCandidate | AbsorbedCandidate | None:
    """The refit with ``c`` scored by Frisch-Waugh (:func:`fit_round`), or None when it cannot
    be a finding: columns that are not finite or all zero, a singular refit, an effect whose
    best admissible fit (friction, inertia and spring bounded at 0) holds its defining
    parameter at the bound, a delay within half a sample period. ``moments``: its products,
    when :func:`round_moments` computed them (a one-joint candidate's with its joint's others')."""
    if c.effect == "torque_gain":
        return _score_gain(c, rnd, n_used)
    proj, ctc, ctr, gv, cv_res, cvcv, cv_full = moments if moments is not None else _moments(c, rnd, ident, held, wt_i, wt_v)
    if not np.isfinite(ctc).all() or not np.any(np.diag(ctc) > 0):
        return None
    schur = ctc - proj.T @ proj
    if np.trace(schur) <= 1e-12 * np.trace(ctc):
        return AbsorbedCandidate(proj)
    try:
        # the best admissible fit (bounded least squares on the candidate's columns, the model's
        # profiled out by Frisch-Waugh: the joint fit, not a filter afterwards)
        gamma = bounded_quadratic(schur, ctr, lower_bounds(c))
    except (np.linalg.LinAlgError, ValueError):
        return None
    if not np.all(np.isfinite(gamma)):
        return None
    bound = defining(c)
    if bound and bool(np.all(gamma[bound] <= 0.0)):
        return None  # held at its bound: friction, an inertia or a spring that adds nothing physical
    if c.effect == "time_delay" and abs(float(gamma[0])) < 0.5 * sample_period:
        # shorter than half a sample period: within the timing uncertainty of the
        # samples themselves (zero-order hold of the current, current loop, filters)
        return None
    rss1 = rnd.rss - float(2.0 * ctr @ gamma - gamma @ schur @ gamma)
    u = proj @ gamma
    rss_v1 = float(rnd.rss_v + 2 * rnd.h_vec @ u + u @ rnd.h_mat @ u - 2 * cv_res @ gamma - 2 * u @ gv @ gamma + gamma @ cvcv @ gamma)
    k = len(gamma)
    dof = n_used - rnd.a_i.shape[1] - k
    f_stat = ((rnd.rss - rss1) / k) / max(rss1 / dof, 1e-300)
    p_value = f_sf(f_stat, k, dof)
    power_after: Array | None = None
    if cv_full is not None:  # the held-out residual power it leaves on each joint
        res_c = rnd.res_v + rnd.g_mat @ u - cv_full @ gamma
        power_after = np.bincount(rnd.joint_of_row, res_c**2, rnd.n_joints)
    return ScoredCandidate(rss_v1, p_value, c, gamma, proj, None, power_after, rss1)


def joint_power_after(s: ScoredCandidate, rnd: RoundModel, held: StackedData, wt_v: Array) -> float:
    """The whitened held-out residual power a one-joint candidate leaves on its own joint (its
    rows weigh alike, so whitening does not change which of two shapes leaves less)."""
    j, nj = s.candidate.joint, rnd.n_joints
    assert j is not None and s.candidate.block is not None and s.projection is not None
    cv = s.candidate.block(held) * wt_v[j::nj, None]
    res = rnd.res_v[j::nj] + rnd.rows_of_joint[j].g_t.T @ (s.projection @ s.gamma) - cv @ s.gamma
    return float(res @ res)


def _score_gain(c: Candidate, rnd: RoundModel, n_used: int) -> ScoredCandidate | None:
    """A drive gain fitted exactly, not linearised about the current fit: the joint's
    rigid-body columns scaled by the gain, profiled over it (:class:`_GainProfile`); None for a
    gain below 0.1 or above 10 (a wrong robot file or wiring, not an effect)."""
    assert c.joint is not None
    exact = rnd.gain_fit.best(c.joint)
    if exact is None:
        return None
    scale, rss1, rss_v1, pred_exact = exact
    dof = n_used - rnd.a_i.shape[1] - 1
    f_stat = (rnd.rss - rss1) / max(rss1 / dof, 1e-300)
    return ScoredCandidate(rss_v1, f_sf(f_stat, 1, dof), c, np.array([scale - 1.0]), None, pred_exact, None, rss1)


Moments = tuple[Array, Array, Array, Array, Array, Array, Array | None]
"""What :func:`_moments` gives: ``P, C^T C, C^T r, G^T Cv, Cv^T res_v, Cv^T Cv`` and the held-out columns of an arm-wide candidate."""


def round_moments(candidates: list[Candidate], rnd: RoundModel, ident: StackedData, held: StackedData, wt_i: Array, wt_v: Array) -> dict[int, Moments]:
    """:func:`_moments` of every candidate but a drive gain (by ``id``). A joint's one-joint
    candidates go joint by joint in one matrix product over all their columns: the round's
    rows are read once a joint instead of once a candidate (hundreds a round, most of them
    cogging periods). The joints and the other candidates (a delay's prediction on each
    joint's motion shifted either way, the arm's) are independent, and share the cores
    (identify.kernels.threads)."""
    nj = rnd.n_joints
    out: dict[int, Moments] = {}
    alone = [c for c in candidates if c.block is None and c.effect != "torque_gain"]

    def one_joint(j: int) -> None:
        mine = [(c, c.block) for c in candidates if c.block is not None and c.joint == j and c.effect != "torque_gain"]
        if not mine:
            return
        bis = [block(ident) * wt_i[j::nj, None] for _, block in mine]
        bvs = [block(held) * wt_v[j::nj, None] for _, block in mine]
        bi, bv = np.hstack(bis), np.hstack(bvs)
        rows = rnd.rows_of_joint[j]
        proj, gv = rows.q_t @ bi, rows.g_t @ bv
        ctr, cv_res = bi.T @ rnd.r[j::nj], bv.T @ rnd.res_v[j::nj]
        k = 0
        for (c, _), a, v in zip(mine, bis, bvs):
            cols = slice(k, k + a.shape[1])
            k += a.shape[1]
            out[id(c)] = (proj[:, cols], a.T @ a, ctr[cols], gv[:, cols], cv_res[cols], v.T @ v, None)

    def task(k: int) -> None:
        if k < nj:
            one_joint(k)
        else:
            c = alone[k - nj]
            out[id(c)] = _moments(c, rnd, ident, held, wt_i, wt_v)

    each_shared(task, nj + len(alone), "scoring")
    return out


def _moments(c: Candidate, rnd: RoundModel, ident: StackedData, held: StackedData, wt_i: Array,
             wt_v: Array) -> Moments:
    """The products of a candidate's whitened columns Frisch-Waugh needs: ``P = Q^T C``,
    ``C^T C``, ``C^T r``, ``G^T Cv``, ``Cv^T res_v``, ``Cv^T Cv``, and the held-out columns
    themselves for an arm-wide candidate (None for one that lives in its joint's rows: only
    those rows enter)."""
    nj = rnd.n_joints
    if c.block is not None:
        j = c.joint
        assert j is not None
        bi = c.block(ident) * wt_i[j :: nj, None]
        bv = c.block(held) * wt_v[j :: nj, None]
        rows = rnd.rows_of_joint[j]
        proj = rows.q_t @ bi
        ctc, ctr = bi.T @ bi, bi.T @ rnd.r[j::nj]
        gv, cv_res, cvcv = rows.g_t @ bv, bv.T @ rnd.res_v[j::nj], bv.T @ bv
        return proj, ctc, ctr, gv, cv_res, cvcv, None
    assert c.full is not None
    ci_full = c.full(ident) * wt_i[:, None]
    cv_full = c.full(held) * wt_v[:, None]
    proj = rnd.q_mat.T @ ci_full
    ctc, ctr = ci_full.T @ ci_full, ci_full.T @ rnd.r
    gv, cv_res, cvcv = rnd.g_mat.T @ cv_full, cv_full.T @ rnd.res_v, cv_full.T @ cv_full
    return proj, ctc, ctr, gv, cv_res, cvcv, cv_full

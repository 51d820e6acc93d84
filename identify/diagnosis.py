"""Close the loop: find in the residual the effect the model lacks, add it, refit, repeat.

The base model is the rigid body (eq. 18) with the robot file's declared effects. Every
entry of the catalogue becomes candidate regressor columns on a joint (or the arm):

- linear in its parameters: viscous (``qd``), Coulomb (``sign qd``), offset (``1``), rotor
  inertia (``qdd``), spring (``q``, with an offset);
- nonlinear in one parameter, searched on a grid and linear given it: Stribeck friction
  (``sign(qd) exp(-(qd/v_s)^2)`` over ``v_s``), cogging (``sin, cos(2 pi q / P)`` over the
  period ``P``, an integer number of periods per turn from 2 to 120);
- linearised about the current fit: a torque-constant error (the joint's predicted torque:
  the measured torque is the true one over the gain), a delay between current and position
  (the derivative of the prediction when joint j's motion is shifted in time) and a tilt
  of gravity (the derivative of the prediction when gravity turns about base x or y; the
  parameters the base set leaves out come from the modeled values).

A round scores every candidate by the held-out error of the refitted model: rows are
whitened by each joint's noise level, the candidate's columns are projected off the
current model (Frisch-Waugh), the refit is solved on the even tenths of the identification
data and its error measured on the odd tenths (held-out blocks; the validation data are
kept for measuring before and after, never for choosing). The best candidate is added if it (a) cuts the
held-out residual power by at least ``min_gain`` (a penalty every added parameter must
pay) and (b) passes an F-test on the identification data at ``alpha``. Then refit and
repeat, until nothing passes. A candidate whose columns lie in the span of the model is
absorbed (rotor inertia of a first joint with a vertical axis joins ``Izz1``), and is
reported as such. When a look-alike (Coulomb/Stribeck, torque gain/rotor inertia,
delay/viscous) explains nearly as much, both are named with the experiment that would
separate them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import stats

from .dynamics import regressor
from .identification import declared_effects, stacked_regressor, structural_base
from .metrics import masked_summary, summary
from .preprocess import Prepared
from .robot import Robot
from .spatial import Array

LOOKALIKES = {
    "coulomb_friction": "stribeck_friction",
    "stribeck_friction": "coulomb_friction",
    "torque_gain": "rotor_inertia",
    "rotor_inertia": "torque_gain",
    "time_delay": "viscous_friction",
    "viscous_friction": "time_delay",
    "torque_offset": "spring",
    "spring": "torque_offset",
}
SEPARATE = {
    frozenset(("coulomb_friction", "stribeck_friction")): "slow constant-velocity moves of joint {j} at several speeds "
    "between 0.01 and 0.5 rad/s: Stribeck friction falls with speed, Coulomb friction does not",
    frozenset(("torque_gain", "rotor_inertia")): "hold joint {j} still at poses with different gravity load, or move it "
    "with and without a known payload: a torque-constant error scales the static torque, rotor inertia adds none at rest",
    frozenset(("time_delay", "viscous_friction")): "excite joint {j} at two frequencies with the same velocity amplitude: "
    "a delay's error grows with frequency, viscous friction depends on velocity alone",
    frozenset(("torque_offset", "spring")): "hold joint {j} still at several positions across its whole range (with the "
    "others fixed): a spring's torque changes with position, an offset does not; over a short range gravity absorbs a spring",
}
DISSIPATIVE = ("viscous_friction", "coulomb_friction", "stribeck_friction", "rotor_inertia")  # last parameter > 0
STRIBECK_VELOCITIES = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5)


@dataclass(frozen=True)
class DiagnoseOptions:
    min_gain: float = 0.10  # least fraction of the held-out residual power a finding must remove
    alpha: float = 1e-6  # F-test significance on the identification data
    min_error_drop: float = 0.05  # ... and the held-out relative error must fall by this fraction
    per_parameter: float = 0.005  # penalty per added parameter, as a fraction of the residual power
    max_findings: int = 12
    max_cogging_per_turn: int = 120
    # a joint's equation is left out while it moves slower than this (rad/s or m/s): at rest
    # its friction is anything up to the breakaway force, which no model of qd predicts
    min_speed: float = 0.02
    # ... and while it is within this time of a velocity reversal (|qd| < |qdd| t): a filtered
    # torque smooths the step of Coulomb friction over the filter's span, sign(qd) does not
    reversal_margin_s: float = 0.025


@dataclass
class _Data:
    """One data set stacked sample by sample: rows ``k N + j`` are joint j of sample k."""

    q: Array
    qd: Array
    qdd: Array
    tau: Array
    period: float
    t: Array | None = None

    @property
    def n_joints(self) -> int:
        return int(self.q.shape[1])

    @property
    def y(self) -> Array:
        return self.tau.reshape(-1)

    def on_joint(self, j: int, columns: Array) -> Array:
        """(rows, k) with ``columns`` (n, k) in joint j's rows and zeros elsewhere."""
        out = np.zeros((self.q.shape[0] * self.n_joints, columns.shape[1]))
        out[j :: self.n_joints] = columns
        return out

    def shifted(self, j: int, steps: int) -> _Data:
        """Joint j's motion ``steps`` samples later (edges repeated)."""
        def shift(x: Array) -> Array:
            x = x.copy()
            x[:, j] = np.roll(x[:, j], -steps)
            if steps > 0:
                x[-steps:, j] = x[-steps - 1, j]
            elif steps < 0:
                x[:-steps, j] = x[-steps, j]
            return x
        return _Data(shift(self.q), shift(self.qd), shift(self.qdd), self.tau, self.period, self.t)


def _stack(prepared: list[Prepared]) -> _Data:
    """The equations' samples: kinematics and torque through each segment's parallel filter
    (low-pass, edges, decimation), so that torque and motion stay aligned."""
    segs = [s for p in prepared for s in p.segments]
    filt = segs[0].parallel
    period = filt.period_s * filt.decimation
    q, qd, qdd, tau = (np.concatenate([s.parallel.apply(getattr(s, k)) for s in segs]) for k in ("q", "qd", "qdd", "tau"))
    t = np.concatenate([s.t[s.parallel.kept(s.n_samples)] for s in segs])
    return _Data(q, qd, qdd, tau, period, t)


def _as_measured(prepared: list[Prepared], tau_model: Array) -> Array:
    """:meth:`Stamps.as_measured` segment by segment over stacked stamps ((n N,) or (n, N))."""
    st = [s.at_stamps for p in prepared for s in p.segments]
    nj = st[0].q.shape[1]
    flat = tau_model.reshape(-1, nj)
    bounds = np.cumsum([0] + [s.t.size for s in st])
    out = np.concatenate([s.as_measured(flat[a:b]) for s, a, b in zip(st, bounds[:-1], bounds[1:])])
    return out.reshape(tau_model.shape)


def _stack_stamps(prepared: list[Prepared]) -> _Data:
    """Every input sample the segments cover, at its own stamp, with the raw torque."""
    st = [s.at_stamps for p in prepared for s in p.segments]
    q, qd, qdd, tau, t = (np.concatenate([getattr(s, k) for s in st]) for k in ("q", "qd", "qdd", "tau", "t"))
    period = float(np.median(np.diff(st[0].t))) if st[0].t.size > 1 else 1.0
    return _Data(q, qd, qdd, tau, period, t)


@dataclass(frozen=True)
class Candidate:
    """Columns of one effect. ``block`` gives (n, k) columns living in joint ``joint``'s rows
    only (the cheap, common case); otherwise ``full`` gives (rows, k) for every row."""

    effect: str
    joint: int | None  # 0-based, None for the arm
    setting: tuple[tuple[str, float], ...]
    labels: tuple[str, ...]
    block: Callable[[_Data], Array] | None = None
    full: Callable[[_Data], Array] | None = None

    def columns(self, d: _Data) -> Array:
        """(rows, k), unweighted."""
        if self.block is not None:
            assert self.joint is not None
            return d.on_joint(self.joint, self.block(d))
        assert self.full is not None
        return self.full(d)


@dataclass
class Finding:
    effect: str
    joint: int | None
    parameters: dict[str, float]
    explained: float  # fraction of the held-out residual power this finding removed
    error_before: float
    error_after: float
    lookalike: str | None = None
    separate_by: str | None = None

    def sentence(self) -> str:
        where = f"joint {self.joint + 1}" if self.joint is not None else "arm"
        signature = {
            "coulomb_friction": "residual follows sign(qd)", "viscous_friction": "residual follows qd",
            "stribeck_friction": "residual peaks at low speed with sign(qd)", "torque_offset": "residual has a constant offset",
            "rotor_inertia": "residual follows qdd", "torque_gain": "residual is proportional to the torque",
            "time_delay": "residual follows the rate of change of the torque", "cogging": "residual is periodic in position",
            "spring": "residual grows linearly with position", "gravity_tilt": "residual follows a gravity load about a tilted axis",
        }[self.effect]
        params = ", ".join(f"{k} {v:.4g}" for k, v in self.parameters.items())
        text = f"{where}: {signature}: {self.effect.replace('_', ' ')} {params}; held-out error (identification data) {100 * self.error_before:.2f} % -> {100 * self.error_after:.2f} %"
        if self.lookalike:
            text += f" (cannot be told apart from {self.lookalike.replace('_', ' ')} on this data; to separate them: {self.separate_by})"
        return text

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"effect": self.effect, "joint": None if self.joint is None else self.joint + 1,
                               "parameters": self.parameters, "explained": self.explained}
        if self.lookalike:
            out["lookalike"] = {"effect": self.lookalike, "separate_by": self.separate_by}
        return out


@dataclass
class Diagnosis:
    found: list[Finding]
    absorbed: list[dict[str, Any]]
    before: dict[str, Any]
    after: dict[str, Any]
    base_effects: list[str]
    rounds: list[list[tuple[str, float]]] = field(default_factory=list)
    residual_before: tuple[Array, Array] | None = None  # validation (tau, tau_hat) before
    residual_after: tuple[Array, Array] | None = None
    validation_motion: tuple[Array, Array, Array, Array] | None = None  # t, q, qd, qdd
    used: Array | None = None  # (n, N) validation equations the scores used
    predictions: tuple[Array, Array, Array] | None = None  # t, raw tau, final model's tau_hat at the validation stamps
    noise_floor: dict[str, Any] | None = None

    def to_json(self) -> dict[str, Any]:
        return {"found": [f.to_json() for f in self.found], "absorbed": self.absorbed, "declared": self.base_effects,
                "before": self.before, "after": self.after, "noise_floor": self.noise_floor,
                "chosen_on": "the identification data: fitted on its even tenths, scored on its odd tenths",
                "measured_on": "the validation data (before and after), at every sample's own stamp against the raw torque"}


def _phi_hat(robot: Robot, base: Any, beta_base: Array, n_cols: int) -> Array:
    """Standard parameters that reproduce the base estimate and otherwise stay modeled (min-norm)."""
    p = robot.n_parameters
    phi0 = robot.modeled_parameters()
    b = np.array([base.base_values(np.eye(n_cols)[k]) for k in range(p)]).T  # (n_base, p)
    return phi0 + np.linalg.lstsq(b, beta_base - b @ phi0, rcond=None)[0]


def _candidates(robot: Robot, data: _Data, present: set[tuple[str, int | None]], ctx: dict[str, Any], opts: DiagnoseOptions) -> list[Candidate]:
    out: list[Candidate] = []
    nj = robot.n_joints
    for j in range(nj):
        revolute = robot.joints[j].revolute

        def lin(name: str, fn: Callable[[_Data], Array], labels: tuple[str, ...], j: int = j, setting: tuple = ()) -> None:  # type: ignore[type-arg]
            if (name, j) not in present:
                out.append(Candidate(name, j, setting, labels, block=fn))

        lin("viscous_friction", lambda d, j=j: d.qd[:, j : j + 1], ("fv",))  # type: ignore[misc]
        lin("coulomb_friction", lambda d, j=j: np.sign(d.qd[:, j : j + 1]), ("fc",))  # type: ignore[misc]
        lin("torque_offset", lambda d: np.ones((d.q.shape[0], 1)), ("offset",))
        lin("rotor_inertia", lambda d, j=j: d.qdd[:, j : j + 1], ("ia",))  # type: ignore[misc]
        with_offset = ("torque_offset", j) not in present
        lin("spring", (lambda d, j=j: np.column_stack([d.q[:, j], np.ones(d.q.shape[0])])) if with_offset else (lambda d, j=j: d.q[:, j : j + 1]),  # type: ignore[misc]
            ("stiffness", "offset") if with_offset else ("stiffness",))
        with_coulomb = ("coulomb_friction", j) not in present
        for vs in STRIBECK_VELOCITIES:
            def strib(d: _Data, j: int = j, vs: float = vs, wc: bool = with_coulomb) -> Array:
                s = np.sign(d.qd[:, j])
                cols = [s * np.exp(-((d.qd[:, j] / vs) ** 2))]
                return np.column_stack(([s] if wc else []) + cols)
            lin("stribeck_friction", strib, (("fc",) if with_coulomb else ()) + ("fs",), setting=(("velocity", vs),))
        if revolute:
            span = float(np.ptp(data.q[:, j]))
            for k in range(2, opts.max_cogging_per_turn + 1):
                period = 2.0 * np.pi / k
                if span < 2.0 * period:
                    continue
                lin("cogging", lambda d, j=j, p=period: np.column_stack([np.sin(2 * np.pi * d.q[:, j] / p), np.cos(2 * np.pi * d.q[:, j] / p)]),  # type: ignore[misc]
                    ("a", "b"), setting=(("period_rad", period),))
        if ("torque_gain", j) not in present:
            out.append(Candidate("torque_gain", j, (), ("c",), block=lambda d, j=j: ctx["predict"](d)[:, j : j + 1]))  # type: ignore[misc]
        if ("time_delay", j) not in present:
            out.append(Candidate("time_delay", j, (), ("delay_s",), full=lambda d, j=j: ((ctx["predict_smooth"](d.shifted(j, 1)) - ctx["predict_smooth"](d.shifted(j, -1))) / (2 * d.period)).reshape(-1, 1)))  # type: ignore[misc]
    # friction on every joint (what a real arm's residual mostly is) as one arm-wide candidate:
    # judged against the whole arm, not N separate one-joint gains
    bare = [j for j in range(nj) if not {("coulomb_friction", j), ("viscous_friction", j), ("torque_offset", j)} & present]
    if len(bare) >= 2 and ("coulomb_friction", None) not in present:
        def friction(d: _Data, joints: list[int] = bare) -> Array:
            cols = np.zeros((d.q.shape[0] * nj, 3 * len(joints)))
            for k, j in enumerate(joints):
                cols[j::nj, 3 * k : 3 * k + 3] = np.column_stack([np.sign(d.qd[:, j]), d.qd[:, j], np.ones(d.q.shape[0])])
            return cols
        labels = tuple(f"{name}{j + 1}" for j in bare for name in ("fc", "fv", "offset"))
        out.append(Candidate("coulomb_friction", None, (), labels, full=friction))
    if ("gravity_tilt", None) not in present:
        def tilt(d: _Data) -> Array:
            g = np.asarray(robot.gravity, float)
            cols = []
            for axis in np.eye(3)[:2]:
                tilted = replace(robot, gravity=np.cross(axis, g))
                z = np.zeros_like(d.q)
                cols.append((regressor(tilted, d.q, z, z) @ ctx["phi"]).reshape(-1))
            return np.column_stack(cols)
        out.append(Candidate("gravity_tilt", None, (), ("tilt_x_rad", "tilt_y_rad"), full=tilt))
    return out


def _parameters(c: Candidate, gamma: Array) -> dict[str, float]:
    g = [float(x) for x in gamma]
    setting = dict(c.setting)
    if c.effect == "torque_gain":
        return {"gain": 1.0 / (1.0 + g[0])}
    if c.effect == "cogging":
        return {"amplitude": float(np.hypot(g[0], g[1])), "period_rad": setting["period_rad"], "phase_rad": float(np.arctan2(g[1], g[0]))}
    if c.effect == "spring":
        out = {"stiffness": g[0]}
        if len(g) > 1 and g[0] != 0:
            out["rest_position"] = -g[1] / g[0]
        return out
    return {**dict(zip(c.labels, g)), **setting}


def diagnose(robot: Robot, experiments: list[Prepared], validation: list[Prepared], options: DiagnoseOptions | None = None) -> Diagnosis:
    """Find, add and report the undeclared effects (module docstring).

    Findings are chosen on held-out blocks of the identification data (every other tenth of
    it, fitted on the rest); ``validation`` only measures the errors before and after, so
    the figures reported are not the ones the search optimised."""
    opts = options or DiagnoseOptions()
    ident_all, valid = _stack(experiments), _stack(validation)
    ident, held = _blocks(ident_all)
    stamps = _stack_stamps(validation)
    nj = robot.n_joints
    effects = declared_effects(robot)
    base = structural_base(robot, effects)
    n_cols = robot.n_parameters + sum(len(e.parameter_names) for e in effects)

    def base_columns(d: _Data) -> Array:
        return stacked_regressor(robot, effects, d.q, d.qd, d.qdd)[:, base.independent]

    wi, wv = base_columns(ident), base_columns(held)
    yi, yv = ident.y, held.y
    # per-joint noise levels from the base fit whiten the rows (as weighted least squares)
    moving = _moving(ident, opts).reshape(-1)
    beta0 = np.linalg.lstsq(wi[moving], yi[moving], rcond=None)[0]
    res0 = np.where(moving, yi - wi @ beta0, np.nan).reshape(-1, nj)
    sigma = np.sqrt(np.nanmean(res0**2, axis=0))
    sigma = np.maximum(np.nan_to_num(sigma, nan=1.0), 1e-9 * max(1.0, float(np.nanmax(np.abs(res0)))))
    used_i, used_v = _moving(ident, opts), _moving(held, opts)
    wt_i = (np.tile(1.0 / sigma, yi.size // nj) * used_i.reshape(-1))
    wt_v = (np.tile(1.0 / sigma, yv.size // nj) * used_v.reshape(-1))
    n_used = int(used_i.sum())
    extra_i, extra_v = np.zeros((yi.size, 0)), np.zeros((yv.size, 0))
    extra_s = np.zeros((stamps.y.size, 0))
    ws = base_columns(stamps)
    before_stamps = ws @ beta0
    present: set[tuple[str, int | None]] = {(e.effect, e.joint) for e in effects}
    found: list[Finding] = []
    absorbed: list[dict[str, Any]] = []
    absorbed_keys: set[tuple[str, int | None]] = set()
    ctx: dict[str, Any] = {}
    before_pred = wv @ beta0
    rounds = []
    chosen: list[Candidate] = []
    beta = beta0
    for _ in range(opts.max_findings):
        a_i = np.column_stack([wi, extra_i]) * wt_i[:, None]
        q_mat, r_mat = np.linalg.qr(a_i)
        yw = yi * wt_i
        beta = np.linalg.solve(r_mat, q_mat.T @ yw)
        r = yw - q_mat @ (q_mat.T @ yw)
        rss = float(r @ r)
        a_v = np.column_stack([wv, extra_v])
        res_v = (yv - a_v @ beta) * wt_v
        rss_v = float(res_v @ res_v)
        if not found:
            before_pred = a_v @ beta  # the base model, fitted as every later model is
            before_stamps = ws @ beta
        p_base = wi.shape[1]
        ctx["predict"] = lambda d, b=beta[:p_base]: (base_columns(d) @ b).reshape(-1, nj)
        # the delay's derivative leaves out Coulomb friction: a step in sign(qd) shifted by a
        # sample is a spike at every reversal, which would fit friction's misfit near rest
        smooth = beta[:p_base] * np.array([not base.names[c].startswith("fc") for c in base.independent])
        ctx["predict_smooth"] = lambda d, b=smooth: (base_columns(d) @ b).reshape(-1, nj)
        ctx["phi"] = _phi_hat(robot, base, beta[:p_base], n_cols)
        # Frisch-Waugh on the whitened system A = QR with residual r (r is orthogonal to Q):
        # for columns C, P = Q^T C, gamma = (C^T C - P^T P)^-1 C^T r, the refit's beta is
        # beta - R^-1 P gamma, and the held-out residual is res_v + G P gamma - Cv gamma with
        # G = A_v R^-1. Only a candidate's own rows enter, so a round costs little.
        g_mat = np.linalg.solve(r_mat.T, (a_v * wt_v[:, None]).T).T
        h_vec, h_mat = g_mat.T @ res_v, g_mat.T @ g_mat
        scored = []
        for c in _candidates(robot, ident, present | absorbed_keys, ctx, opts):
            if c.block is not None:
                j = c.joint
                assert j is not None
                bi = c.block(ident) * wt_i[j :: nj, None]
                bv = c.block(held) * wt_v[j :: nj, None]
                proj = q_mat[j::nj].T @ bi
                ctc, ctr = bi.T @ bi, bi.T @ r[j::nj]
                gv, cv_res, cvcv = g_mat[j::nj].T @ bv, bv.T @ res_v[j::nj], bv.T @ bv
            else:
                ci_full = c.full(ident) * wt_i[:, None]  # type: ignore[misc]
                cv_full = c.full(held) * wt_v[:, None]  # type: ignore[misc]
                bi = ci_full
                proj = q_mat.T @ ci_full
                ctc, ctr = ci_full.T @ ci_full, ci_full.T @ r
                gv, cv_res, cvcv = g_mat.T @ cv_full, cv_full.T @ res_v, cv_full.T @ cv_full
            if not np.isfinite(ctc).all() or not np.any(np.diag(ctc) > 0):
                continue
            schur = ctc - proj.T @ proj
            if np.trace(schur) <= 1e-12 * np.trace(ctc):
                key = (c.effect, c.joint)
                if key not in absorbed_keys:
                    coef = np.linalg.lstsq(r_mat, proj, rcond=None)[0]
                    exprs = base.expressions()
                    top = int(np.argmax(np.abs(coef[:, 0])))
                    absorbed.append({"effect": c.effect, "joint": None if c.joint is None else c.joint + 1,
                                     "into": exprs[top] if top < len(exprs) else "an effect found earlier"})
                    absorbed_keys.add(key)
                continue
            try:
                gamma = np.linalg.solve(schur, ctr)
            except np.linalg.LinAlgError:
                continue
            if c.effect in DISSIPATIVE and (float(gamma[-1]) <= 0.0 if c.joint is not None else float(np.median(gamma[0::3])) <= 0.0):
                continue  # friction that pushes the joint along, or a negative inertia: not physical
            if c.effect == "time_delay" and abs(float(gamma[0])) < 0.5 * ident.period:
                # shorter than half a sample period: within the timing uncertainty of the
                # samples themselves (zero-order hold of the current, current loop, filters)
                continue
            rss1 = rss - float(ctr @ gamma)
            u = proj @ gamma
            rss_v1 = float(rss_v + 2 * h_vec @ u + u @ h_mat @ u - 2 * cv_res @ gamma - 2 * u @ gv @ gamma + gamma @ cvcv @ gamma)
            k = len(gamma)
            dof = n_used - a_i.shape[1] - k
            f_stat = ((rss - rss1) / k) / max(rss1 / dof, 1e-300)
            p_value = float(stats.f.sf(f_stat, k, dof))
            scored.append((rss_v1, p_value, c, gamma, proj))
        if not scored:
            break
        # the best by held-out residual power, each added parameter paying its penalty
        scored.sort(key=lambda s: s[0] / rss_v + opts.per_parameter * len(s[3]))
        rounds.append([(f"{s[2].effect}@{s[2].joint}", 1.0 - s[0] / rss_v) for s in scored[:5]])
        rss_v1, p_value, best, gamma, proj = scored[0]
        if rss_v1 > (1.0 - opts.min_gain) * rss_v or p_value > opts.alpha:
            break
        ci, cv = best.columns(ident), best.columns(held)
        beta_c = beta - np.linalg.solve(r_mat, proj @ gamma)
        pred_before, pred_after = a_v @ beta, a_v @ beta_c + cv @ gamma
        err_before = _rel(yv * (wt_v > 0), pred_before * (wt_v > 0))
        err_after = _rel(yv * (wt_v > 0), pred_after * (wt_v > 0))
        # a joint's effect is judged by its joint's error (on 6-7 joints a perfect fix of one
        # joint moves the whole arm's error by about 1/N); one that acts on every joint's row
        # (a delay, a tilt) by the whitened power alone (min_gain), each joint at its own noise
        rows = (wt_v > 0) & (np.arange(yv.size) % nj == best.joint)
        if best.block is not None and _rel(yv * rows, pred_after * rows) > (1.0 - opts.min_error_drop) * _rel(yv * rows, pred_before * rows):
            break  # it whitens the residual but does not move the error anyone reads
        finding = Finding(best.effect, best.joint, _parameters(best, gamma), 1.0 - rss_v1 / rss_v, err_before, err_after)
        alt_name = LOOKALIKES.get(best.effect)
        if alt_name:
            alt = next((s for s in scored if s[2].effect == alt_name and s[2].joint == best.joint), None)
            if alt is not None and (rss_v - alt[0]) >= 0.9 * (rss_v - rss_v1):
                finding.lookalike = alt_name
                finding.separate_by = SEPARATE[frozenset((best.effect, alt_name))].format(j=(best.joint or 0) + 1)
        found.append(finding)
        chosen.append(best)
        present.add((best.effect, best.joint))
        if best.joint is None and best.effect == "coulomb_friction":  # friction on every joint it covers
            present |= {(e, int(label[len(p) :]) - 1) for label in best.labels
                        for e, p in (("coulomb_friction", "fc"), ("viscous_friction", "fv"), ("torque_offset", "offset")) if label.startswith(p)}
        extra_i = np.column_stack([extra_i, ci])
        extra_v = np.column_stack([extra_v, cv])
        extra_s = np.column_stack([extra_s, best.columns(stamps)])
    found, chosen = _merge_offset_into_spring(found, chosen)
    # the final fits on all the identification data: the declared model, and with every finding
    wa = base_columns(ident_all)
    used_a = _moving(ident_all, opts)
    wt_a = np.tile(1.0 / sigma, ident_all.y.size // nj) * used_a.reshape(-1)
    beta0 = np.linalg.lstsq(wa * wt_a[:, None], ident_all.y * wt_a, rcond=None)[0]
    extra_a = np.column_stack([wa[:, :0]] + [c.columns(ident_all) for c in chosen])
    a_a = np.column_stack([wa, extra_a]) * wt_a[:, None]
    beta = np.linalg.lstsq(a_a, ident_all.y * wt_a, rcond=None)[0]
    k0 = wa.shape[1]
    values: dict[tuple[str, int | None], Array] = {}
    for c in chosen:
        width = len(c.labels)
        values[(c.effect, c.joint)] = beta[k0 : k0 + width]
        k0 += width
    by_key = {(c.effect, c.joint): c for c in chosen}
    for f in found:
        c = by_key[(f.effect, f.joint)]
        gamma = values[(c.effect, c.joint)]
        if f.effect == "spring" and ("torque_offset", c.joint) in values and len(gamma) == 1:
            gamma = np.append(gamma, values[("torque_offset", c.joint)])
        f.parameters = _parameters(c, gamma)
    wv = base_columns(valid)
    used_v = _moving(valid, opts)
    before_pred = wv @ beta0
    before_stamps = _as_measured(validation, ws @ beta0)
    after_pred = np.column_stack([wv] + [c.columns(valid) for c in chosen]) @ beta if found else before_pred
    after_stamps = _as_measured(validation, np.column_stack([ws, extra_s]) @ beta) if found else before_stamps
    # before and after as anyone can check them: the model at every validation sample, against the raw torque
    before = summary(stamps.tau, before_stamps.reshape(-1, nj))
    after = summary(stamps.tau, after_stamps.reshape(-1, nj))
    before["moving_equations"] = masked_summary(valid.tau, before_pred.reshape(-1, nj), used_v)
    after["moving_equations"] = masked_summary(valid.tau, after_pred.reshape(-1, nj), used_v)
    noise = _noise_floor(validation)
    t_v = valid.t if valid.t is not None else np.arange(valid.q.shape[0]) * valid.period
    return Diagnosis(found, absorbed, before, after, [f"{e.effect}@{e.joint + 1}" for e in effects], rounds,
                     (valid.tau, before_pred.reshape(-1, nj)), (valid.tau, after_pred.reshape(-1, nj)), (t_v, valid.q, valid.qd, valid.qdd), used_v,
                     (np.asarray(stamps.t), stamps.tau, after_stamps.reshape(-1, nj)), noise)


def _blocks(d: _Data, parts: int = 10) -> tuple[_Data, _Data]:
    """The identification data split into every other tenth: the even tenths to fit on, the
    odd ones held out to choose by (neighbouring samples are not independent, so whole
    blocks, each spanning the trajectory's phases alike)."""
    n = d.q.shape[0]
    block = np.minimum(np.arange(n) * parts // max(n, 1), parts - 1)
    held = block % 2 == 1

    def take(mask: Array) -> _Data:
        return _Data(d.q[mask], d.qd[mask], d.qdd[mask], d.tau[mask], d.period, None if d.t is None else d.t[mask])

    return take(~held), take(held)


def _noise_floor(validation: list[Prepared]) -> dict[str, Any]:
    """The validation torque's noise, estimated as what a low-pass at the chosen cut-off
    removes (or, without one, at a tenth of the Nyquist frequency), as a relative error."""
    from .filtering import ParallelFilter, noise_level

    num = den = 0.0
    for p in validation:
        for seg in p.segments:
            filt = seg.parallel
            if filt.cutoff_hz is None:
                filt = ParallelFilter(filt.period_s, 0.05 / filt.period_s)
            sd = noise_level(seg.tau, filt)
            num += float(np.sum(sd**2)) * seg.n_samples
            den += float(np.sum(seg.tau**2))
    value = float(np.sqrt(num / den)) if den > 0 else None
    return {"relative_error": value, "how": "the validation torque's content above the low-pass cut-off (white noise spreads "
            "over the whole band; what lies below the cut-off is not counted), over its norm"}


def _merge_offset_into_spring(found: list[Finding], chosen: list[Candidate]) -> tuple[list[Finding], list[Candidate]]:
    """An offset found first and a spring on the same joint later are one spring off zero."""
    drop = set()
    for k, f in enumerate(found):
        if f.effect != "spring":
            continue
        for m, g in enumerate(found[:k]):
            if g.effect == "torque_offset" and g.joint == f.joint:
                f.error_before, f.explained = g.error_before, 1.0 - (1.0 - g.explained) * (1.0 - f.explained)
                drop.add(m)
    keep = [k for k in range(len(found)) if k not in drop]
    # the offset's columns stay in the model (the spring's parameters include them)
    return [found[k] for k in keep], chosen


def _moving(d: _Data, opts: DiagnoseOptions) -> Array:
    """(n, N): the equations whose joint moves clear of rest and of a reversal."""
    return np.abs(d.qd) >= np.maximum(opts.min_speed, np.abs(d.qdd) * opts.reversal_margin_s)


def _rel(y: Array, y_hat: Array) -> float:
    return float(np.linalg.norm(y - y_hat)) / max(float(np.linalg.norm(y)), 1e-300)



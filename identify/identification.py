"""Identification from recordings: regressor, base parameters, least squares, metrics.

``identify`` is what ``armid identify`` runs: the stacked regressor of eq. (18) with the
declared effects as extra columns, the structural base parameters (5.4), an excitation
check (5.2), weighted least squares, and the fit and held-out errors (INTERFACES.md
metrics).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .dynamics import regressor
from .effects import LOAD_DEPENDENT, PROFILED, SETTINGS, LinearEffect, LoadFriction, effect_columns, linear_effect, load_friction
from .equations import advanced, column_count, equation_column, equation_motion, measured_torque, regression_system, segment_loads
from .errors import IdentificationError, PoorExcitationWarning
from .estimation import (
    ColumnTrials,
    JointFactors,
    LeastSquares,
    batch_means_covariance,
    bounded_quadratic,
    correlation_length,
    effective_batches,
    factor_columns,
    solve_factors,
    with_prior,
)
from .identifiability import UNIQUE, BaseParameters, Excitation, base_parameters, excitation, identified_ranges, preferred_order
from .metrics import summary
from .model_errors import Refit, measure_errors
from .preprocess import Prepared, Segment
from .prior import RELATIVE_STD, Prior, base_prior, link_scales, scaled, widened
from .robot import Robot
from .spatial import Array


@dataclass(frozen=True)
class IdentifyOptions:
    weighting: str = "wls"
    max_condition: float = 1e3
    seed: int = 0
    # "batch_means": robust to correlated residuals (filtered 2 ms data); "white": s^2 (W^T W)^-1
    covariance: str = "batch_means"
    # leave out a joint's equation while it is slower than 0.02 rad/s or within 25 ms of a
    # velocity reversal (|qd| < |qdd| 0.025 s): sign(qd) is wrong there (pre-sliding, and a
    # filtered torque smooths the Coulomb step), as in identify.single_link and diagnosis
    exclude_reversals: bool = False
    # a drive's torque gain and a sensor's delay, per joint, as the diagnosis finds them:
    # joint j measures ``torque_scale[j] * tau_j(t - delay_s[j])`` of the model's torque, and
    # reports its position ``motion_delay_s[j]`` late (q_j(t - d) at t)
    torque_scale: tuple[float, ...] | None = None
    delay_s: tuple[float, ...] | None = None
    motion_delay_s: tuple[float, ...] | None = None
    # "modeled": the robot file's modeled values as a prior (identify.prior) for what the
    # data do not excite; "none": least squares alone
    prior: str = "modeled"
    # the prior's widening (identify.prior.widened) fixed instead of estimated on these data:
    # the diagnosis fits its findings with the declared model's, so that a finding is not
    # paid for by a prior that lost its weight (None: estimated, empirical Bayes)
    prior_widening: float | None = None
    # a load-dependent friction's load parameters (10 per link) fixed: one fit with that load
    # instead of the fixed-point passes (a refit close to a fit already made: the diagnosis)
    load_parameters: tuple[float, ...] | None = None
    # effect parameters held >= 0 in the fit itself (bounded least squares, the prior's penalty
    # included), by column name ("fv3", "ks2"): the diagnosis's findings, whose physics bounds
    # them (friction dissipative, inertia and a passive spring's stiffness positive). Empty for
    # `armid identify`: a declared effect is fitted as declared
    nonnegative: tuple[str, ...] = ()
    # the errors at every input sample (``fit``, ``validation``: the model against the raw
    # torque) measured; False for a fit wanted for its parameters alone (a load-dependent
    # friction's first passes, the diagnosis's trial fits): its ``fit`` is then the filtered
    # equations', and a prediction at every stamp (a regressor of the whole log) is saved
    stamp_errors: bool = True
    # the ten-fold held-out error on the identification data measured with them (ten refits:
    # a quarter of the fleet's time per recording); False where only the validation error is
    # wanted (the fleet's cross-validation of each half on the other)
    held_out_error: bool = True


PRIORS = ("modeled", "none")

SEARCH_EQUATIONS = 10_000
"""Equations per joint the grid search of a declared effect's setting scores its tries on."""

STAMPS_KEPT_BYTES = 32 * 2**20
"""Predictions at the stamps a result keeps (:meth:`IdentificationResult.predict_stamps`):
a validation log's (12,500 samples of 6 joints: 1.8 MB), not a 20-minute 1 kHz log's."""

PREDICT_BLOCK = 8192
"""Samples whose regressor a prediction holds at once (7 joints: about 40 MB)."""


def declared_effects(robot: Robot, load_parameters: Array | None = None) -> list[LinearEffect]:
    """The robot file's effects as regressor columns (``joint: null`` means every joint).
    A load-dependent friction's load is the rigid-body torque of ``load_parameters`` (default
    :func:`nominal_load`); its sign's smoothing is the same joint's declared Coulomb velocity
    unless it declares its own, and follows the search of an undeclared one."""
    phi = nominal_load(robot) if load_parameters is None else np.asarray(load_parameters, float)
    coulomb = {j: float(e.options["velocity"]) for e in robot.effects if e.effect == "coulomb_friction" and "velocity" in e.options
               for j in (range(robot.n_joints) if e.joint is None else [e.joint - 1])}
    out: list[LinearEffect] = []
    for eff in robot.effects:
        if eff.effect in PROFILED:
            continue  # not a column: fitted by profiling (_profile_gains)
        joints = range(robot.n_joints) if eff.joint is None else [eff.joint - 1]
        if eff.effect in LOAD_DEPENDENT:
            own = "velocity" in eff.options
            out += [load_friction(robot, j, phi, float(eff.options["velocity"]) if own else coulomb.get(j, 0.0), follows_coulomb=not own)
                    for j in joints]
            continue
        setting = {k: float(v) for k, v in eff.options.items() if k in ("velocity", "period_rad")}
        out += [linear_effect(eff.effect, j, **setting) for j in joints]
    return out


STAND_IN_LINK = np.array([1.0, 0.0, 0.0, 0.0, 0.01, 0.0, 0.0, 0.01, 0.0, 0.01])
"""A 1 kg link with its mass at its frame's origin: the load of a link the robot file does not
model, before any estimate (it only gives the column its structure)."""


def nominal_load(robot: Robot) -> Array:
    """The load parameters before any estimate: the robot file's modeled values, a stand-in
    link where it has none (:data:`STAND_IN_LINK`). Used where only the column's structure
    matters (structural base parameters, excitation design); an identification replaces it
    by its own estimate (:func:`identify`)."""
    phi = robot.modeled_parameters()
    for i in range(robot.n_joints):
        if np.isnan(phi[10 * i : 10 * i + 10]).any():
            phi[10 * i : 10 * i + 10] = STAND_IN_LINK
    return phi


def declared_gains(robot: Robot) -> list[int]:
    """0-based joints whose drive gain the robot file declares (``torque_gain``)."""
    return sorted({j for e in robot.effects if e.effect in PROFILED
                   for j in (range(robot.n_joints) if e.joint is None else [e.joint - 1])})


def _profile_gains(factors: JointFactors, joints: list[int], weighting: str) -> Array:
    """Per joint, the gain ``s`` with which joint j measures ``s`` times the model's torque,
    for the joints in ``joints`` (1 elsewhere): the weighted least-squares fit profiled over
    the gains (variable projection: the linear parameters eliminated for each try). Scaling
    ``W_j`` by ``s`` scales the columns of its R factor, so a try costs one small QR and
    never touches the data. Weights are the joints' noise levels of the fit without gains."""
    from scipy import optimize  # here: its import is a tenth of a whole identification's time
    p = factors.n_parameters
    weights = np.ones(len(factors.r))
    if weighting == "wls":
        sigma = solve_factors(factors, weighting).joint_sigma
        weights = 1.0 / np.maximum(sigma, max(float(sigma.max()) * 1e-6, 1e-300))

    def rss(log_s: Array) -> float:
        s = np.ones(len(factors.r))
        s[joints] = np.exp(log_s)
        stacked = np.vstack([wt * r * np.append(np.full(p, sj), 1.0) for wt, r, sj in zip(weights, factors.r, s)])
        r_all: Array = np.linalg.qr(stacked, mode="r")  # type: ignore[assignment]
        return float(r_all[p, p] ** 2)

    bounds = [(np.log(0.1), np.log(10.0))] * len(joints)  # beyond: a wrong robot file or wiring, not a gain
    best = optimize.minimize(rss, np.zeros(len(joints)), method="Powell", bounds=bounds, options={"xtol": 1e-8, "ftol": 1e-12})
    out = np.ones(len(factors.r))
    out[joints] = np.exp(best.x)
    return out


def _searched(robot: Robot) -> set[tuple[str, int]]:
    """Declared effects whose fixed parameter the robot file leaves to the data."""
    out = set()
    for eff in robot.effects:
        if eff.effect in SETTINGS and "velocity" not in eff.options:
            joints = range(robot.n_joints) if eff.joint is None else [eff.joint - 1]
            out |= {(eff.effect, j) for j in joints}
    return out


def column_names(robot: Robot, effects: list[LinearEffect]) -> list[str]:
    return robot.parameter_names + [label for e in effects for label in e.labels()]


def random_motion(robot: Robot, n_samples: int, seed: int = 0) -> tuple[Array, Array, Array]:
    """Random configurations within the joint limits, with random velocity and acceleration."""
    rng = np.random.default_rng(seed)
    lo = np.array([j.limits.position[0] if j.limits.position else -np.pi for j in robot.joints])
    hi = np.array([j.limits.position[1] if j.limits.position else np.pi for j in robot.joints])
    q = rng.uniform(lo, hi, (n_samples, robot.n_joints))
    return q, rng.normal(size=q.shape), rng.normal(size=q.shape)


def modeled_torque(robot: Robot, prepared: Prepared, most: int = 5000) -> tuple[Array, Array] | None:
    """The measured torque and the robot file's modeled rigid-body torque at up to ``most``
    evenly spaced samples of a prepared recording (None when it models no inertials): what
    :func:`identify.plausibility.check_against_model` compares."""
    phi = robot.modeled_parameters()
    if np.isnan(phi).any() or not prepared.segments:
        return None
    q, qd, qdd, tau = (np.concatenate([getattr(s, k) for s in prepared.segments]) for k in ("q", "qd", "qdd", "tau"))
    take = np.unique(np.linspace(0, q.shape[0] - 1, min(most, q.shape[0])).astype(int))
    return tau[take], regressor(robot, q[take], qd[take], qdd[take]) @ phi


def base_torque(robot: Robot, effects: list[LinearEffect], independent: Array, beta: Array, q: Array, qd: Array, qdd: Array) -> Array:
    """Torques (n, N) of base parameters ``beta`` (on the regressor's columns ``independent``)
    at each sample of a motion, a block of samples at a time: the regressor of a 20-minute
    log at 1 kHz would take 10 GB whole."""
    coef = np.zeros(column_count(robot, effects))
    coef[independent] = beta  # zero elsewhere: no copy of the columns
    tau = np.empty((q.shape[0], robot.n_joints))
    for a in range(0, q.shape[0], PREDICT_BLOCK):
        b = slice(a, a + PREDICT_BLOCK)
        tau[b] = (stacked_regressor(robot, effects, q[b], qd[b], qdd[b]) @ coef).reshape(-1, robot.n_joints)
    return tau


def stacked_regressor(robot: Robot, effects: list[LinearEffect], q: Array, qd: Array, qdd: Array) -> Array:
    """(n N, 10 N + k) rows of eq. (18) with effect columns, sample by sample."""
    n, nj = np.shape(q)
    m = np.empty((n, nj, column_count(robot, effects)))
    regressor(robot, q, qd, qdd, out=m[:, :, : 10 * nj])
    if effects:
        m[:, :, 10 * nj :] = effect_columns(effects, q, qd, qdd, rigid=m[:, :, : 10 * nj])
    return m.reshape(-1, m.shape[2])


def structural_base(robot: Robot, effects: list[LinearEffect] | None = None, seed: int = 0) -> BaseParameters:
    """Base parameters from the kinematics alone (random motion over the joint ranges)."""
    effects = declared_effects(robot) if effects is None else effects
    names = column_names(robot, effects)
    n_samples = max(60, 4 * len(names))
    w = stacked_regressor(robot, effects, *random_motion(robot, n_samples, seed))
    return base_parameters(w, names, preferred_order(robot.n_joints, len(names) - robot.n_parameters))


@dataclass
class IdentificationResult:
    robot: Robot
    names: list[str]
    effects: list[LinearEffect]
    base: BaseParameters
    estimate: LeastSquares
    excitation: Excitation
    samples: int
    fit: dict[str, Any]
    validation: dict[str, Any] | None = None
    validation_samples: int = 0
    held_out: dict[str, Any] | None = None  # identify.model_errors: each fold predicted by the fit of the other nine
    notes: list[str] = field(default_factory=list)
    filtering: list[dict[str, Any]] = field(default_factory=list)
    # per-joint R factors of [W_j | tau_j] over the base columns: the data's metric for
    # anything fitted after least squares (identify.feasible), without the data
    factors: JointFactors | None = None
    torque_scale: Array | None = None  # IdentifyOptions.torque_scale / delay_s / motion_delay_s, per joint
    delay_s: Array | None = None
    motion_delay_s: Array | None = None
    prior: dict[str, Any] | None = None  # the prior the estimate used (identify.prior), None for least squares alone
    covariance_batches: int | None = None  # the batch-means covariance's batches (a joint test's degrees of freedom)
    # predict_stamps's answers by the segments asked about (held with them: an id is only
    # unique while its object lives); the estimate is fixed once the result is made
    _at_stamps: dict[tuple[int, ...], tuple[list[Segment], tuple[Array, Array, Array]]] = field(default_factory=dict, repr=False, compare=False)

    def __getstate__(self) -> dict[str, Any]:
        """Pickled without the predictions kept (they hold the segments asked about)."""
        return {**self.__dict__, "_at_stamps": {}}

    def predict(self, segment: Segment) -> Array:
        """Torques (n, N) the identified model predicts for a segment's motion (its grid)."""
        return self.predict_motion(segment.q, segment.qd, segment.qdd)

    def predict_motion(self, q: Array, qd: Array, qdd: Array) -> Array:
        """Torques (n, N) the model predicts at each sample of a motion."""
        tau = base_torque(self.robot, self.effects, self.base.independent, self.estimate.beta, q, qd, qdd)
        return tau if self.torque_scale is None else tau * self.torque_scale

    def predict_stamps(self, segments: list[Segment]) -> tuple[Array, Array, Array]:
        """Time stamps, raw measured torque and the model's torque at every input sample the
        segments cover, each evaluated at that sample (INTERFACES.md ``--predictions``). Once
        per list of segments: the errors, the diagnosis's gates and its report read the
        validation's several times (kept up to ``STAMPS_KEPT_BYTES``). The arrays may be
        shared, so read-only."""
        key = tuple(id(s) for s in segments)
        if key in self._at_stamps:
            return self._at_stamps[key][1]
        st = [s.at_stamps for s in segments]
        t = np.concatenate([s.t for s in st])
        tau = np.concatenate([s.tau for s in st])
        tau_hat = np.concatenate([s.as_measured(self.predict_times(s.t, s.q, s.qd, s.qdd)) for s in st])
        for a in (t, tau, tau_hat):
            a.flags.writeable = False
        if sum(a.nbytes for a in (t, tau, tau_hat)) + sum(a.nbytes for v in self._at_stamps.values() for a in v[1]) <= STAMPS_KEPT_BYTES:
            self._at_stamps[key] = (list(segments), (t, tau, tau_hat))
        return t, tau, tau_hat

    def predict_times(self, t: Array, q: Array, qd: Array, qdd: Array) -> Array:
        """Torques (n, N) at the times ``t`` of a motion, with the delays the model has."""
        q, qd, qdd = (advanced(x, t, self.motion_delay_s) for x in (q, qd, qdd))
        tau = self.predict_motion(q, qd, qdd)
        return tau if self.delay_s is None else measured_torque(tau, t, None, self.delay_s)

    def parameter_values(self) -> tuple[Array, Array]:
        """Value and std per standard parameter; NaN where it has no unique value."""
        value = np.full(len(self.names), np.nan)
        std = np.full(len(self.names), np.nan)
        for k, col in enumerate(self.base.independent):
            if self.classes[col] == UNIQUE:
                value[col], std[col] = self.estimate.beta[k], self.estimate.std[k]
        return value, std

    @property
    def classes(self) -> list[str]:
        return self.base.classes()

    def to_json(self) -> dict[str, Any]:
        """The ``identify --json`` document of INTERFACES.md (plus a few extra fields; ``identified``:
        :func:`~identify.identifiability.identified_ranges`, the values and stds the estimate's whatever it says)."""
        nj = self.robot.n_joints
        value, std = self.parameter_values()
        modeled = self.robot.modeled_parameters()
        classes = self.classes
        column_range, column_ok, base_range, base_ok = identified_ranges(self.robot, self.names, self.base, std, self.estimate.std)
        params = []
        for k in range(self.robot.n_parameters):
            params.append(
                {
                    "name": self.names[k],
                    "link": k // 10 + 1,
                    "value": _num(value[k]),
                    "std": _num(std[k]),
                    "identifiability": classes[k],
                    "modeled": _num(modeled[k]),
                    "identified": bool(column_ok[k]), "physical_range": _num(column_range[k]),
                }
            )
        base = []
        exprs = self.base.expressions()
        modeled_base = self.base.base_values(np.concatenate([modeled, np.zeros(len(self.names) - len(modeled))]))
        for k, expr in enumerate(exprs):
            base.append(
                {
                    "expression": expr,
                    "value": float(self.estimate.beta[k]),
                    "std": float(self.estimate.std[k]),
                    "relative_std_percent": _num(self.estimate.relative_std[k]),
                    "modeled": _num(modeled_base[k]),
                    "identified": bool(base_ok[k]), "physical_range": _num(base_range[k]),
                }
            )
        effects = []
        for e in self.effects:
            cols = [self.names.index(label) for label in e.labels()]
            effects.append(
                {
                    "effect": e.effect,
                    "joint": e.joint + 1,
                    "parameters": {p: _num(value[c]) for p, c in zip(e.parameter_names, cols)},
                    "std": {p: _num(std[c]) for p, c in zip(e.parameter_names, cols)},
                    "identifiability": {p: classes[c] for p, c in zip(e.parameter_names, cols)},
                    **({"setting": dict(e.setting)} if e.setting else {}),
                    **({"load": list(e.load_parameters)} if isinstance(e, LoadFriction) else {}),  # the rigid body whose torque is its load
                }
            )
        return {
            "robot": self.robot.name,
            "n_joints": nj,
            "samples": self.samples,
            "condition_number": self.excitation.condition_number,
            "rank": self.excitation.rank,
            "weighting": self.estimate.weighting,
            "joint_noise_sigma": [float(x) for x in self.estimate.joint_sigma],
            "parameters": params,
            "base_parameters": base,
            "effects": effects,
            "fit": self.fit,
            "validation": self.validation,
            "validation_samples": self.validation_samples,
            "held_out": self.held_out,
            "preprocessing": self.notes,
            "filtering": self.filtering,
            "prior": self.prior,
            # joint j measures torque_scale[j] times the model's torque (a declared or found drive gain)
            "torque_scale": None if self.torque_scale is None else [float(x) for x in self.torque_scale],
        }


def _num(x: float) -> float | None:
    return None if not np.isfinite(x) else float(x)


def _search_settings(system: Array, names: list[str], effects: list[LinearEffect], searched: set[tuple[str, int]],
                     segments: list[Segment], columns: Array, motion_delay: Array | None = None) -> tuple[list[LinearEffect], list[str]]:
    """Each searched effect's fixed parameter, joint by joint: the value whose columns leave
    the least residual of the whole least-squares fit (:data:`SWEEPS` of coordinate descent),
    first on its grid (``SETTINGS``), then refined between the best value's neighbours
    (:func:`_refine`): real friction's smoothing is whatever it is, and a grid step of 3x left
    a clean log's held-out error at 1.5x its noise floor. The scores use every ``stride``-th
    equation, at most :data:`SEARCH_EQUATIONS` of them, and a try projects only the columns it
    changes (:class:`ColumnTrials`): refactoring a long log's triangles per try took most of the
    identification's time."""
    nj = system.shape[0]
    keep = np.append(columns, system.shape[1] - 1)
    where = {c: i for i, c in enumerate(columns.tolist())}
    stride = max(1, -(-system.shape[2] // SEARCH_EQUATIONS))
    r = [_triangle(system[j][:, ::stride][keep]) for j in range(nj)]

    def rss(rs: list[Array]) -> float:
        return float(JointFactors(rs, np.ones(nj)).combined()[-1, -1] ** 2)

    effects = list(effects)
    loads: list[Array] | None = None
    notes: dict[int, str] = {}
    factored: dict[tuple[int, tuple[int, ...]], ColumnTrials] = {}
    columns_of: dict[tuple[Any, ...], Array] = {}
    for sweep, k in [(sweep, k) for sweep in range(SWEEPS) for k in range(len(effects))]:
        e = effects[k]
        if (e.effect, e.joint) not in searched or len(e.parameter_names) != 1:
            continue
        col = names.index(e.labels()[0])
        if col not in where:
            continue
        j = e.joint
        key, grid = SETTINGS[e.effect]
        # a Stribeck or load-dependent term on the same joint shares Coulomb's smoothing of sign(qd)
        follow = [(m, names.index(f.labels()[0])) for m, f in enumerate(effects)
                  if e.effect == "coulomb_friction" and f.joint == j
                  and (f.effect == "stribeck_friction" or (isinstance(f, LoadFriction) and f.follows_coulomb))]
        tried_along = [(m, c) for m, c in follow if c in where]  # the others are not in the fit
        for m, _ in follow:
            following = effects[m]
            if isinstance(following, LoadFriction) and loads is None:
                loads = segment_loads(segments, following, motion_delay)  # every load effect shares one load
        changed = (where[col], *(where[c] for _, c in tried_along))
        if (j, changed) not in factored:  # the joint's other columns, factored once for every sweep
            factored[j, changed] = ColumnTrials(system[j][:, ::stride][keep].T, list(changed))
        trials = factored[j, changed]
        tried: dict[float, tuple[float, Array]] = {}

        def score(value: float, e: LinearEffect = e, along: list[tuple[int, int]] = tried_along, trials: ColumnTrials = trials,
                  tried: dict[float, tuple[float, Array]] = tried, j: int = j, k: int = k, key: str = key,
                  loads: list[Array] | None = loads) -> float:
            if value not in tried:
                # a value's columns are the same in every sweep, unless a term following this
                # Coulomb's smoothing (a Stribeck term with its own searched velocity) changed
                cached = (k, value, tuple(effects[m].setting for m, _ in along))
                if cached not in columns_of:
                    cols = [equation_column(segments, e.with_setting(**{key: value}), motion_delay)]
                    cols += [equation_column(segments, effects[m].with_setting(smoothing=value), motion_delay, loads) for m, _ in along]
                    columns_of[cached] = np.column_stack([c[::stride] for c in cols])
                rows = trials.rows(columns_of[cached])
                tried[value] = (rss(r[:j] + [rows] + r[j + 1 :]), rows)
            return tried[value][0]

        # the grid first for every joint, then each refined with the others at their choices
        chosen = _grid_best(grid, score) if sweep < SWEEPS - 1 else _refine(grid, score, around=dict(e.setting)[key])
        best = e.with_setting(**{key: chosen})
        system[j][col] = equation_column(segments, best, motion_delay)
        for m, c in follow:
            effects[m] = effects[m].with_setting(smoothing=chosen)
            system[j][c] = equation_column(segments, effects[m], motion_delay, loads)
        r[j] = tried[chosen][1]
        effects[k] = best
        for other in [f for f in factored if f[0] == j and f[1] != changed]:
            del factored[other]  # its fixed columns include the ones just rewritten
        notes[k] = f"{e.effect} on joint {j + 1}: {key} {chosen:.3g} (grid {', '.join(f'{v:g}' for v in grid)}, refined)"
    return effects, list(notes.values())


SWEEPS = 2
"""Sweeps of the settings' coordinate descent: the first takes each joint's best grid value,
the last refines each (:func:`_refine`) with every other joint at its choice. Refined in one
sweep, a joint's setting was chosen while the joints after it still had their starting
values: a clean 1 kHz log of the second independent generator stayed at 1.09x its noise
floor (joint 2's smoothing 0.031 rad/s for the true 0.020)."""

REFINE_HALVINGS = 2
"""Halvings of the log step when a setting is refined beyond its grid: 2 tries each, the
result within about 8 % of the best value (a 3x grid step / 2^3). Four halvings chose the
same to within the noise on the lab cases (held-out 1.00-1.05x their floor either way) and
made every identification's search half as long again."""


def _grid_best(grid: tuple[float, ...], score: Callable[[float], float]) -> float:
    """The grid value of least ``score`` (the first of equals)."""
    best, best_score = grid[0], score(grid[0])
    for value in grid[1:]:
        s = score(value)
        if s < best_score * (1 - 1e-9):
            best, best_score = value, s
    return best


def _refine(grid: tuple[float, ...], score: Callable[[float], float], around: float | None = None) -> float:
    """A pattern search in log(value) around ``around`` (the grid's best if not given): tries
    at ``best * exp(+-step)``, the step starting at half the log distance to the nearer grid
    neighbour and halving :data:`REFINE_HALVINGS` times. A best of 0 (a sharp sign) stays 0;
    below the smallest positive value the missing neighbour mirrors the present one (towards
    a sharp sign), and nothing is tried above the largest: on the KUKA LWR4+ the data chose
    0.32 rad/s for two joints' "Coulomb" smoothing, a curved viscous law fitted to one
    trajectory's speeds that predicted another's worse (10.6 % against 9.9 %)."""
    best = _grid_best(grid, score) if around is None else around
    best_score = score(best)
    positive = sorted(v for v in grid if v > 0)
    if best <= 0 or len(positive) < 2:
        return best
    above = min((v for v in positive if v > best), default=None)
    below = max((v for v in positive if v < best), default=None)
    below = best**2 / (above if above is not None else positive[-1]) if below is None else below
    step = min(np.log(best / below), np.log(above / best) if above is not None else np.inf) / 2
    for _ in range(REFINE_HALVINGS + 1):
        centre = best
        for value in (centre * np.exp(-step), centre * np.exp(step)):
            value = float(value)
            if value > positive[-1]:
                continue
            s = score(value)
            if s < best_score * (1 - 1e-9):
                best, best_score = value, s
        step /= 2
    return best


def _triangle(columns: Array) -> Array:
    """The R factor of one joint's ``[W_j | tau_j]`` stored column by column (a copy)."""
    return factor_columns([np.array(columns)]).r[0]


def _factors(system: Array, columns: Array) -> JointFactors:
    """Per-joint R factors of the chosen regressor columns and the torque."""
    keep = np.append(columns, system.shape[1] - 1)
    buffer = np.empty((keep.size, system.shape[2]))  # one joint at a time, its QR in place: a fresh copy's first touch cost more
    return factor_columns(np.take(system[j], keep, axis=0, out=buffer, mode="clip") for j in range(system.shape[0]))


def _robust(system: Array, columns: Array, residual: Array, est: LeastSquares, factors: JointFactors, weighting: str,
            penalty: Array | None = None) -> tuple[LeastSquares, int, float]:
    """``est`` with the batch-means sandwich covariance (:func:`batch_means_covariance`);
    the information matrix comes from the QR triangles, the scores from one pass. With a
    prior (``penalty``, in the same scale) the prior counts as observations of its own: it
    joins the bread and, with its own covariance, the meat, so a direction the data leave
    to the prior keeps the prior's uncertainty instead of none."""
    weights = 1.0 / np.maximum(est.joint_sigma, 1e-300) if weighting == "wls" else np.ones(system.shape[0])
    scores = np.zeros((residual.shape[0], columns.size))
    for j in range(system.shape[0]):
        scores += system[j][columns].T * (weights[j] ** 2 * residual[:, j])[:, None]
    r = factors.combined(weights)[:-1, :-1]
    if penalty is None:
        rinv = np.linalg.pinv(r)
        bread = rinv @ rinv.T
    else:
        bread = np.linalg.inv(r.T @ r + penalty)
    block = 4 * correlation_length(residual * weights)
    cov = batch_means_covariance(bread, scores, block)
    if penalty is not None:
        cov = cov + bread @ penalty @ bread.T
    return replace(est, covariance=cov, std=np.sqrt(np.maximum(np.diag(cov), 0.0))), block, effective_batches(scores, block)


def _modeled_prior(robot: Robot, names: list[str], effects: list[LinearEffect], base: BaseParameters, system: Array) -> Prior | None:
    """The robot file's modeled values as a prior on the base parameters (identify.prior);
    None when no link has modeled values."""
    phi0 = robot.modeled_parameters()
    std = np.full(len(names), np.inf)
    std[: robot.n_parameters] = link_scales(phi0)
    if not np.isfinite(std[: robot.n_parameters]).any():
        return None
    mean = np.zeros(len(names))
    mean[: robot.n_parameters] = np.nan_to_num(phi0)
    for e in effects:
        tau_rms = float(np.sqrt(np.mean(system[e.joint][-1] ** 2)))
        for label in e.labels():
            c = names.index(label)
            col_rms = float(np.sqrt(np.mean(system[e.joint][c] ** 2)))
            if col_rms > 0 and tau_rms > 0:
                std[c] = tau_rms / col_rms
    return base_prior(base, mean, std)


LOAD_PASSES = 2
"""Fits with a load-dependent friction's load taken from the fit before (the first from the
fit without it): ``fl`` is a few percent, so the load moves a few percent of a few percent
between passes."""


def identify(robot: Robot, experiments: list[Prepared], validation: list[Prepared] | None = None, options: IdentifyOptions | None = None) -> IdentificationResult:
    """Estimate the base parameters from ``experiments``; measure the error on ``validation``.

    A declared load-dependent friction (``fl |tau_load| sign(qd)``) is bilinear in the
    parameters; with its load fixed it is one more column. The load is the model's own
    rigid-body torque, so it is found by fixed-point passes (:data:`LOAD_PASSES`): the fit
    without the effect gives the first load, each fit the next (Gauss-Seidel on the two
    factors; cheaper than Gauss-Newton on all parameters and, with ``fl`` small, as good).

    On one BLAS thread: its factorisations are a few dozen columns wide, and OpenBLAS's
    threads on them cost more than they share. On the 2-core machine, the 6-joint 100 Hz log
    of ``benchmarks/bench_diagnose.py`` took 0.6 s on one thread against 0.8-1.2 s on two,
    and beside two busy cores 0.8 s against 3.5 s; 100,000 samples at 500 Hz
    (``benchmarks/bench_identify.py``) 2.4 s against 2.3 s."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1, "blas"):
        return _identify_passes(robot, experiments, validation, options or IdentifyOptions())


def _identify_passes(robot: Robot, experiments: list[Prepared], validation: list[Prepared] | None,
                     options: IdentifyOptions) -> IdentificationResult:
    """:func:`identify`: one fit, or the load-dependent friction's fixed-point passes."""
    if not any(e.effect in LOAD_DEPENDENT for e in robot.effects):
        return _identify(robot, experiments, validation, options)
    if options.load_parameters is not None:
        result = _identify(robot, experiments, validation, options, np.asarray(options.load_parameters, float))
        result.notes.append("load-dependent friction: its load the rigid-body torque of the given parameters (one fit)")
        return result
    plain = replace(robot, effects=tuple(e for e in robot.effects if e.effect not in LOAD_DEPENDENT))
    with warnings.catch_warnings():  # the final pass warns what there is to warn
        warnings.simplefilter("ignore", PoorExcitationWarning)
        passes = replace(options, stamp_errors=False)  # their parameters alone carry on
        load = rigid_parameters(_identify(plain, experiments, None, passes))
        for _ in range(LOAD_PASSES - 1):
            load = rigid_parameters(_identify(robot, experiments, None, passes, load))
    result = _identify(robot, experiments, validation, options, load)
    moved = float(np.linalg.norm(rigid_parameters(result) - load) / max(float(np.linalg.norm(load)), 1e-300))
    result.notes.append(f"load-dependent friction: its load the estimate's own rigid-body torque ({LOAD_PASSES} passes from the fit "
                        f"without it; the last moved the rigid-body parameters {100 * moved:.2g} %)")
    return result


def rigid_parameters(result: IdentificationResult) -> Array:
    """A standard parameter vector (10 N,) whose rigid-body torque is the estimate's: the base
    parameters in their own columns, zero in the dependent ones (eq. 18's torque is the same)."""
    coef = np.zeros(len(result.names))
    coef[result.base.independent] = result.estimate.beta
    return coef[: result.robot.n_parameters]


def _identify(robot: Robot, experiments: list[Prepared], validation: list[Prepared] | None, options: IdentifyOptions,
              load_parameters: Array | None = None) -> IdentificationResult:
    """One weighted least-squares fit of eq. (18) with the declared effects, their load fixed:
    the filtered equations, what the robot file leaves to the data (settings, drive gains),
    the excitation check (5.2) on the structural base parameters (5.4), the prior, the
    covariance, and the errors against the raw torque."""
    effects = declared_effects(robot, load_parameters)
    names = column_names(robot, effects)
    segments = [s for p in experiments for s in p.segments]
    if not segments:
        raise IdentificationError("no usable samples in the identification data")
    scale = None if options.torque_scale is None else np.asarray(options.torque_scale, float)
    delay = None if options.delay_s is None else np.asarray(options.delay_s, float)
    motion_delay = None if options.motion_delay_s is None else np.asarray(options.motion_delay_s, float)
    system = regression_system(robot, effects, segments, scale, delay, motion_delay)
    if options.exclude_reversals:
        _leave_out_reversals(system, segments)
    base = structural_base(robot, effects, options.seed)
    notes = [f"{s}" for p in experiments for s in p.notes]
    # with reversals left out, a Coulomb model's smoothing has nothing to show itself on
    searched = set() if options.exclude_reversals else _searched(robot)
    if searched:
        effects, found = _search_settings(system, names, effects, searched, segments, base.independent, motion_delay)
        notes.append("chosen on the data: " + "; ".join(found))
    factors = _factors(system, base.independent)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PoorExcitationWarning)
        # the singular values and column norms of the regressor are those of its R factor
        exc = excitation(factors.combined()[:-1, :-1], base.expressions(), options.max_condition)
    if exc.rank < base.n_base:
        base, factors = _regrouped(robot, system, names, exc, notes)
    for c in caught:
        warnings.warn(c.message, PoorExcitationWarning, stacklevel=2)
    gains = declared_gains(robot)
    if gains:
        scale, factors = _with_declared_gains(system, factors, gains, scale, options.weighting, notes)
    est, tau_hat, penalty, prior_doc, refit = _fit_with_prior(robot, names, effects, base, system, factors, options, notes)
    tau = system[:, -1].T
    fit = summary(tau, tau_hat)
    if options.covariance == "batch_means":
        est, block, batches = _robust(system, base.independent, tau - tau_hat, est, factors, options.weighting, penalty)
        notes.append(f"standard deviations: batch-means sandwich over blocks of {block} samples (four times the residual's correlation length)")
    result = IdentificationResult(robot, names, effects, base, est, exc, sum(p.n_stamps for p in experiments), fit, notes=notes, factors=factors,
                                  torque_scale=scale, delay_s=delay, motion_delay_s=motion_delay, prior=prior_doc,
                                  covariance_batches=None if options.covariance != "batch_means" else int(batches))
    result.fit["equations"] = int(tau.shape[0])
    if options.stamp_errors:
        measure_errors(result, system, segments, validation, refit, options.held_out_error)
    result.filtering = [p.filtering() for p in experiments]
    return result


def _leave_out_reversals(system: Array, segments: list[Segment]) -> None:
    """``IdentifyOptions.exclude_reversals``: each joint's equations while it is slower than
    0.02 rad/s or within 25 ms of a velocity reversal set to zero (a zero equation weighs
    nothing): sign(qd) is wrong there."""
    qd = equation_motion(segments, "qd")
    qdd = equation_motion(segments, "qdd")
    reversing = np.abs(qd) < np.maximum(0.02, np.abs(qdd) * 0.025)
    for j in range(system.shape[0]):
        system[j][:, reversing[:, j]] = 0.0  # a zero equation weighs nothing


def _regrouped(robot: Robot, system: Array, names: list[str], exc: Excitation, notes: list[str]) -> tuple[BaseParameters, JointFactors]:
    """The data excite fewer base parameters than the kinematics allow (the excitation check,
    5.2): the base parameters regrouped on the data's own regressor (5.4), with their R factors."""
    every = _factors(system, np.arange(len(names)))
    order = preferred_order(robot.n_joints, len(names) - robot.n_parameters)
    base = base_parameters(every.combined()[:-1, :-1], names, order, rtol=1e-7)
    notes.append(f"the data excites {exc.rank} of the {exc.n_base} structural base parameters; regrouped on the data")
    return base, every.select(base.independent)


def _with_declared_gains(system: Array, factors: JointFactors, gains: list[int], scale: Array | None, weighting: str,
                         notes: list[str]) -> tuple[Array, JointFactors]:
    """Each declared drive gain by profiling the fit over it (:func:`_profile_gains`); the
    measured torque is then brought back to the model's, as a found gain is (``_model_torque``
    divides by it; the parallel filter is linear, so dividing the filtered row is the same, and
    dividing the last column of an R factor is the R factor of the divided system). Returns the
    torque's scale per joint and the factors of the divided system; ``system`` is divided in place."""
    found_gain = _profile_gains(factors, gains, weighting)
    scale = found_gain if scale is None else scale * found_gain
    system[:, -1] /= found_gain[:, None]
    factors = JointFactors([r * np.append(np.ones(factors.n_parameters), 1.0 / g) for r, g in zip(factors.r, found_gain)], factors.counts)
    notes.append("torque gain chosen on the data (the joint measures gain x the model's torque): "
                 + ", ".join(f"joint {j + 1} {found_gain[j]:.4g}" for j in gains))
    return scale, factors


def _system_torque(system: Array, names: list[str], independent: Array, beta: Array) -> Array:
    """The model's torque (n, N) at the system's equations, of base parameters ``beta`` on the columns ``independent``."""
    coef = np.zeros(len(names))
    coef[independent] = beta
    return np.stack([system[j, :-1].T @ coef for j in range(system.shape[0])], axis=1)


def _fit_with_prior(robot: Robot, names: list[str], effects: list[LinearEffect], base: BaseParameters, system: Array,
                    factors: JointFactors, options: IdentifyOptions,
                    notes: list[str]) -> tuple[LeastSquares, Array, Array | None, dict[str, Any] | None, Refit]:
    """Weighted least squares on the R factors, then, with ``prior="modeled"``, the robot
    file's modeled values as a prior for what the data do not excite (identify.prior: the data
    weighed as one equation per correlation length, the prior widened until it agrees with
    them, or at ``options.prior_widening``). Returns the estimate, its torque at the equations,
    the prior's penalty (None without one), the prior's document, and the same estimator (its
    weighting and prior, without bounds) for other factors of the same columns."""
    est = solve_factors(factors, options.weighting)
    tau = system[:, -1].T
    tau_hat = _system_torque(system, names, base.independent, est.beta)
    penalty, prior_doc = None, None
    if options.prior not in PRIORS:
        raise ValueError(f"prior must be one of {PRIORS}, got {options.prior!r}")
    prior = _modeled_prior(robot, names, effects, base, system) if options.prior == "modeled" else None
    if prior is not None:
        weights = 1.0 / np.maximum(est.joint_sigma, 1e-300) if options.weighting == "wls" else np.ones(robot.n_joints)
        length = correlation_length((tau - tau_hat) * weights)
        prior = (widened(prior, est.beta, length * est.covariance) if options.prior_widening is None
                 else scaled(prior, options.prior_widening))
        prior_doc = prior.to_json(length)
        if prior.covered:
            est, penalty = with_prior(factors, est, prior.mean, prior.precision, length)
            tau_hat = _system_torque(system, names, base.independent, est.beta)
            wider = f", widened {prior.widening:.3g}x in variance to agree with the data" if prior.widening > 1.0 else ""
            notes.append(f"prior: the modeled values (within {100 * RELATIVE_STD:g} % of themselves{wider}) on {prior.covered} of "
                         f"{base.n_base} base parameters, the data weighed as one equation in {length} (their correlation length)")
        else:
            notes.append("prior: the data contradict the modeled values beyond any width; least squares alone")
    elif options.prior == "modeled":
        notes.append("prior: none (the robot file models no link's inertial values); least squares alone")
    if options.nonnegative:
        est, tau_hat = _bounded(system, names, base, factors, est, penalty, None if prior is None else prior.mean, options.nonnegative, notes)
    held = prior if prior is not None and prior.covered else None

    def refit(other: JointFactors) -> LeastSquares:
        plain = solve_factors(other, options.weighting)
        return plain if held is None else with_prior(other, plain, held.mean, held.precision, length)[0]

    return est, tau_hat, penalty, prior_doc, refit


def _bounded(system: Array, names: list[str], base: BaseParameters, factors: JointFactors, est: LeastSquares, penalty: Array | None,
             mean: Array | None, nonnegative: tuple[str, ...], notes: list[str]) -> tuple[LeastSquares, Array]:
    """``est`` refitted with the parameters named in ``nonnegative`` held >= 0: the same
    weighted least squares (and prior penalty) with bounds (estimation.bounded_quadratic);
    the covariance stays the unbounded fit's. A bounded parameter that is not a base column
    of its own (absorbed into a combination) is left free."""
    lower = np.array([0.0 if names[c] in nonnegative else -np.inf for c in base.independent])
    if not np.isfinite(lower).any() or np.all(est.beta[np.isfinite(lower)] >= 0.0):
        return est, _system_torque(system, names, base.independent, est.beta)
    weights = 1.0 / np.maximum(est.joint_sigma, 1e-300) if est.weighting == "wls" else np.ones(system.shape[0])
    r = factors.combined(weights)
    rr, z = r[:-1, :-1], r[:-1, -1]
    h, g = rr.T @ rr, rr.T @ z
    if penalty is not None and mean is not None:
        h, g = h + penalty, g + penalty @ mean
    beta = bounded_quadratic(h, g, lower)
    held = [names[c] for c, b, lo in zip(base.independent, beta, lower) if np.isfinite(lo) and b <= lo]
    notes.append("bounded least squares: " + (", ".join(held) + " held at 0" if held else "no bound active")
                 + " (friction dissipative, inertia and stiffness positive); standard deviations of the unbounded fit")
    return replace(est, beta=beta), _system_torque(system, names, base.independent, beta)

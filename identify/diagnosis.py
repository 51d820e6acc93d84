"""Close the loop: find in the residual the effect the model lacks, add it, refit, repeat.

The base model is the rigid body (eq. 18) with the robot file's declared effects. Every
entry of the catalogue becomes candidate regressor columns on a joint (or the arm):

- linear in its parameters: viscous (``qd``), Coulomb (``sign qd``), offset (``1``), rotor
  inertia (``qdd``), spring (``q``, with an offset), load-dependent Coulomb
  (``|tau_load| sign qd``, its load the modeled rigid body, or the fit's where the robot file
  models no inertials), and friction on every joint at once;
- nonlinear in one parameter, searched on a grid and linear given it: Stribeck friction
  (``sign(qd) exp(-(qd/v_s)^2)`` over ``v_s``), cogging (``sin, cos(2 pi q / P)`` over the
  period ``P``, an integer number of periods per turn from 2 to 120);
- a torque-constant error (the joint measures ``s`` times the model's torque), fitted
  exactly: that joint's rigid-body rows scaled by ``s`` and the fit profiled over ``s``
  (:class:`_GainProfile`);
- linearised about the current fit: a delay of a joint's torque (or of the
  whole torque channel) behind the positions (minus the rate of change of the prediction:
  ``tau(t - d) ~ tau - d dtau/dt``) and a tilt
  of gravity (the derivative of the prediction when gravity turns about base x or y; the
  parameters the base set leaves out come from the modeled values).

A round scores every candidate by the held-out error of the refitted model: rows are
whitened by each joint's noise level, the candidate's columns are projected off the
current model (Frisch-Waugh), the refit is solved on the even tenths of the identification
data and its error measured on the odd tenths (held-out blocks; the validation data never
rank, they only veto, gate (f), and measure before and after). The best-ranked candidate that
clears its gates is added: (a) it cuts the held-out residual power by at least ``min_gain_joint``
of its joint's (``min_gain`` of the arm's, for an arm-wide effect, and ``min_gain`` of the power
of the joints other than the one it helps most: an effect of the arm must show on more than
one joint), each added parameter paying a penalty in the ranking, (b) a one-joint effect cuts its joint's held-out error by
``min_error_drop`` and the arm's by ``min_arm_drop``, (c) it passes an F-test on the identification data at ``alpha``, and (d) with
it added, least squares on the identification data stays as close to the robot file's modeled
values: the prior (identify.prior) widens at most ``max_prior_widening`` over the model before
it. Held-out tenths of one trajectory cannot see what a finding does where that trajectory is
silent; a finding that trades against poorly excited parameters (a tilt against the first
moments) shows there as a model the data now contradict, and is set aside (reported, not
taken), and (e) what it changes in the prediction is at least ``min_noise_fraction`` of the
torque's own noise (its joint's, or the arm's): a long filtered record makes an effect far below
the noise significant, and on clean low-noise data such an effect is the fit's own model
error, and (f) it does not raise its joint's (the arm's) error on the validation data
consistently (a one-sided t test at ``veto_alpha`` over the validation's tenths): tenths of
one trajectory share its excitation, and a fit's own model error can look like an effect
there and on no other run. Then refit and repeat, until nothing passes. The findings are fitted with the prior as
wide as the declared model's fit or the last accepted finding's found it, whichever is less. A candidate whose columns lie in the span of the model is
absorbed (rotor inertia of a first joint with a vertical axis joins ``Izz1``), and is
reported as such. When a look-alike (Coulomb/Stribeck, torque gain/rotor inertia,
delay/viscous) explains nearly as much, both are named with the experiment that would
separate them.

Before and after are then fitted as ``identify`` fits (:func:`findings_model`): before is the
declared model exactly as ``armid identify`` gives it, after the same with the findings added.
A position-dependent finding (spring, cogging) whose joint the validation moves beyond the
positions it was found on is reported as extrapolated: held-out tenths of one motion cannot
tell a spring from the local slope of a ripple longer than that motion.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import stats

from .dynamics import regressor
from .effects import ColumnFunction
from .errors import PoorExcitationWarning
from .identification import (
    IdentificationResult,
    IdentifyOptions,
    column_count,
    declared_effects,
    declared_gains,
    identify,
    rigid_parameters,
    stacked_regressor,
    structural_base,
)
from .metrics import masked_summary, summary
from .preprocess import Prepared
from .robot import DeclaredEffect, Robot
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
    "load_dependent_coulomb": "coulomb_friction",
}
SEPARATE = {
    frozenset(("coulomb_friction", "stribeck_friction")): "slow constant-velocity moves of joint {j} at several speeds "
    "between 0.01 and 0.5 rad/s: Stribeck friction falls with speed, Coulomb friction does not",
    frozenset(("torque_gain", "rotor_inertia")): "hold joint {j} still at poses with different gravity load, or move it "
    "with and without a known payload: a torque-constant error scales the static torque, rotor inertia adds none at rest",
    frozenset(("time_delay", "viscous_friction")): "excite joint {j} at two frequencies with the same velocity amplitude: "
    "a delay's error grows with frequency, viscous friction depends on velocity alone",
    frozenset(("load_dependent_coulomb", "coulomb_friction")): "move joint {j} at the same speeds under different loads (poses "
    "with different gravity torque on it, or with and without a known payload): load-dependent friction grows with the load, "
    "Coulomb friction does not",
    frozenset(("torque_offset", "spring")): "hold joint {j} still at several positions across its whole range (with the "
    "others fixed): a spring's torque changes with position, an offset does not; over a short range gravity absorbs a spring",
}
DISSIPATIVE = ("viscous_friction", "coulomb_friction", "stribeck_friction", "rotor_inertia", "load_dependent_coulomb")  # last parameter > 0
DISSIPATIVE_PARAMETER = {"viscous_friction": "fv", "coulomb_friction": "fc", "stribeck_friction": "fs", "rotor_inertia": "ia",
                         "load_dependent_coulomb": "fl"}
"""... the parameter of each that must be > 0, by its name in a finding."""
# the Stribeck velocity on a log grid 0.01-1 rad/s, a factor 1.33 apart (a coarser grid left
# a third of a blind case's Stribeck term in the residual)
STRIBECK_VELOCITIES = tuple(float(v) for v in np.round(np.geomspace(0.01, 1.0, 17), 4))
# ... of which a joint is offered those its motion outruns: at least a fifth of its samples
# faster than 1.73 vs, where exp(-(qd/vs)^2) is under 5 % of fs. A slower "peak" never decays
# in the data: Coulomb and viscous friction bent into another shape, not a low-speed effect
# (clean logs of the second independent generator got Stribeck at 0.75-1 rad/s on joints
# moving at up to 1 rad/s, and every such finding on its lab cases was on a joint without one)
STRIBECK_DECAYED = (80.0, np.sqrt(-np.log(0.05)))


@dataclass(frozen=True)
class DiagnoseOptions:
    min_gain: float = 0.10  # least fraction of the held-out residual power an arm-wide finding must remove
    # ... and a one-joint finding of its joint's (many more one-joint candidates are tried: on
    # clean data the best of them removed up to a tenth of a joint's power by chance)
    min_gain_joint: float = 0.20
    alpha: float = 1e-6  # F-test significance on the identification data
    min_error_drop: float = 0.05  # ... and the held-out relative error must fall by this fraction
    min_arm_drop: float = 0.005  # ... and a one-joint finding the arm's held-out relative error by this one
    per_parameter: float = 0.005  # penalty per added parameter, as a fraction of the residual power
    max_findings: int = 12
    ranked: int = 10  # candidates tried in rank order each round for one that clears the gates
    arm_margin: float = 1.25  # an arm-wide delay over the best one-joint delay, in explained power
    max_cogging_per_turn: int = 120
    # a joint's equation is left out while it moves slower than this (rad/s or m/s): at rest
    # its friction is anything up to the breakaway force, which no model of qd predicts
    min_speed: float = 0.02
    # ... and while it is within this time of a velocity reversal (|qd| < |qdd| t): a filtered
    # torque smooths the step of Coulomb friction over the filter's span, sign(qd) does not
    reversal_margin_s: float = 0.025
    # a finding must not pull the estimate away from the robot file's modeled values: with it
    # added, the prior (identify.prior) may widen at most this factor over the model before it
    max_prior_widening: float = 1.5
    # ... and what it changes in the prediction must be at least this fraction of the torque's
    # own noise (its joint's, or the arm's for an arm-wide one): long filtered records make an
    # effect far below the noise significant, and on clean low-noise data such a one is the
    # fit's own model error (a cogging of 6 % of the noise was found on a clean blind case)
    min_noise_fraction: float = 0.25
    # a finding the validation data contradict (gate f): its rise of the validation error is
    # significant at this level over the validation's tenths (one-sided t test, batch means)
    veto_alpha: float = 0.05


@dataclass
class _Data:
    """One data set stacked sample by sample: rows ``k N + j`` are joint j of sample k."""

    q: Array
    qd: Array
    qdd: Array
    tau: Array
    period: float
    t: Array | None = None
    # pointwise columns of the motion computed at the input's full rate and put through the
    # same parallel filter as the torque (for columns that vary faster than the cut-off:
    # cogging at speed); None: computed on the filtered samples themselves
    full_rate: Callable[[ColumnFunction], Array] | None = None
    _cache: dict[Any, Array] = field(default_factory=dict, compare=False, repr=False)

    def filtered(self, fn: ColumnFunction) -> Array:
        """``fn(q, qd, qdd)`` -> (n, k) as the equations see it (see ``full_rate``); the same
        function (a partial: the same function and arguments) is computed once per data set."""
        if self.full_rate is None:
            return fn(self.q, self.qd, self.qdd)
        key = (fn.func, fn.args, tuple(sorted(fn.keywords.items()))) if isinstance(fn, functools.partial) else fn
        if key not in self._cache:
            self._cache[key] = self.full_rate(fn)
        return self._cache[key]

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

    def lagged(self, j: int | None, delay: float) -> _Data:
        """The data with a found delay undone: joint j's motion read ``delay`` later (its
        position was reported late), or for ``j`` None every joint's torque read ``delay``
        later (the torque channel lags the positions)."""
        n = self.q.shape[0]
        idx = np.arange(n, dtype=float)
        src = idx + delay / self.period

        def later(x: Array, cols: range | list[int]) -> Array:
            x = x.copy()
            for c in cols:
                x[:, c] = np.interp(src, idx, x[:, c])
            return x

        if j is None:
            return replace(self, tau=later(self.tau, range(self.n_joints)), _cache={})
        # the full-rate columns would not see the lag: computed on the lagged samples instead
        return replace(self, q=later(self.q, [j]), qd=later(self.qd, [j]), qdd=later(self.qdd, [j]), full_rate=None, _cache={})

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


def _cogging_columns(j: int, period: float, q: Array, qd: Array, qdd: Array) -> Array:
    x = 2 * np.pi * q[:, j] / period
    return np.column_stack([np.sin(x), np.cos(x)])


def _stack(prepared: list[Prepared]) -> _Data:
    """The equations' samples: kinematics and torque through each segment's parallel filter
    (low-pass, edges, decimation), so that torque and motion stay aligned."""
    segs = [s for p in prepared for s in p.segments]
    filt = segs[0].parallel
    period = filt.period_s * filt.decimation
    q, qd, qdd, tau = (np.concatenate([s.parallel.apply(getattr(s, k)) for s in segs]) for k in ("q", "qd", "qdd", "tau"))
    t = np.concatenate([s.t[s.parallel.kept(s.n_samples)] for s in segs])

    def full_rate(fn: ColumnFunction) -> Array:
        return np.concatenate([s.parallel.apply(fn(s.q, s.qd, s.qdd)) if s.parallel.cutoff_hz is not None
                               else fn(s.q, s.qd, s.qdd)[s.parallel.kept(s.n_samples)] for s in segs])

    return _Data(q, qd, qdd, tau, period, t, full_rate)


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
            "load_dependent_coulomb": "residual follows sign(qd), growing with the joint's load torque",
        }[self.effect]
        name = self.effect.replace("_", " ")
        # a parameter named as the effect's last word is the effect's value: "torque gain 1.143"
        params = ", ".join(f"{v:.4g}" if name.endswith(f" {k}") else f"{k} {v:.4g}" for k, v in self.parameters.items())
        text = f"{where}: {signature}: {name} {params}; held-out error (identification data) {100 * self.error_before:.2f} % -> {100 * self.error_after:.2f} %"
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
    # candidates that cleared every other gate but pulled the estimate away from the modeled
    # values (DiagnoseOptions.max_prior_widening): set aside, not findings
    conflicting: list[dict[str, Any]] = field(default_factory=list)
    # position-dependent findings the validation uses beyond the positions they were found on
    extrapolated: list[dict[str, Any]] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"found": [f.to_json() for f in self.found], "absorbed": self.absorbed, "declared": self.base_effects,
                "set_aside": self.conflicting, "extrapolated": self.extrapolated,
                "before": self.before, "after": self.after, "noise_floor": self.noise_floor,
                "chosen_on": "the identification data: fitted on its even tenths, scored on its odd tenths; a finding that "
                             "raises its joint's error on the validation data consistently (over its tenths) is set aside (a veto, never a ranking)",
                "measured_on": "the validation data (before and after), at every sample's own stamp against the raw torque"}


def _phi_hat(robot: Robot, base: Any, beta_base: Array, n_cols: int) -> Array:
    """Standard parameters that reproduce the base estimate and otherwise stay modeled (min-norm)."""
    p = robot.n_parameters
    phi0 = robot.modeled_parameters()
    b = np.array([base.base_values(np.eye(n_cols)[k]) for k in range(p)]).T  # (n_base, p)
    return phi0 + np.linalg.lstsq(b, beta_base - b @ phi0, rcond=None)[0]


def _load_friction_columns(robot: Robot, phi: tuple[float, ...], q: Array, qd: Array, qdd: Array) -> Array:
    """(n, N) every joint's ``|tau_load_j| sign(qd_j)``, the load the rigid-body torque of
    ``phi``: computed where the torque was measured, before the parallel filter (the filtered
    torque smooths the step at a reversal; the sign of the filtered velocity does not)."""
    return np.abs(regressor(robot, q, qd, qdd) @ np.asarray(phi)) * np.sign(qd)


def _rate(d: _Data, tau: Array) -> Array:
    """d(tau)/dt along the samples (n, N), by their stamps where they have them."""
    if tau.shape[0] < 2:
        return np.zeros_like(tau)
    return np.gradient(tau, d.t, axis=0) if d.t is not None and np.all(np.diff(d.t) > 0) else np.gradient(tau, d.period, axis=0)


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
        outrun = float(np.percentile(np.abs(data.qd[:, j]), STRIBECK_DECAYED[0])) / STRIBECK_DECAYED[1]
        for vs in [v for v in STRIBECK_VELOCITIES if v <= outrun]:
            def strib(d: _Data, j: int = j, vs: float = vs, wc: bool = with_coulomb) -> Array:
                s = np.sign(d.qd[:, j])
                cols = [s * np.exp(-((d.qd[:, j] / vs) ** 2))]
                return np.column_stack(([s] if wc else []) + cols)
            lin("stribeck_friction", strib, (("fc",) if with_coulomb else ()) + ("fs",), setting=(("velocity", vs),))
        def load_friction(d: _Data, j: int = j, wc: bool = with_coulomb) -> Array:
            cols = d.filtered(functools.partial(_load_friction_columns, robot, ctx["load"]))
            return np.column_stack(([np.sign(d.qd[:, j])] if wc else []) + [cols[:, j]])
        lin("load_dependent_coulomb", load_friction, (("fc",) if with_coulomb else ()) + ("fl",))
        if revolute:
            span = float(np.ptp(data.q[:, j]))
            for k in range(2, opts.max_cogging_per_turn + 1):
                period = 2.0 * np.pi / k
                if span < period:  # at least one whole period over the motion
                    continue
                cog = functools.partial(_cogging_columns, j, period)
                lin("cogging", lambda d, fn=cog: d.filtered(fn), ("a", "b"), setting=(("period_rad", period),))  # type: ignore[misc]
        if ("torque_gain", j) not in present:
            out.append(Candidate("torque_gain", j, (), ("c",), block=lambda d, j=j: ctx["predict"](d)[:, j : j + 1]))  # type: ignore[misc]
        if ("time_delay", j) not in present:  # joint j's drive reports its position late: every joint's torque leads it
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
    if ("time_delay", None) not in present and not any(e == "time_delay" for e, _ in present):
        # the whole torque channel lags the positions (a current loop, a bus, a filter): one delay
        out.append(Candidate("time_delay", None, (), ("delay_s",), full=lambda d: -_rate(d, ctx["predict_smooth"](d)).reshape(-1, 1)))
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

    Findings are ranked on held-out blocks of the identification data (every other tenth of
    it, fitted on the rest); ``validation`` can only veto one (gate f) and measures the errors
    before and after, so the figures reported are not the ones the search optimised."""
    opts = options or DiagnoseOptions()
    ident_all, valid = _stack(experiments), _stack(validation)
    ident, held = _blocks(ident_all)
    nj = robot.n_joints
    # the declared model exactly as `armid identify` fits it ("before"): its settings, its
    # declared drive gains and how far its prior had to widen (the search starts from its
    # gains; gate (d) from its widening)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoorExcitationWarning)
        result0 = identify(robot, experiments, validation)
    # a declared load-dependent friction's load: that fit's own rigid-body torque, here and in
    # every refit of a candidate (one fit each instead of identify's fixed-point passes)
    load0 = rigid_parameters(result0)
    effects = declared_effects(robot, load0)
    base = structural_base(robot, effects)
    n_cols = column_count(robot, effects)
    # drive gains: joint j measures gain_scale[j] times the model's torque (declared, then found)
    gain_scale = np.ones(nj) if result0.torque_scale is None else np.array(result0.torque_scale, float)

    def base_columns(d: _Data) -> Array:  # with the gravity as tilted so far and the drive gains found so far
        cols = stacked_regressor(robot, effects, d.q, d.qd, d.qdd)[:, base.independent]
        return cols if np.all(gain_scale == 1.0) else cols * np.tile(gain_scale, d.q.shape[0])[:, None]

    robot0 = robot
    sample_period = min(s.parallel.period_s for p in experiments for s in p.segments)  # the input's, before decimation
    tilt_total, tilt_rounds = np.zeros(2), 0
    delay_total: dict[int | None, float] = {}
    delay_rounds: dict[int | None, int] = {}

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
    present: set[tuple[str, int | None]] = {(e.effect, e.joint) for e in effects} | {("torque_gain", j) for j in declared_gains(robot)}
    found: list[Finding] = []
    absorbed: list[dict[str, Any]] = []
    absorbed_keys: set[tuple[str, int | None]] = set()
    ctx: dict[str, Any] = {}
    rounds = []
    phi0 = robot.modeled_parameters()
    modeled = None if np.isnan(phi0).any() else phi0
    chosen: list[Candidate] = []
    beta = beta0
    conflicting: list[dict[str, Any]] = []
    settled = _settled(robot0, result0)
    # exact fits of the declared model with findings (gates d and f), and their residuals at
    # the validation stamps, by the findings' effects, joints and parameters
    fits: dict[str, IdentificationResult] = {}
    residuals: dict[str, Array] = {}
    validation_segments = [sg for p in validation for sg in p.segments]
    tau_validation = np.concatenate([sg.at_stamps.tau for sg in validation_segments])

    def key_of(found: list[Finding]) -> str:
        return repr([(f.effect, f.joint, sorted(f.parameters.items())) for f in found])

    def trial_fit(found: list[Finding]) -> IdentificationResult:
        """``identify``'s fit of the declared model with ``found`` (as gates d and f see it)."""
        key = key_of(found)
        if key not in fits:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", PoorExcitationWarning)
                fits[key] = _trial_fit(settled, experiments, found, load0)
        return fits[key]

    def validation_residual(found: list[Finding]) -> Array:
        """That fit's residual at every validation stamp, against the raw torque (n, N)."""
        key = key_of(found)
        if key not in residuals:
            residuals[key] = tau_validation - trial_fit(found).predict_stamps(validation_segments)[2]
        return residuals[key]
    noise_sd = _noise_levels(experiments, nj)
    widening_now = _widening(result0)
    set_aside: set[tuple[str, int | None]] = set()
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
        p_base = wi.shape[1]
        ctx["predict"] = lambda d, b=beta[:p_base]: (base_columns(d) @ b).reshape(-1, nj)
        # the delay's derivative leaves out Coulomb friction: a step in sign(qd) shifted by a
        # sample is a spike at every reversal, which would fit friction's misfit near rest
        smooth = beta[:p_base] * np.array([not base.names[c].startswith(("fc", "fs", "fl")) for c in base.independent])
        ctx["predict_smooth"] = lambda d, b=smooth: (base_columns(d) @ b).reshape(-1, nj)
        ctx["phi"] = _phi_hat(robot, base, beta[:p_base], n_cols)
        # a load-dependent friction's load: the modeled rigid body where the robot file models
        # every link (the fit so far has the friction it lacks in its rigid-body parameters),
        # else the fit's own (its base parameters in their columns, as identify's passes take it)
        load = modeled
        if load is None:
            fitted = np.zeros(n_cols)
            fitted[base.independent] = beta[:p_base]
            load = fitted[: robot.n_parameters]
        ctx["load"] = tuple(float(x) for x in load)
        # Frisch-Waugh on the whitened system A = QR with residual r (r is orthogonal to Q):
        # for columns C, P = Q^T C, gamma = (C^T C - P^T P)^-1 C^T r, the refit's beta is
        # beta - R^-1 P gamma, and the held-out residual is res_v + G P gamma - Cv gamma with
        # G = A_v R^-1. Only a candidate's own rows enter, so a round costs little.
        g_mat = np.linalg.solve(r_mat.T, (a_v * wt_v[:, None]).T).T
        h_vec, h_mat = g_mat.T @ res_v, g_mat.T @ g_mat
        gain_fit = _GainProfile(a_i, yw, a_v, yv, wt_v, nj, p_base)
        joint_of_row = np.arange(yv.size) % nj
        power_before = np.bincount(joint_of_row, res_v**2, nj)  # the held-out residual power per joint
        # (held-out RSS, p-value, candidate, parameters, projection on the model or None,
        # held-out prediction of an exactly fitted one or None, per-joint held-out power after or None)
        scored: list[tuple[float, float, Candidate, Array, Array | None, Array | None, Array | None]] = []
        for c in _candidates(robot, ident, present | absorbed_keys, ctx, opts):
            if c.effect == "torque_gain":
                # fitted exactly, not linearised about the current fit: the joint's rigid-body
                # columns scaled by the gain, profiled over it (see _GainProfile)
                assert c.joint is not None
                exact = gain_fit.best(c.joint)
                if exact is None:
                    continue  # a gain below 0.1 or above 10: a wrong robot file or wiring, not an effect
                scale, rss1, rss_v1, pred_exact = exact
                dof = n_used - a_i.shape[1] - 1
                f_stat = (rss - rss1) / max(rss1 / dof, 1e-300)
                scored.append((rss_v1, float(stats.f.sf(f_stat, 1, dof)), c, np.array([scale - 1.0]), None, pred_exact, None))
                continue
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
            if c.effect in DISSIPATIVE and (bool(np.any(gamma <= 0.0)) if c.joint is not None else float(np.median(gamma[0::3])) <= 0.0):
                continue  # friction that pushes the joint along, or a negative inertia: not physical
            if c.effect == "time_delay" and abs(float(gamma[0])) < 0.5 * sample_period:
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
            power_after: Array | None = None
            if c.block is None:  # the held-out residual power it leaves on each joint
                res_c = res_v + g_mat @ u - cv_full @ gamma
                power_after = np.bincount(joint_of_row, res_c**2, nj)
            scored.append((rss_v1, p_value, c, gamma, proj, None, power_after))
        if not scored:
            break
        # the best by held-out residual power, each added parameter paying its penalty
        scored.sort(key=lambda s: s[0] / rss_v + opts.per_parameter * len(s[3]))
        # an arm-wide delay claims every joint: it must explain clearly more (arm_margin) than
        # the same effect on the one joint that explains most, or that joint's is preferred
        for effect in ("time_delay",):
            arm = next((x for x in scored if x[2].effect == effect and x[2].joint is None), None)
            one = next((x for x in scored if x[2].effect == effect and x[2].joint is not None), None)
            if arm is not None and one is not None and (rss_v - arm[0]) < opts.arm_margin * (rss_v - one[0]):
                scored.remove(arm)
        rounds.append([(f"{s[2].effect}@{s[2].joint}", 1.0 - s[0] / rss_v) for s in scored[:5]])
        # a joint's effect is judged by its joint's residual (on 6-7 joints a perfect fix of one
        # joint removes about 1/N of the arm's): it must remove min_gain of that joint's held-out
        # residual power and cut that joint's error by min_error_drop; one that acts on every
        # joint's row (a delay, a tilt, friction everywhere) min_gain of the whole arm's. The
        # best-ranked candidate that clears its gates is taken (the ranking still favours the
        # larger effect); none clears them: the search ends.
        pick = None
        for rss_v1, p_value, best, gamma, proj_s, pred_x, power_after in scored[: opts.ranked]:
            if p_value > opts.alpha:
                continue
            pred_before = a_v @ beta
            if pred_x is not None:
                cv, pred_after = None, pred_x
            else:
                assert proj_s is not None
                beta_c = beta - np.linalg.solve(r_mat, proj_s @ gamma)
                cv = best.columns(held)
                pred_after = a_v @ beta_c + cv @ gamma
            if best.block is None:
                if rss_v1 > (1.0 - opts.min_gain) * rss_v:
                    continue
                if power_after is not None and nj > 1:
                    # an effect of the arm must show on the arm: what it removes from the joints
                    # other than the one it helps most must be min_gain of their power too (a
                    # tilt bent to fit one joint's unmodeled position-dependent torque helps that
                    # joint alone and leaves the others as they were, or worse)
                    drop = power_before - power_after
                    top = int(np.argmax(drop))
                    rest = float(np.sum(power_before) - power_before[top])
                    if float(np.sum(drop) - drop[top]) < opts.min_gain * rest:
                        continue
            else:
                rows = (wt_v > 0) & (np.arange(yv.size) % nj == best.joint)
                own = float(np.sum(res_v[rows] ** 2))
                if rss_v - rss_v1 < opts.min_gain_joint * own:
                    continue
                if _rel(yv * rows, pred_after * rows) > (1.0 - opts.min_error_drop) * _rel(yv * rows, pred_before * rows):
                    continue  # it whitens the residual but does not move the error anyone reads
                used = wt_v > 0
                if _rel(yv * used, pred_after * used) > (1.0 - opts.min_arm_drop) * _rel(yv * used, pred_before * used):
                    continue  # ... nor the arm's: a joint whose torque is a thousandth of the others
            change = (pred_after - pred_before).reshape(-1, nj)
            if best.joint is not None:
                if float(np.sqrt(np.mean(change[:, best.joint] ** 2))) < opts.min_noise_fraction * noise_sd[best.joint]:
                    continue  # far below its joint's noise: not what anyone measuring the torque would see
            elif float(np.sqrt(np.mean(np.sum(change**2, axis=1)))) < opts.min_noise_fraction * float(np.sqrt(np.sum(noise_sd**2))):
                continue
            if (best.effect, best.joint) in set_aside:
                continue  # another setting of an effect already set aside
            correction = best.effect in ("gravity_tilt", "time_delay") and any(f.effect == best.effect and f.joint == best.joint for f in found)
            if not correction:
                # judged by exact fits too: the model with the finding added as `identify` fits it
                trial = Finding(best.effect, best.joint, _parameters(best, gamma), 0.0, 0.0, 0.0)
                fit_with = trial_fit(found + [trial])
                widening = _widening(fit_with)
                if widening_now is not None and (widening is None or widening > opts.max_prior_widening * widening_now):
                    # (d) on the identification data: the prior's widening with the finding
                    conflicting.append({"effect": best.effect, "joint": None if best.joint is None else best.joint + 1,
                                        "parameters": trial.parameters, "before": widening_now,
                                        "prior_widened_by": widening if widening is not None and np.isfinite(widening) else None, "reason": "prior"})
                    present.add((best.effect, best.joint))
                    set_aside.add((best.effect, best.joint))
                    continue
                # (f) on the validation data: its joint's error (the arm's) must not rise there
                # consistently. Tenths of one trajectory share its excitation; a fit's own model
                # error (the modeled values the prior holds where the data are silent) can look
                # like a spring on them and on no other run (a clean 100 Hz blind case)
                res_before, res_with = validation_residual(found), validation_residual(found + [trial])
                cols = slice(None) if best.joint is None else [best.joint]
                on_validation = tuple(_rel(tau_validation[:, cols], tau_validation[:, cols] - r[:, cols]) for r in (res_before, res_with))
                t_stat = _worse_on_validation(res_before, res_with, best.joint)
                if t_stat > stats.t.isf(opts.veto_alpha, VETO_BLOCKS - 1):
                    residuals.pop(key_of(found + [trial]), None)  # a validation-length array no later round needs
                    conflicting.append({"effect": best.effect, "joint": None if best.joint is None else best.joint + 1,
                                        "parameters": trial.parameters, "reason": "validation",
                                        "validation_error_before": on_validation[0], "validation_error_with": on_validation[1],
                                        "t": t_stat})
                    present.add((best.effect, best.joint))
                    set_aside.add((best.effect, best.joint))
                    continue
                if widening_now is not None:
                    widening_now = widening
            pick = (rss_v1, p_value, best, gamma, cv, pred_before, pred_after)
            break
        if pick is None:
            break
        rss_v1, p_value, best, gamma, cv, pred_before, pred_after = pick
        err_before = _rel(yv * (wt_v > 0), pred_before * (wt_v > 0))
        err_after = _rel(yv * (wt_v > 0), pred_after * (wt_v > 0))
        finding = Finding(best.effect, best.joint, _parameters(best, gamma), 1.0 - rss_v1 / rss_v, err_before, err_after)
        alt_name = LOOKALIKES.get(best.effect)
        if alt_name:
            alt = next((s for s in scored if s[2].effect == alt_name and s[2].joint == best.joint), None)
            if alt is not None and (rss_v - alt[0]) >= 0.9 * (rss_v - rss_v1):
                finding.lookalike = alt_name
                finding.separate_by = SEPARATE[frozenset((best.effect, alt_name))].format(j=(best.joint or 0) + 1)
        if best.effect == "gravity_tilt":
            # applied exactly, not as its linearisation: the base columns are rebuilt with the
            # tilted gravity and the search goes on from there (a linearised tilt leaves a
            # residual that springs and gains would chase); a further tilt found later is a
            # correction of this one (at most two), merged into the same finding
            rotation = _rotate(np.array([gamma[0], gamma[1], 0.0]))
            robot = replace(robot, gravity=rotation @ np.asarray(robot.gravity, float))
            total = np.array([gamma[0], gamma[1]]) + tilt_total
            earlier = next((f for f in found if f.effect == "gravity_tilt"), None)
            if earlier is not None:
                earlier.parameters.update(tilt_x_rad=float(total[0]), tilt_y_rad=float(total[1]))
                earlier.explained = 1.0 - (1.0 - earlier.explained) * (1.0 - finding.explained)
                earlier.error_after = finding.error_after
            else:
                finding.parameters.update(tilt_x_rad=float(total[0]), tilt_y_rad=float(total[1]))
                found.append(finding)
            tilt_total = total
            tilt_rounds += 1
            if tilt_rounds >= 3:
                present.add(("gravity_tilt", None))
            base = structural_base(robot, effects)  # a tilt makes more of the first links' parameters seen
            wi, wv = base_columns(ident), base_columns(held)
            continue
        if best.effect == "torque_gain":
            # applied exactly, like the tilt: the joint's rigid-body columns scaled by the gain
            assert best.joint is not None
            gain_scale[best.joint] *= 1.0 + float(gamma[0])
            found.append(finding)
            present.add(("torque_gain", best.joint))
            wi, wv = base_columns(ident), base_columns(held)
            continue
        if best.effect == "time_delay":
            # applied exactly, like the tilt: the data are shifted by the delay and the search
            # goes on; a further delay of the same kind found later corrects this one (the
            # linearised estimate is biased by the fit it was taken about; at most two corrections)
            key = ("time_delay", best.joint)
            d = float(gamma[0])
            ident, held = ident.lagged(best.joint, d), held.lagged(best.joint, d)
            delay_total[best.joint] = delay_total.get(best.joint, 0.0) + d
            earlier = next((f for f in found if f.effect == "time_delay" and f.joint == best.joint), None)
            if earlier is not None:
                earlier.parameters["delay_s"] = delay_total[best.joint]
                earlier.explained = 1.0 - (1.0 - earlier.explained) * (1.0 - finding.explained)
                earlier.error_after = finding.error_after
            else:
                found.append(finding)
            delay_rounds[best.joint] = delay_rounds.get(best.joint, 0) + 1
            if delay_rounds[best.joint] >= 3:
                present.add(key)
            yi, yv = ident.y, held.y
            wi, wv = base_columns(ident), base_columns(held)
            extra_i = np.column_stack([np.zeros((yi.size, 0))] + [c.columns(ident) for c in chosen])
            extra_v = np.column_stack([np.zeros((yv.size, 0))] + [c.columns(held) for c in chosen])
            continue
        assert cv is not None
        ci = best.columns(ident)
        found.append(finding)
        chosen.append(best)
        present.add((best.effect, best.joint))
        if best.effect in ("stribeck_friction", "load_dependent_coulomb") and "fc" in best.labels:  # found with its Coulomb level
            present.add(("coulomb_friction", best.joint))
        if best.joint is None and best.effect == "coulomb_friction":  # friction on every joint it covers
            present |= {(e, int(label[len(p) :]) - 1) for label in best.labels
                        for e, p in (("coulomb_friction", "fc"), ("viscous_friction", "fv"), ("torque_offset", "offset")) if label.startswith(p)}
        extra_i = np.column_stack([extra_i, ci])
        extra_v = np.column_stack([extra_v, cv])
    found, chosen = _merge_offset_into_spring(found, chosen)
    # before and after, fitted as `identify` fits (parallel filtering, every equation, the
    # declared Coulomb smoothing chosen on the data, weighted least squares): before is the
    # declared model exactly as `armid identify` gives it, after the same with the findings
    # added to the model (findings_model), so the two differ by the findings alone
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoorExcitationWarning)
        robot = robot0
        _refine_delays(settled, found, experiments, load0)  # the declared settings as chosen: a delay's fit per try

        def fit_findings(found: list[Finding]) -> IdentificationResult:
            model, model_options = findings_model(robot, found)
            # the prior as wide as the declared model's fit found it: a finding whose columns lean
            # on poorly excited parameters (a tilt on the first moments) moves least squares away
            # from the modeled values and would widen the prior for the whole model; on the KUKA
            # LWR4+ (1 -> 3) that cost more on another trajectory than the tilt gained
            if widening_now is not None:
                model_options = replace(model_options, prior_widening=min(_widening(result0) or np.inf, widening_now))
            result = identify(model, experiments, validation, model_options) if found else result0
            _update_parameters(found, result)
            return result

        result1 = fit_findings(found)
        # friction or inertia whose sign the whole fit turns (the search saw it positive on its
        # blocks): not physical, so not a finding; the rest refitted without it
        reversed_sign = _sign_reversed(found)
        if reversed_sign:
            conflicting += [{"effect": f.effect, "joint": f.joint + 1, "parameters": dict(f.parameters), "reason": "sign"}
                            for f in reversed_sign if f.joint is not None]
            found = [f for f in found if f not in reversed_sign]
            result1 = fit_findings(found)
    st = [s for p in validation for s in p.segments]
    t_s, tau_s, before_stamps = result0.predict_stamps(st)
    _, _, after_stamps = result1.predict_stamps(st)
    t_v = valid.t if valid.t is not None else np.arange(valid.q.shape[0]) * valid.period
    before_pred = result0.predict_times(t_v, valid.q, valid.qd, valid.qdd)
    after_pred = result1.predict_times(t_v, valid.q, valid.qd, valid.qdd)
    used_v = _moving(valid, opts)
    # before and after as anyone can check them: the model at every validation sample, against the raw torque
    before = summary(tau_s, before_stamps)
    after = summary(tau_s, after_stamps)
    before["moving_equations"] = masked_summary(valid.tau, before_pred, used_v)
    after["moving_equations"] = masked_summary(valid.tau, after_pred, used_v)
    noise = _noise_floor(validation)
    return Diagnosis(found, absorbed, before, after, [f"{e.effect}@{e.joint + 1}" for e in effects], rounds,
                     (valid.tau, before_pred), (valid.tau, after_pred), (t_v, valid.q, valid.qd, valid.qdd), used_v,
                     (np.asarray(t_s), tau_s, after_stamps), noise, conflicting, _extrapolated(found, ident_all.q, valid.q))


POSITION_DEPENDENT = ("spring", "cogging")
"""Effects that are functions of one joint's position: beyond the positions a finding was
fitted on, it is an extrapolation (a spring may be the local slope of a ripple longer than
the motion; held-out tenths of the same motion cannot tell)."""


def _extrapolated(found: list[Finding], q_ident: Array, q_valid: Array, tolerance: float = 0.05) -> list[dict[str, Any]]:
    """The position-dependent findings whose joint the validation takes more than
    ``tolerance`` of the identified range beyond it, with both ranges."""
    out = []
    for f in found:
        if f.effect not in POSITION_DEPENDENT or f.joint is None:
            continue
        lo, hi = float(q_ident[:, f.joint].min()), float(q_ident[:, f.joint].max())
        vlo, vhi = float(q_valid[:, f.joint].min()), float(q_valid[:, f.joint].max())
        beyond = (max(lo - vlo, 0.0) + max(vhi - hi, 0.0)) / max(hi - lo, 1e-12)
        if beyond > tolerance:
            out.append({"effect": f.effect, "joint": f.joint + 1, "identified_range": [lo, hi], "validation_range": [vlo, vhi],
                        "beyond_fraction": beyond})
    return out


def extrapolation_sentence(x: dict[str, Any]) -> str:
    """One line for a finding the validation extrapolates (the text output and the report)."""
    lo, hi = x["identified_range"]
    vlo, vhi = x["validation_range"]
    return (f"{x['effect'].replace('_', ' ')} on joint {x['joint']} was found on positions {lo:.4g}..{hi:.4g}; the validation "
            f"goes to {vlo:.4g}..{vhi:.4g}, {100 * x['beyond_fraction']:.0f} % of that range beyond it: there the finding is "
            "an extrapolation, and a local fit of something else (a ripple longer than the motion) extrapolates badly. "
            "Identify on a motion that covers the validation's positions to tell")


FIXED_OPTIONS = ("velocity", "period_rad")


def findings_model(robot: Robot, found: list[Finding]) -> tuple[Robot, IdentifyOptions]:
    """The declared model with every finding added, as `identify` takes it: a joint's
    friction, offset, rotor inertia, spring or cogging as a declared effect (its searched
    setting kept), friction on every joint as three declared effects per joint, a tilt of
    gravity as the tilted gravity vector, a drive gain as the torque's scale, a delay of the
    torque channel as its lag, a joint's late position as its motion's lag (IdentifyOptions). Declaring the same in the robot file gives the same fit."""
    nj = robot.n_joints
    declared: list[DeclaredEffect] = []
    gravity = np.asarray(robot.gravity, float)
    scale = np.ones(nj)
    delay = np.zeros(nj)
    motion_delay = np.zeros(nj)
    have = {(e.effect, j) for e in robot.effects for j in (range(1, nj + 1) if e.joint is None else [e.joint])}
    for f in found:
        if f.effect == "coulomb_friction" and f.joint is None:  # friction on every joint it covers
            joints = sorted({int(k[2:]) for k in f.parameters if k.startswith("fc")})
            declared += [DeclaredEffect(e, j) for j in joints for e in ("coulomb_friction", "viscous_friction", "torque_offset")]
        elif f.effect == "gravity_tilt":
            axis = np.array([f.parameters["tilt_x_rad"], f.parameters["tilt_y_rad"], 0.0])
            gravity = _rotate(axis) @ gravity
        elif f.effect == "torque_gain" and f.joint is not None:
            scale[f.joint] /= f.parameters["gain"]
        elif f.effect == "time_delay" and f.joint is None:
            delay += f.parameters["delay_s"]
        elif f.effect == "time_delay" and f.joint is not None:
            motion_delay[f.joint] += f.parameters["delay_s"]
        elif f.joint is not None:
            # a found Coulomb's smoothing is chosen on the data, as for a declared one
            fixed = {k: v for k, v in f.parameters.items() if k in FIXED_OPTIONS and f.effect != "coulomb_friction"}
            declared.append(DeclaredEffect(f.effect, f.joint + 1, fixed))
            if f.effect == "spring" and "rest_position" in f.parameters and ("torque_offset", f.joint + 1) not in have:
                declared.append(DeclaredEffect("torque_offset", f.joint + 1))
            if f.effect in ("stribeck_friction", "load_dependent_coulomb") and "fc" in f.parameters and ("coulomb_friction", f.joint + 1) not in have:
                declared.append(DeclaredEffect("coulomb_friction", f.joint + 1))  # found with its Coulomb level
    model = replace(robot, gravity=gravity, effects=tuple(robot.effects) + tuple(declared))
    return model, IdentifyOptions(torque_scale=tuple(scale) if np.any(scale != 1.0) else None,
                                  delay_s=tuple(delay) if np.any(delay != 0.0) else None,
                                  motion_delay_s=tuple(motion_delay) if np.any(motion_delay != 0.0) else None)


def _sign_reversed(found: list[Finding]) -> list[Finding]:
    """The one-joint friction or inertia findings whose fitted parameter is not positive."""
    return [f for f in found if f.joint is not None and f.effect in DISSIPATIVE
            and f.parameters.get(DISSIPATIVE_PARAMETER[f.effect], 1.0) <= 0.0]


def set_aside_sentence(c: dict[str, Any]) -> str:
    """What the text and the report say of a candidate set aside: by gate (d) or (f), or because
    the final fit turned the sign of its friction or inertia."""
    where = "the arm" if c["joint"] is None else f"joint {c['joint']}"
    if c.get("reason") == "validation":
        return (f"{c['effect'].replace('_', ' ')} on {where}: it cleared the held-out tests on the identification data, but on the "
                f"validation data it takes {where}'s error from {100 * c['validation_error_before']:.3g} % to "
                f"{100 * c['validation_error_with']:.3g} %, over most of its tenths (t = {c['t']:.2g}): it does not hold beyond "
                "the run it was found on")
    if c.get("reason") == "sign":
        name = DISSIPATIVE_PARAMETER[c["effect"]]
        return (f"{c['effect'].replace('_', ' ')} on {where}: it cleared the held-out tests, but refitted with the other findings "
                f"on all the identification data its {name} came out {c['parameters'][name]:.4g}: friction that pushes the joint "
                "along, or a negative inertia, is not physical (another effect's shape it was bent to)")
    wider = "widened beyond any width" if c["prior_widened_by"] is None else f"{c['prior_widened_by'] / c['before']:.3g}x wider"
    return (f"{c['effect'].replace('_', ' ')} on {where}: it cleared the held-out tests, but with it least squares on the "
            f"identification data moves away from the robot file's modeled values (the prior would have to be {wider}): "
            "the data cannot tell it from a worse model")


def _trial_fit(robot: Robot, experiments: list[Prepared], found: list[Finding], load: Array) -> IdentificationResult:
    """The model with ``found`` added, fitted as `identify` fits it.
    Gate (d) reads how far its prior on the modeled values (identify.prior) had to widen to
    agree with least squares (``inf``: beyond any width; None: the robot file models no
    inertial values): a finding that lets least squares wander from the modeled values along
    what the data barely excite (a tilt trading against the first moments) widens it, and the
    data alone cannot tell that finding from a worse model. Gate (f) reads its residual at the
    validation stamps."""
    model, options = findings_model(robot, found)
    return identify(model, experiments, None, replace(options, covariance="white", load_parameters=tuple(load)))


VETO_BLOCKS = 10
"""Gate (f) judges a finding on the validation data's consecutive tenths."""


def _worse_on_validation(before: Array, after: Array, joint: int | None, blocks: int = VETO_BLOCKS) -> float:
    """How consistently a finding raises the validation's squared error (its joint's, or the
    arm's): the t statistic of the rise summed over ``blocks`` consecutive blocks, by batch
    means (neighbouring samples are not independent; whole blocks nearly are). A real effect
    that extrapolates a little worse moves a few blocks (t about 1); a finding the other run
    contradicts raises most of them."""
    cols = slice(None) if joint is None else [joint]
    rise = np.sum(after[:, cols] ** 2 - before[:, cols] ** 2, axis=1)
    sums = np.array([b.sum() for b in np.array_split(rise, blocks)])
    spread = float(np.std(sums, ddof=1)) * np.sqrt(blocks)
    return float(np.sum(sums) / spread) if spread > 0 else 0.0


def _widening(result: IdentificationResult) -> float | None:
    """The factor ``result``'s prior was widened by (``inf``: dropped; None: no prior)."""
    if result.prior is None:
        return None
    w = result.prior.get("widened_by")
    return float("inf") if w is None else float(w)


def _settled(robot: Robot, result: IdentificationResult) -> Robot:
    """``robot`` with its declared effects' settings (a Coulomb model's smoothing) fixed at
    what ``result`` chose on the data, one declared effect per joint: refitting it with a
    finding added then costs a solve, not the settings' grid search again."""
    chosen = {(e.effect, e.joint): dict(e.setting) for e in result.effects}
    out = []
    for e in robot.effects:
        for j in range(1, robot.n_joints + 1) if e.joint is None else [e.joint]:
            out.append(DeclaredEffect(e.effect, j, {**e.options, **chosen.get((e.effect, j - 1), {})}))
    return replace(robot, effects=tuple(out))


def _refine_delays(robot: Robot, found: list[Finding], experiments: list[Prepared], load: Array) -> None:
    """Each found delay, refined on the identification data with the exact model (the motion
    or the torque shifted in time) as `identify` fits it: the fit's error on a grid of
    0.6-1.6 times the search's estimate (not unimodal: a shift by about a period of the
    excitation's harmonics fits again), then Brent's method between the best point's neighbours."""
    from scipy.optimize import minimize_scalar

    for f in found:
        if f.effect != "time_delay":
            continue
        d0 = f.parameters["delay_s"]

        def error(d: float, f: Finding = f) -> float:
            f.parameters["delay_s"] = float(d)
            model, options = findings_model(robot, found)
            return float(identify(model, experiments, None, replace(options, load_parameters=tuple(load))).fit["relative_error"])

        grid = d0 * np.array([0.6, 0.8, 1.0, 1.25, 1.6])
        errors = [error(d) for d in grid]
        k = int(np.argmin(errors))
        lo, hi = sorted((grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]))
        best = minimize_scalar(error, bounds=(lo, hi), method="bounded", options={"xatol": 1e-3 * abs(d0), "maxiter": 6})
        f.parameters["delay_s"] = float(best.x) if best.fun <= errors[k] else float(grid[k])


def _rotate(rotation_vector: Array) -> Array:
    """Rodrigues: the rotation by ``|v|`` about ``v``."""
    angle = float(np.linalg.norm(rotation_vector))
    if angle == 0.0:
        return np.eye(3)
    k = rotation_vector / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * kx @ kx


def _update_parameters(found: list[Finding], result: IdentificationResult) -> None:
    """A declared finding's parameters as the final fit (all the identification data) gives them."""
    value, _ = result.parameter_values()
    by_name = dict(zip(result.names, value))
    for f in found:
        if f.joint is None or f.effect in ("torque_gain", "time_delay", "gravity_tilt"):
            continue
        j = f.joint + 1
        if f.effect == "cogging":
            a, b = by_name.get(f"cog_a{j}", np.nan), by_name.get(f"cog_b{j}", np.nan)
            if np.isfinite(a) and np.isfinite(b):
                f.parameters.update(amplitude=float(np.hypot(a, b)), phase_rad=float(np.arctan2(b, a)))
            continue
        if f.effect == "spring":
            k, off = by_name.get(f"ks{j}", np.nan), by_name.get(f"offset{j}", np.nan)
            if np.isfinite(k):
                f.parameters["stiffness"] = float(k)
                if "rest_position" in f.parameters and np.isfinite(off) and k != 0:
                    f.parameters["rest_position"] = float(-off / k)
            continue
        for label in list(f.parameters):
            v = by_name.get(f"{label}{j}", np.nan)
            if np.isfinite(v):
                f.parameters[label] = float(v)
        for e in result.effects:  # the Coulomb smoothing chosen on the data
            if e.effect == f.effect and e.joint == f.joint and e.setting and f.effect == "coulomb_friction":
                f.parameters.update({k: float(v) for k, v in e.setting})


def _blocks(d: _Data, parts: int = 10) -> tuple[_Data, _Data]:
    """The identification data split into every other tenth: the even tenths to fit on, the
    odd ones held out to choose by (neighbouring samples are not independent, so whole
    blocks, each spanning the trajectory's phases alike)."""
    n = d.q.shape[0]
    block = np.minimum(np.arange(n) * parts // max(n, 1), parts - 1)
    held = block % 2 == 1

    full = d.full_rate

    def take(mask: Array) -> _Data:
        rows = None if full is None else (lambda fn: full(fn)[mask])
        return _Data(d.q[mask], d.qd[mask], d.qdd[mask], d.tau[mask], d.period, None if d.t is None else d.t[mask], rows)

    return take(~held), take(held)


def _noise_floor(validation: list[Prepared]) -> dict[str, Any]:
    """The validation torque's noise, estimated as what a low-pass at the chosen cut-off
    removes (or, without one, at a tenth of the Nyquist frequency), as a relative error."""
    num = den = 0.0
    for seg, sd in _segment_noise(validation):
        num += float(np.sum(sd**2)) * seg.n_samples
        den += float(np.sum(seg.tau**2))
    value = float(np.sqrt(num / den)) if den > 0 else None
    return {"relative_error": value, "how": "the validation torque's content above the low-pass cut-off (white noise spreads "
            "over the whole band; what lies below the cut-off is not counted), over its norm"}


def _noise_levels(experiments: list[Prepared], n_joints: int) -> Array:
    """(N,) each joint's raw torque noise in the identification data: the rms of what a
    low-pass at the chosen cut-off removes (as :func:`_noise_floor`), over all segments."""
    power, count = np.zeros(n_joints), 0
    for seg, sd in _segment_noise(experiments):
        power += sd**2 * seg.n_samples
        count += seg.n_samples
    return np.sqrt(power / max(count, 1))


def _segment_noise(prepared: list[Prepared]) -> list[tuple[Any, Array]]:
    """Each segment with its per-joint torque noise: what a low-pass at its chosen cut-off
    removes (without one, at a tenth of the Nyquist frequency)."""
    from .filtering import ParallelFilter, noise_level

    out = []
    for p in prepared:
        for seg in p.segments:
            filt = seg.parallel if seg.parallel.cutoff_hz is not None else ParallelFilter(seg.parallel.period_s, 0.05 / seg.parallel.period_s)
            out.append((seg, noise_level(seg.tau, filt)))
    return out


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



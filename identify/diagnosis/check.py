"""Does an identified model hold on new data, and if not, what changed (``armid check``).

The model is held fixed: ``tau_hat = M(q, qd, qdd)[:, base] beta`` (eq. 18, with its effect
columns and drive gains) exactly as ``armid identify --json`` wrote it; nothing it identified
is refitted. Its error on the new data is compared with what it showed on its own data (its
fit or validation error, per joint too) and with the new data's noise floor
(:func:`~identify.diagnosis_data.validation_noise_floor`). It *holds* while the new error's power stays
within ``1 + rise`` of the larger of the two (the arm, and each joint with ``joint_rise``).

Where it does not hold, what changed is searched in the new data's residual: the diagnosis's
catalogue (:func:`~identify.diagnosis_candidates.candidate_catalogue`: friction, offsets, gains,
springs, cogging, delays, a tilt) and a **load on the last link**: the ten parameters a rigid
body fixed to link N adds to that link's ``phi_N`` (eq. 10), whose columns are the last ten of
``M`` (eqs. 16-18; the payload of :mod:`identify.payload`, here fitted in batch). Each data
file's time is cut into tenths; a candidate is fitted on the even tenths and scored on the odd
ones, and the other way round (two-fold cross-fitting): it is taken only where it lowers the
held-out error on both folds by a material share of the error above the floor. The errors
before and after are measured at the input's own stamps against the raw torque, each sample
predicted by the fit made without its fold: never on the samples a finding was fitted on.
A load's parameters are fitted on every equation and projected onto the physically possible
ones (its pseudo-inertia positive semidefinite, :func:`~identify.payload_projection.project_feasible`);
standard deviations come from a jackknife over the tenths (the equations of filtered data are
correlated: least squares' own would be several times too small).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..dynamics import regressor
from ..effects import LinearEffect
from ..identifiability import ArmSize
from ..identification import IdentificationResult, base_torque
from ..metrics import summary
from ..payload.projection import project_feasible
from ..preprocess import Prepared
from ..robot import Robot, inertia_entries, inertia_matrix
from ..spatial import Array
from .candidates import Candidate, candidate_catalogue, candidate_parameters, lower_bounds
from .data import StackedData, joint_noise_floors, noise_levels, stack_experiments, validation_noise_floor

__all__ = ["CheckOptions", "CheckResult", "Change", "FixedModel", "Reference", "beyond_motion", "check", "motion_ranges", "where_it_does_not_hold"]

PARTS = 10
"""Each file's time is cut into this many blocks; even and odd ones are the two folds."""


@dataclass(frozen=True, eq=False)
class FixedModel:
    """An identified model held fixed: ``tau = M[:, independent] beta`` (eq. 18 with its effect
    columns), joint j's torque scaled by ``torque_scale[j]`` (a drive gain it declared)."""

    robot: Robot
    effects: tuple[LinearEffect, ...]
    independent: Array
    beta: Array
    torque_scale: Array | None = None
    joint_sigma: Array | None = None

    def torque(self, q: Array, qd: Array, qdd: Array) -> Array:
        """(n, N) the model's torque at each sample of a motion."""
        tau = base_torque(self.robot, list(self.effects), self.independent, self.beta, q, qd, qdd)
        return tau if self.torque_scale is None else tau * self.torque_scale

    def rigid_phi(self) -> Array:
        """(10 N,) standard parameters that reproduce the model's rigid-body torque: its base
        values on their columns, zero elsewhere (the regrouping puts everything there)."""
        n_std = self.robot.n_parameters
        coef = np.zeros(n_std + sum(len(e.parameter_names) for e in self.effects))
        coef[np.asarray(self.independent, int)] = self.beta
        return coef[:n_std]


@dataclass(frozen=True)
class Reference:
    """What the model showed on its own data: the relative error (arm and per joint) and which
    figure it is (``"validation"``: other runs; ``"held_out"``: its identification data where each fold
    was left out of the fit, identify.model_errors; ``"fit"``: its identification data)."""

    relative_error: float
    relative: Array
    kind: str


@dataclass(frozen=True)
class CheckOptions:
    rise: float = 0.5  # the arm's error power may exceed max(reference, floor)^2 by this fraction and the model holds
    joint_rise: float = 1.0  # ... a joint's, by this one (a joint's error scatters more from run to run)
    joint_share: float = 0.05  # ... and a joint's rise counts only where its excess is this share of the arm's error power
    materiality: float = 0.05  # a change must remove this share of the held-out error power above the floor, on each fold
    per_parameter: float = 0.002  # ranking penalty per parameter, as a share of the held-out residual power
    ranked: int = 5  # candidates tried in rank order each round for one that clears the gates
    max_changes: int = 4
    min_speed: float = 0.02  # rad/s: a joint's equation at rest (breakaway friction) is left out, as the diagnosis does
    reversal_margin_s: float = 0.025
    max_cogging_per_turn: int = 60


@dataclass
class Change:
    """One thing found changed: an effect of the catalogue or a load on the last link (``payload``)."""

    effect: str
    joint: int | None  # 0-based; None for the arm
    parameters: dict[str, Any]
    std: dict[str, float]
    error_before: float  # the held-out relative error without it and with it (cross-fitted, at the stamps)
    error_after: float
    torque_rms: float  # its torque's rms at the stamps, on its joint (the joint it moves most)

    def to_json(self) -> dict[str, Any]:
        return {"effect": self.effect, "joint": None if self.joint is None else self.joint + 1, "parameters": self.parameters,
                "std": self.std, "validation": {"relative_error_before": self.error_before, "relative_error_after": self.error_after},
                "torque_rms": self.torque_rms}

    def sentence(self, extrapolating: bool = False) -> str:
        """What changed, in words, with its size and uncertainty (``extrapolating``: the data move
        beyond the model's, so it may be the model's extrapolation instead)."""
        where = "the arm" if self.joint is None else f"joint {self.joint + 1}"
        p, s = self.parameters, self.std
        if self.effect == "payload":
            com = "" if p.get("cx") is None else (", centre of mass [" + ", ".join(f"{100 * p[k]:.1f}" for k in ("cx", "cy", "cz"))
                                                  + "] cm" + ("" if s.get("cx") is None else " +- [" + ", ".join(
                                                      f"{100 * s[k]:.2g}" for k in ("cx", "cy", "cz")) + "] cm"))
            verb = "added to" if p["m"] >= 0 else "removed from"
            what = f"a load of {abs(p['m']):.3f} +- {s['m']:.3f} kg {verb} link {self.joint + 1 if self.joint is not None else '?'} (the last){com}"
        else:
            what = f"{self.effect.replace('_', ' ')} on {where}: " + ", ".join(
                f"{k} {v:.4g}" + (f" +- {s[k]:.2g}" if s.get(k) is not None else "") for k, v in p.items() if isinstance(v, float))
        head = "fits (beyond the model's data: a change, or its extrapolation)" if extrapolating else "changed"
        return f"{head}: {what}; error {100 * self.error_before:.3g} % -> {100 * self.error_after:.3g} % (held out)"


@dataclass
class CheckResult:
    holds: bool
    before: dict[str, Any]  # the fixed model on the new data, at its stamps
    after: dict[str, Any]  # ... with the changes found, each sample predicted by the fit without its fold
    noise_floor: dict[str, Any]
    reference: Reference
    found: list[Change] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    joints_beyond: list[int] = field(default_factory=list)  # 0-based joints whose error rose beyond the rule
    predictions: Array | None = None  # (n, N) at the stamps: the model with what changed (cross-fitted), or the model as it is
    beyond_motion: list[str] = field(default_factory=list)  # where the data move beyond the model's identification data

    def to_json(self) -> dict[str, Any]:
        return {"holds": self.holds, "found": [c.to_json() for c in self.found], "before": self.before, "after": self.after,
                "noise_floor": self.noise_floor,
                "reference": {"relative_error": self.reference.relative_error, "relative": [float(x) for x in self.reference.relative],
                              "kind": self.reference.kind},
                "joints_beyond": [j + 1 for j in self.joints_beyond], "beyond_motion": self.beyond_motion, "notes": self.notes}


def check(model: FixedModel, data: list[Prepared], reference: Reference, options: CheckOptions | None = None) -> CheckResult:
    """The fixed model on ``data``: whether it holds and, where it does not, what changed
    (module docstring)."""
    from threadpoolctl import threadpool_limits

    opts = options or CheckOptions()
    with threadpool_limits(1, "blas"):
        stamps = [s.at_stamps for p in data for s in p.segments]
        tau_s = np.concatenate([st.tau for st in stamps])
        pred_s = np.concatenate([st.as_measured(model.torque(st.q, st.qd, st.qdd)) for st in stamps])
        before = summary(tau_s, pred_s)
        floor = validation_noise_floor(data)
        joint_floor = joint_noise_floors(data) / np.maximum(np.linalg.norm(tau_s, axis=0), 1e-300)
        holds, beyond = _holds(before, floor["relative_error"] or 0.0, joint_floor, reference, opts)
        result = CheckResult(holds, before, before, floor, reference, joints_beyond=beyond, predictions=pred_s)
        if holds:
            return result
        search = _Search(model, data, opts, floor["relative_error"] or 0.0, reference)
        result.found, result.after, result.predictions = search.run()
        result.notes += search.notes
        return result


def where_it_does_not_hold(final: IdentificationResult, validation: list[Prepared]) -> CheckResult | None:
    """What :func:`identify.check.check` says of the validation data against the final model
    (the declared model with the findings, held fixed) where that model does not hold on them:
    an error the findings on the identification data leave well above both the validation's
    floor and the model's own error is no noise; the validation data differ (a load, a
    friction that moved), and the check names what. None where it holds (or a delay, which
    the fixed model does not carry, was found)."""
    if final.delay_s is not None or final.motion_delay_s is not None or not validation:
        return None
    model = FixedModel(final.robot, tuple(final.effects), final.base.independent, final.estimate.beta, final.torque_scale,
                       final.estimate.joint_sigma)
    kind, own = ("held_out", final.held_out) if final.held_out is not None else ("fit", final.fit)
    reference = Reference(float(own["relative_error"]), np.asarray(own["relative"], float), kind)
    result = check(model, validation, reference)
    return None if result.holds else result


def motion_ranges(data: list[Prepared]) -> dict[str, list[float]]:
    """Per joint, what the data span: position (0.5 and 99.5 percentiles), speed and
    acceleration (99.5 percentile of the magnitude). A model is checked on data like these;
    beyond them it extrapolates (``armid identify --json`` writes them as ``motion``)."""
    q = np.concatenate([s.q for p in data for s in p.segments])
    qd = np.concatenate([s.qd for p in data for s in p.segments])
    qdd = np.concatenate([s.qdd for p in data for s in p.segments])
    return {"position_low": np.percentile(q, 0.5, axis=0).tolist(), "position_high": np.percentile(q, 99.5, axis=0).tolist(),
            "speed": np.percentile(np.abs(qd), 99.5, axis=0).tolist(), "acceleration": np.percentile(np.abs(qdd), 99.5, axis=0).tolist()}


def beyond_motion(model_motion: dict[str, list[float]], data: list[Prepared], margin: float = 0.1) -> list[str]:
    """Where ``data`` move beyond what the model was identified on, by more than ``margin`` of
    its range (positions) or of its peak (speed, acceleration): one phrase per joint and kind."""
    new = motion_ranges(data)
    out = []
    for j in range(len(new["speed"])):
        lo, hi = model_motion["position_low"][j], model_motion["position_high"][j]
        span = max(hi - lo, 1e-9)
        if new["position_low"][j] < lo - margin * span or new["position_high"][j] > hi + margin * span:
            out.append(f"joint {j + 1}'s position {new['position_low'][j]:.3g}..{new['position_high'][j]:.3g} against {lo:.3g}..{hi:.3g}")
        for kind in ("speed", "acceleration"):
            if new[kind][j] > (1.0 + margin) * model_motion[kind][j]:
                out.append(f"joint {j + 1}'s {kind} up to {new[kind][j]:.3g} against {model_motion[kind][j]:.3g}")
    return out


def _holds(before: dict[str, Any], floor: float, joint_floor: Array, reference: Reference, opts: CheckOptions) -> tuple[bool, list[int]]:
    """Whether the new error stays within the rule (module docstring), and the joints beyond it."""
    e = before["relative_error"]
    arm_ok = e**2 <= (1.0 + opts.rise) * max(reference.relative_error, floor) ** 2
    rel = np.asarray(before["relative"], float)
    ref = np.maximum(np.asarray(reference.relative, float), joint_floor)
    rms = np.asarray(before["rms"], float)
    # a joint's excess counts where it matters to the arm: its share of the arm's error power
    share = rms**2 * (1.0 - (1.0 + opts.joint_rise) * (ref / np.maximum(rel, 1e-300)) ** 2) / max(float(np.sum(rms**2)), 1e-300)
    beyond = [j for j in range(rel.size) if rel[j] ** 2 > (1.0 + opts.joint_rise) * ref[j] ** 2 and share[j] >= opts.joint_share]
    return bool(arm_ok and not beyond), beyond


def _last_link_columns(robot: Robot, q: Array, qd: Array, qdd: Array) -> Array:
    """(n, N 10) the last link's ten columns of ``M`` (eq. 18) for every joint's row: the torque
    a body fixed to link N adds, linear in its ``phi`` (eq. 10)."""
    m = regressor(robot, q, qd, qdd)
    return np.ascontiguousarray(m[:, :, -10:]).reshape(q.shape[0], -1)


def _tenths(data: list[Prepared], times: list[Array]) -> Array:
    """(n,) each sample's tenth (0..PARTS-1) of its segment's time span, segment by segment."""
    segs = [s for p in data for s in p.segments]
    out = []
    for seg, t in zip(segs, times):
        t0, t1 = float(seg.t[0]), float(seg.t[-1])
        out.append(np.clip(((t - t0) * PARTS / max(t1 - t0, 1e-12)).astype(int), 0, PARTS - 1))
    return np.concatenate(out)


@dataclass(frozen=True)
class _FixedView:
    """The fixed model as the candidates read it (:class:`~identify.diagnosis.candidates.CurrentModel`)."""

    model: FixedModel
    phi: Array
    load: tuple[float, ...]

    def predict(self, d: StackedData) -> Array:
        return self.model.torque(d.q, d.qd, d.qdd)

    def predict_smooth(self, d: StackedData) -> Array:
        return _rigid_torque(self.model, d)


class _Search:
    """Greedy forward selection of changes on the fixed model's residual, cross-fitted over two folds."""

    def __init__(self, model: FixedModel, data: list[Prepared], opts: CheckOptions, floor: float, reference: Reference) -> None:
        self.model, self.opts, self.floor = model, opts, floor
        robot = model.robot
        self.robot, self.nj = robot, robot.n_joints
        self.d = stack_experiments(data)
        segs = [s for p in data for s in p.segments]
        self.tenth = _tenths(data, [s.t[s.parallel.kept(s.n_samples)] for s in segs])
        self.stamps = [s.at_stamps for s in segs]
        self.tenth_s = _tenths(data, [st.t for st in self.stamps])
        self.ds = StackedData(np.concatenate([st.q for st in self.stamps]), np.concatenate([st.qd for st in self.stamps]),
                        np.concatenate([st.qdd for st in self.stamps]), np.concatenate([st.tau for st in self.stamps]),
                        self.d.period, np.concatenate([st.t for st in self.stamps]))
        self.held_s = np.concatenate([np.full(st.t.size, st.held) for st in self.stamps])
        self.segment_s = np.concatenate([np.full(st.t.size, k) for k, st in enumerate(self.stamps)])
        pred = self.d.filtered(functools.partial(_model_torque, model))
        self.r = (self.d.tau - pred).reshape(-1)
        self.pred_s = np.concatenate([st.as_measured(model.torque(st.q, st.qd, st.qdd)) for st in self.stamps])
        self.r_s = self.ds.tau - self.pred_s
        moving = np.abs(self.d.qd) >= np.maximum(opts.min_speed, np.abs(self.d.qdd) * opts.reversal_margin_s)
        sigma = model.joint_sigma if model.joint_sigma is not None else noise_levels(data, self.nj)
        sigma = np.maximum(np.asarray(sigma, float), 1e-9)
        self.wt = (moving / sigma).reshape(-1)
        self.rw = self.r * self.wt
        self.odd = np.repeat(self.tenth % 2 == 1, self.nj)
        self.odd_s = self.tenth_s % 2 == 1
        self.notes: list[str] = []
        self.level = max(floor, reference.relative_error)
        self.reach = ArmSize.of(robot).reach_m
        self.rss_scale = float(self.rw @ self.rw)
        phi = tuple(float(x) for x in model.rigid_phi())
        self.view = _FixedView(model, np.asarray(phi), phi)
        present: set[tuple[str, int | None]] = {(e.effect, e.joint) for e in model.effects}
        if any(p.torque_from_current is False for p in data):  # a joint torque sensor has no torque constant to change
            present |= {("torque_gain", j) for j in range(self.nj)}
            self.notes.append("torque gain not tested: the recordings give joint torque, not current")
        self.candidates = [c for c in candidate_catalogue(robot, self.d, present, self.view, opts.max_cogging_per_turn)
                           if c.effect != "time_delay"] + [self._payload()]

    def _payload(self) -> Candidate:
        robot, scale = self.robot, self.model.torque_scale

        def columns(d: StackedData) -> Array:
            cols = d.filtered(functools.partial(_last_link_columns, robot)).reshape(-1, self.nj, 10)
            if scale is not None:
                cols = cols * np.asarray(scale)[None, :, None]
            return cols.reshape(-1, 10)

        return Candidate("payload", self.nj - 1, (), ("m", "msx", "msy", "msz", "Ixx", "Ixy", "Ixz", "Iyy", "Iyz", "Izz"), full=columns)

    # --- the fits: each fold's normal equations, a candidate's on its own rows ---
    def _weighted(self, c: Candidate) -> tuple[Array, int | None]:
        """``c``'s weighted columns and the joint whose rows they live on (None: every row)."""
        if c.block is not None and c.joint is not None:
            return c.block(self.d) * self.wt[c.joint :: self.nj, None], c.joint
        return c.columns(self.d) * self.wt[:, None], None

    def _product(self, a: tuple[Array, int | None], b: tuple[Array, int | None], fold: Array) -> Array:
        """``A^T B`` over the fold's rows, each on its own rows (zero where they share none)."""
        (ca, ja), (cb, jb) = a, b
        if ja is None and jb is None:
            return ca[fold].T @ cb[fold]
        if ja is not None and jb is not None:
            f = fold[ja :: self.nj]
            return ca[f].T @ cb[f] if ja == jb else np.zeros((ca.shape[1], cb.shape[1]))
        if ja is None:
            return self._product(b, a, fold).T
        f = fold[ja :: self.nj]
        return ca[f].T @ cb[ja :: self.nj][f]

    def _moments(self, cols: list[tuple[Array, int | None]], masks: list[Array] | None = None) -> list[tuple[Array, Array, float]]:
        """Per set of rows (by default the folds: even, odd tenths): ``Z^T Z``, ``Z^T r`` and
        ``r^T r`` of the weighted rows."""
        starts = np.cumsum([0] + [c.shape[1] for c, _ in cols])
        out = []
        for fold in ([~self.odd, self.odd] if masks is None else masks):
            g, b = np.zeros((starts[-1], starts[-1])), np.zeros(starts[-1])
            for i, a in enumerate(cols):
                si = slice(starts[i], starts[i + 1])
                b[si] = self._product(a, (self.rw[:, None], None), fold)[:, 0]
                for k in range(i, len(cols)):
                    sk = slice(starts[k], starts[k + 1])
                    g[si, sk] = self._product(a, cols[k], fold)
                    g[sk, si] = g[si, sk].T
            out.append((g, b, float(self.rw[fold] @ self.rw[fold])))
        return out

    @staticmethod
    def _solve(g: Array, b: Array, lower: Array) -> Array:
        """Least squares from its normal equations with each parameter's lower bound (friction
        >= 0); a small ridge keeps a direction the data do not see at zero, not at noise."""
        if not g.size:
            return np.zeros(0)
        g = g + 1e-10 * max(float(np.trace(g)) / g.shape[0], 1e-300) * np.eye(g.shape[0])
        x = np.linalg.solve(g, b)
        if np.any(x < lower):
            from ..estimation import bounded_quadratic

            x = bounded_quadratic(g, b, lower)
        return x

    def _held_out(self, moments: list[tuple[Array, Array, float]], lower: Array) -> tuple[float, float]:
        """Each fold's weighted residual power predicted by the fit on the other."""
        out = []
        for fit, score in ((moments[0], moments[1]), (moments[1], moments[0])):
            x = self._solve(fit[0], fit[1], lower)
            g, b, rr = score
            out.append(rr - 2.0 * float(x @ b) + float(x @ g @ x))
        return out[1], out[0]

    def run(self) -> tuple[list[Change], dict[str, Any], Array]:
        """The changes found, in order, and the error after them (cross-fitted, at the stamps).

        Each round ranks every candidate by its held-out power on the equations, then takes the
        first of the best ``ranked`` that lowers the held-out error at the stamps on both folds
        by a material share of the error above ``level`` (the larger of the floor and the
        model's own error); the search stops once the model with the changes holds again
        (what is left is the model's own misfit or noise, not a change)."""
        chosen: list[Candidate] = []
        cols: list[tuple[Array, int | None]] = []
        lower = np.zeros(0)
        errors = [self._cross_fitted_error(chosen)]
        keys = {(c.effect, c.joint) for c in self.candidates}
        for _ in range(self.opts.max_changes):
            e0 = errors[-1][1]["relative_error"]
            if e0**2 <= (1.0 + self.opts.rise) * self.level**2:
                break
            ranked = []
            for c in self.candidates:
                if (c.effect, c.joint) in keys:
                    trial_cols = cols + [self._weighted(c)]
                    lc = np.concatenate([lower, lower_bounds(c)])
                    trial = self._held_out(self._moments(trial_cols), lc)
                    ranked.append((sum(trial) + self.opts.per_parameter * len(c.labels) * self.rss_scale, c, trial_cols, lc))
            ranked.sort(key=lambda x: x[0])
            for _, c, trial_cols, lc in ranked[: self.opts.ranked]:
                pred, err = self._cross_fitted_error(chosen + [c])
                if not self._material(errors[-1][0], pred) or not self._plausible(c, trial_cols, lc):
                    continue
                chosen.append(c)
                keys = {k for k in keys if k != (c.effect, c.joint)} - _same_joint_friction(c)
                cols, lower = trial_cols, lc
                errors.append((pred, err))
                break
            else:
                break
        return self._describe(chosen, cols, lower, errors), errors[-1][1], errors[-1][0]

    def _material(self, before: Array, after: Array) -> bool:
        """Whether ``after`` lowers the stamps' error on each fold by ``materiality`` of its
        power above ``level`` (each fold predicted by the fit on the other)."""
        tau = self.ds.tau
        for fold in (self.odd_s, ~self.odd_s):
            norm = float(np.sum(tau[fold] ** 2))
            e0, e1 = float(np.sum((tau[fold] - before[fold]) ** 2)) / norm, float(np.sum((tau[fold] - after[fold]) ** 2)) / norm
            if not (e1 < e0 and e0 - e1 >= self.opts.materiality * max(e0 - self.level**2, 0.0)):
                return False
        return True

    def _plausible(self, c: Candidate, cols: list[tuple[Array, int | None]], lower: Array) -> bool:
        """A load is a body fixed to the last link: its mass clear of its uncertainty (3 sigma,
        jackknife over the tenths), and the body within the arm's reach of that link's frame
        (its centre of mass, and its second moment ``tr(Sigma) <= m R^2``, ``Sigma = tr(I)/2 1 - I``
        about the frame). A fit that is none of these stands for the model's own error in the
        last link's parameters, not a load: set aside, and said."""
        if c.effect != "payload":
            return True
        g, b, _ = self._moments(cols, [np.ones(self.r.size, bool)])[0]
        theta = self._solve(g, b, lower)[-10:]
        tenth_rows = np.repeat(self.tenth, self.nj)
        leave_out = np.array([self._solve(gk, bk, lower)[-10:] for gk, bk, _ in self._moments(cols, [tenth_rows != k for k in range(PARTS)])])
        dev = leave_out - leave_out.mean(axis=0)
        sign = 1.0 if theta[0] >= 0 else -1.0
        body = sign * _projected(sign * theta, _information_metric(g)[-10:, -10:])  # the nearest possible body (removed: negated)
        std_m = float(np.sqrt((PARTS - 1) / PARTS * np.sum(dev[:, 0] ** 2)))
        m, reach = float(body[0]), self.reach
        second = 0.5 * float(np.trace(inertia_matrix(body[4:10])))  # tr(Sigma) = tr(I) / 2
        why = None
        if abs(m) <= 3.0 * std_m:
            why = f"its mass {m:.3g} +- {std_m:.2g} kg is not clear of its uncertainty"
        elif float(np.linalg.norm(body[1:4] / m)) > reach:
            why = f"its centre of mass would lie {float(np.linalg.norm(body[1:4] / m)):.2f} m from the last link's frame"
        elif np.sign(m) * second > abs(m) * reach**2:
            why = f"its second moment {abs(second):.3g} kg*m^2 needs a body larger than the arm ({abs(m) * reach**2:.3g} at most)"
        if why is not None:
            note = f"set aside: a load on the last link fits ({why}; the arm's reach is {reach:.2f} m): the model's own error there, not a load"
            if not any(n.startswith("set aside: a load") for n in self.notes):  # the best-ranked load's reason; the later rounds' alike
                self.notes.append(note)
            return False
        return True

    def _stamp_columns(self, chosen: list[Candidate]) -> Array:
        """(rows, k) the chosen candidates' columns at the stamps (unfiltered: the raw torque's)."""
        cols = [c.columns(self.ds) for c in chosen]
        z = np.column_stack(cols) if cols else np.zeros((self.ds.y.size, 0))
        if np.any(self.held_s):  # a torque held over the period before its stamp: the mean of the two ends
            zz = z.reshape(-1, self.nj, z.shape[1]).copy()
            for k in np.unique(self.segment_s[self.held_s]):
                idx = np.flatnonzero(self.segment_s == k)
                zz[idx[1:]] = 0.5 * (zz[idx[1:]] + zz[idx[:-1]])
            z = zz.reshape(-1, z.shape[1])
        return z

    def _cross_fitted_error(self, chosen: list[Candidate]) -> tuple[Array, dict[str, Any]]:
        """The stamps' prediction with ``chosen`` added, each fold from the fit on the other, and its summary."""
        if not chosen:
            return self.pred_s, summary(self.ds.tau, self.pred_s)
        moments = self._moments([self._weighted(c) for c in chosen])
        lower = np.concatenate([lower_bounds(c) for c in chosen])
        zs = self._stamp_columns(chosen)
        flat = self.pred_s.copy().reshape(-1)
        odd_rows = np.repeat(self.odd_s, self.nj)
        for fit, fold in ((moments[0], odd_rows), (moments[1], ~odd_rows)):
            x = self._solve(fit[0], fit[1], lower)
            flat[fold] += (zs @ x)[fold]
        pred = flat.reshape(self.pred_s.shape)
        return pred, summary(self.ds.tau, pred)

    def _describe(self, chosen: list[Candidate], cols: list[tuple[Array, int | None]], lower: Array,
                  errors: list[tuple[Array, dict[str, Any]]]) -> list[Change]:
        """Each change's parameters fitted on every equation (a load projected onto the possible
        ones), with jackknife standard deviations over the tenths."""
        if not chosen:
            return []
        tenth_rows = np.repeat(self.tenth, self.nj)
        g, b, _ = self._moments(cols, [np.ones(self.r.size, bool)])[0]
        x = self._solve(g, b, lower)
        leave_out = np.array([self._solve(gk, bk, lower) for gk, bk, _ in self._moments(cols, [tenth_rows != k for k in range(PARTS)])])
        dev = leave_out - leave_out.mean(axis=0)
        cov = (PARTS - 1) / PARTS * dev.T @ dev
        metric = _information_metric(g)
        out, col = [], 0
        for k, c in enumerate(chosen):
            n = len(c.labels)
            xc, cc, lo = x[col : col + n], cov[col : col + n, col : col + n], leave_out[:, col : col + n]
            col += n
            prev, after = errors[k][0], errors[k + 1][0]
            change = np.sqrt(np.mean((after - prev) ** 2, axis=0))
            joint = c.joint if c.joint is not None else int(np.argmax(change))
            if c.effect == "payload":
                params, std = _load(xc, metric[col - n : col, col - n : col], cc, lo)
            else:
                params = candidate_parameters(c, xc)
                sd = np.sqrt(np.maximum(np.diag(cc), 0.0))
                std = {label: float(s) for label, s in zip(c.labels, sd)} if c.effect not in ("cogging", "spring", "torque_gain") else {}
            out.append(Change(c.effect, c.joint, params, std, errors[k][1]["relative_error"], errors[k + 1][1]["relative_error"],
                              float(change[joint])))
        return out


def _model_torque(model: FixedModel, q: Array, qd: Array, qdd: Array) -> Array:
    return model.torque(q, qd, qdd)


def _rigid_torque(model: FixedModel, d: StackedData) -> Array:
    """The model's rigid-body torque (no friction's steps) at ``d``'s samples."""
    tau = regressor(model.robot, d.q, d.qd, d.qdd) @ model.rigid_phi()
    return tau if model.torque_scale is None else tau * model.torque_scale


def _same_joint_friction(c: Candidate) -> set[tuple[str, int | None]]:
    """Candidates a friction finding makes redundant on its joint (a Stribeck term carries its Coulomb level)."""
    if c.effect in ("stribeck_friction", "coulomb_friction", "load_dependent_coulomb"):
        return {(e, c.joint) for e in ("stribeck_friction", "coulomb_friction", "load_dependent_coulomb")}
    return set()


def _information_metric(g: Array) -> Array:
    """``(Z^T W Z)^-1`` of the weighted normal equations: the shape of least squares'
    uncertainty, in which a projection moves the directions the data barely see (a load's
    inertia) and keeps the ones they fix (its mass, its first moment). The jackknife's ten
    fits cannot give it: their covariance has rank 9 at most, for ten parameters."""
    return np.linalg.inv(g + 1e-12 * max(float(np.trace(g)) / max(g.shape[0], 1), 1e-300) * np.eye(g.shape[0]))


def _projected(theta: Array, metric: Array) -> Array:
    """The physically possible body nearest ``theta`` in the metric ``metric^-1`` (:func:`_information_metric`)."""
    return project_feasible(theta, metric)


def _load(theta: Array, metric: Array, cov: Array, leave_out: Array) -> tuple[dict[str, Any], dict[str, float]]:
    """A load's mass, centre of mass and inertia about it from its ten parameters about the
    last link's frame (eq. 10, Steiner), projected onto the physically possible bodies in the
    data's metric; a removed load (negative mass) is projected as the body removed. Standard
    deviations of the mass and the centre from the jackknife's fits (``cov``, ``leave_out``)."""
    sign = 1.0 if theta[0] >= 0 else -1.0
    body = _projected(sign * theta, metric)

    def com(phi: Array) -> Array:
        return phi[1:4] / phi[0] if abs(phi[0]) > 1e-9 else np.full(3, np.nan)

    m = float(body[0])
    std_m = float(np.sqrt(max(cov[0, 0], 0.0)))
    params: dict[str, Any] = {"m": sign * m}
    std: dict[str, float] = {"m": std_m}
    # the centre of mass is read where the mass is clear of its own uncertainty
    if m > 3.0 * std_m and m > 0:
        c = com(body)
        cs = np.array([com(sign * lo) for lo in leave_out])
        c_std = np.sqrt((leave_out.shape[0] - 1) / leave_out.shape[0] * np.sum((cs - cs.mean(axis=0)) ** 2, axis=0))
        inertia_c = inertia_matrix(body[4:10]) - m * (float(c @ c) * np.eye(3) - np.outer(c, c))
        params.update({"cx": float(c[0]), "cy": float(c[1]), "cz": float(c[2])})
        params.update({f"I{k}": float(v) for k, v in zip(("xx", "xy", "xz", "yy", "yz", "zz"), inertia_entries(inertia_c))})
        std.update({"cx": float(c_std[0]), "cy": float(c_std[1]), "cz": float(c_std[2])})
    else:
        params.update({"cx": None, "cy": None, "cz": None})
    return params, std

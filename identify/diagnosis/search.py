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
there and on no other run, and (g) that exact fit, which holds friction, rotor inertia and a
spring's stiffness at 0 (physics), does not hold the finding's there: it would explain
nothing. Then refit and repeat, until nothing passes. The findings are fitted with the prior as
wide as the declared model's fit or the last accepted finding's found it, whichever is less. A candidate whose columns lie in the span of the model is
absorbed (rotor inertia of a first joint with a vertical axis joins ``Izz1``), and is
reported as such. An offset is judged as the smaller of a nested pair: the spring on its joint
(``q`` and an offset) is named where its stiffness is a finding beside it (:meth:`DiagnosisSearch._nesting`).
When a look-alike (Coulomb/Stribeck, torque gain/rotor inertia,
delay/viscous) explains nearly as much, both are named with the experiment that would
separate them.

Before and after are then fitted as ``identify`` fits (:func:`findings_model`): before is the
declared model exactly as ``armid identify`` gives it, after the same with the findings added.
A position-dependent finding (spring, cogging) whose joint the validation moves beyond the
positions it was found on is reported as extrapolated: held-out tenths of one motion cannot
tell a spring from the local slope of a ripple longer than that motion.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy import stats

from ..equations import reused_equations
from ..errors import PoorExcitationWarning
from ..identification import (
    IdentificationResult,
    declared_gains,
    identify,
    structural_base,
)
from ..metrics import masked_summary, summary
from ..preprocess import Prepared
from ..robot import Robot
from ..spatial import Array
from .candidates import LOOKALIKES, NESTING, SEPARATE, STRIBECK_VELOCITIES, Candidate, candidate_catalogue, candidate_parameters, coulomb
from .check import where_it_does_not_hold
from .data import joint_noise_floors, noise_levels, relative_error, split_blocks, stack_experiments, validation_noise_floor
from .refit import (
    coulomb_level,
    findings_model,
    merge_offset_into_spring,
    prior_widening,
    refine_delays,
    rotation_matrix,
    sign_reversed,
    trial_fit,
    update_parameters,
)
from .report import (
    MATERIALITY,
    Diagnosis,
    Finding,
    extrapolated_findings,
    extrapolation_sentence,
    negligible_sentence,
    set_aside_sentence,
)
from .scoring import (
    AbsorbedCandidate,
    RoundModel,
    ScoredCandidate,
    f_sf,
    fit_round,
    full_parameters,
    joint_power_after,
    round_moments,
    score_candidate,
)
from .state import (
    DiagnoseOptions,
    ExactFits,
    FindingsSoFar,
    ModelSoFar,
    RoundView,
    SearchData,
    declared_fit,
    moving_equations,
)
from .validation import VETO_BLOCKS, joint_validation_errors, material_drop, validation_error, worse_on_validation

__all__ = ["MATERIALITY", "DiagnoseOptions", "DiagnosisSearch", "Diagnosis", "Finding", "diagnose", "extrapolation_sentence", "findings_model",
           "negligible_sentence", "set_aside_sentence"]
"""The diagnosis's public names; the catalogue, the data, the search's state, the scoring, the
report and the refits live in the other modules of ``identify/diagnosis/``."""


def diagnose(robot: Robot, experiments: list[Prepared], validation: list[Prepared], options: DiagnoseOptions | None = None) -> Diagnosis:
    """Find, add and report the undeclared effects (module docstring).

    Findings are ranked on held-out blocks of the identification data (every other tenth of
    it, fitted on the rest); ``validation`` can only veto one (gate f) and measures the errors
    before and after, so the figures reported are not the ones the search optimised.

    On one BLAS thread: its products are small (a candidate's few columns against the
    model's), and OpenBLAS's threads on them cost several times the work on a 2-core machine
    (22.8x the plain pipeline, issue 34; ``benchmarks/bench_diagnose.py``). Its fits share
    each recording's filtered equations (:func:`~identify.equations.reused_equations`)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1, "blas"), reused_equations():
        search = DiagnosisSearch(robot, experiments, validation, options or DiagnoseOptions())
        for _ in range(search.opts.max_findings):
            if not search.add_one():
                break
        diagnosis = search.report()
    diagnosis.differs = where_it_does_not_hold(search.final_fit, validation)
    return diagnosis


@dataclass(eq=False)
class _Pick:
    """The candidate a round adds, with the held-out prediction before and after it and its
    held-out columns (None when it is applied exactly: a tilt, a gain, a delay)."""

    scored: ScoredCandidate
    columns_v: Array | None
    pred_before: Array
    pred_after: Array


class DiagnosisSearch:
    """One diagnosis from the declared model on, its state one record per idea
    (:mod:`identify.diagnosis.state`): the gates' settings (``opts``), the data (``data``,
    shifted by the delays found), the model so far (``model``: the gravity as tilted, the drive
    gains and delays found, the findings' columns; ``view``, what the candidates read of it), what
    was found, absorbed and set aside (``findings``) and the exact fits the gates judge by
    (``exact``). :meth:`add_one` is a round, :meth:`report` fits before and after as
    ``identify`` fits them."""

    def __init__(self, robot: Robot, experiments: list[Prepared], validation: list[Prepared], opts: DiagnoseOptions) -> None:
        self.opts = opts
        ident_all, valid = stack_experiments(experiments), stack_experiments(validation)
        ident, held = split_blocks(ident_all)
        self.model = model = ModelSoFar.declared(robot, declared_fit(robot, experiments, validation))
        validation_segments = [sg for p in validation for sg in p.segments]
        self.data = data = SearchData(experiments, validation, ident_all, valid, ident, held, robot.n_joints,
                                      min(s.parallel.period_s for p in experiments for s in p.segments), validation_segments,
                                      np.concatenate([sg.at_stamps.tau for sg in validation_segments]),
                                      noise_levels(experiments, robot.n_joints))
        model.rebuild_columns(data)
        data.whiten(model.wi, opts)
        model.extra_i, model.extra_v = np.zeros((data.yi.size, 0)), np.zeros((data.yv.size, 0))
        self.view = RoundView(model)
        self.findings = FindingsSoFar({(e.effect, e.joint) for e in model.effects} | {("torque_gain", j) for j in declared_gains(robot)})
        if any(p.torque_from_current is False for p in experiments):
            # a drive gain is a torque constant's error: a joint torque sensor has none between it and the model
            self.findings.present |= {("torque_gain", j) for j in range(data.nj)}
            self.findings.notes.append("torque gain not tested: the recordings give joint torque, not current"
                                       if all(p.torque_from_current is False for p in experiments) else
                                       "torque gain not tested: some recordings give joint torque, not current (one gain cannot hold for both)")
        self.exact = ExactFits(prior_widening(model.result0))

    # --- a round ---
    def add_one(self) -> bool:
        """Score every candidate against the model so far and add the best-ranked one that
        clears its gates (module docstring); False when none does (the search ends)."""
        rnd = fit_round(self.model.wi, self.model.wv, self.model.extra_i, self.model.extra_v, self.data.yi, self.data.yv, self.data.wt_i, self.data.wt_v, self.data.nj)
        self._predictions(rnd)
        scored = self._scored(rnd)
        if not scored:
            return False
        self._rank(rnd, scored)
        pick = self._pick(rnd, scored)
        if pick is None:
            return False
        self._add(rnd, scored, pick)
        return True

    def _predictions(self, rnd: RoundModel) -> None:
        """What the candidates' columns read of the model so far (:class:`RoundView`): its
        prediction, the same without friction's steps, its standard parameters and a
        load-dependent friction's load."""
        beta, p_base, base, view = rnd.beta, rnd.p_base, self.model.base, self.view
        view.beta = beta[:p_base]
        # the delay's derivative leaves out Coulomb friction: a step in sign(qd) shifted by a
        # sample is a spike at every reversal, which would fit friction's misfit near rest
        smooth = beta[:p_base] * np.array([not base.names[c].startswith(("fc", "fs", "fl")) for c in base.independent])
        view.smooth = smooth
        view.phi = full_parameters(self.model.robot, base, beta[:p_base], self.model.n_cols)
        # a load-dependent friction's load: the modeled rigid body where the robot file models
        # every link (the fit so far has the friction it lacks in its rigid-body parameters),
        # else the fit's own (its base parameters in their columns, as identify's passes take it)
        load = self.model.modeled
        if load is None:
            fitted = np.zeros(self.model.n_cols)
            fitted[base.independent] = beta[:p_base]
            load = fitted[: self.model.robot.n_parameters]
        view.load = tuple(float(x) for x in load)

    def _scored(self, rnd: RoundModel) -> list[ScoredCandidate]:
        """Every candidate not present scored against the round (:func:`score_candidate`); one whose columns
        lie in the model's span is reported as absorbed."""
        scored: list[ScoredCandidate] = []
        candidates = candidate_catalogue(self.model.robot, self.data.ident, self.findings.present | self.findings.absorbed_keys, self.view, self.opts.max_cogging_per_turn)
        moments = round_moments(candidates, rnd, self.data.ident, self.data.held, self.data.wt_i, self.data.wt_v)
        for c in candidates:
            s = score_candidate(c, rnd, self.data.ident, self.data.held, self.data.wt_i, self.data.wt_v, self.data.n_used, self.data.sample_period, moments.get(id(c)))
            if isinstance(s, AbsorbedCandidate):
                self._absorb(c, s.projection, rnd)
            elif s is not None:
                scored.append(s)
        return scored

    def _absorb(self, c: Candidate, projection: Array, rnd: RoundModel) -> None:
        """A candidate in the span of the model (rotor inertia of a first joint with a vertical
        axis joins ``Izz1``): reported once, with the base parameter it joins."""
        key = (c.effect, c.joint)
        if key not in self.findings.absorbed_keys:
            coef = np.linalg.lstsq(rnd.r_mat, projection, rcond=None)[0]
            exprs = self.model.base.expressions()
            top = int(np.argmax(np.abs(coef[:, 0])))
            self.findings.absorbed.append({"effect": c.effect, "joint": None if c.joint is None else c.joint + 1,
                                  "into": exprs[top] if top < len(exprs) else "an effect found earlier"})
            self.findings.absorbed_keys.add(key)

    def _rank(self, rnd: RoundModel, scored: list[ScoredCandidate]) -> None:
        """Best first by held-out residual power, each added parameter paying its penalty; an
        arm-wide delay claims every joint: it must explain clearly more (arm_margin) than the
        same effect on the one joint that explains most, or that joint's is preferred."""
        scored.sort(key=lambda s: s.rss_v / rnd.rss_v + self.opts.per_parameter * len(s.gamma))
        for effect in ("time_delay",):
            arm = next((x for x in scored if x.candidate.effect == effect and x.candidate.joint is None), None)
            one = next((x for x in scored if x.candidate.effect == effect and x.candidate.joint is not None), None)
            if arm is not None and one is not None and (rnd.rss_v - arm.rss_v) < self.opts.arm_margin * (rnd.rss_v - one.rss_v):
                scored.remove(arm)
        self.findings.rounds.append([(f"{s.candidate.effect}@{s.candidate.joint}", 1.0 - s.rss_v / rnd.rss_v) for s in scored[:5]])

    # --- the gates ---
    def _pick(self, rnd: RoundModel, scored: list[ScoredCandidate]) -> _Pick | None:
        """The best-ranked candidate that clears its gates (the ranking still favours the larger
        effect); None when none of the first ``ranked`` does."""
        for ranked in scored[: self.opts.ranked]:
            shape = self._friction_shape(rnd, scored, ranked)
            shape = self._nesting(rnd, scored, shape)
            for s in [shape] + ([ranked] if shape is not ranked else []):  # the Stribeck term or spring named, else the Coulomb or offset itself
                pick = self._gated(rnd, s)
                if pick is not None:
                    return pick
        return None

    def _gated(self, rnd: RoundModel, s: ScoredCandidate) -> _Pick | None:
        """``s`` as the round's pick if it clears gates (c), (a)-(b), (e), then (d) and (f)."""
        if s.p_value > self.opts.alpha:
            return None  # (c) the F-test on the identification data
        pred_before = rnd.a_v @ rnd.beta
        cv, pred_after = self._refit_prediction(rnd, s)
        if not self._clears_held_out(rnd, s, pred_before, pred_after):
            return None
        if not self._clears_noise(s, pred_before, pred_after):
            return None
        if (s.candidate.effect, s.candidate.joint) in self.findings.set_aside:
            return None  # another setting of an effect already set aside
        if not self._clears_exact_fits(s):
            return None
        return _Pick(s, cv, pred_before, pred_after)

    def _friction_shape(self, rnd: RoundModel, scored: list[ScoredCandidate], s: ScoredCandidate) -> ScoredCandidate:
        """A joint's friction named by the held-out blocks of its joint: Coulomb, or the shape of
        two parameters with its Coulomb level that leaves the least there (a Stribeck peak at
        its velocity, a load-dependent term) where that leaves less than Coulomb and viscous
        friction together (both bounded at 0). Coulomb alone ranks first where the shape's term
        is small (one parameter fewer), and a term found next would bend to the rest; the
        shape's term is then judged by the materiality (:meth:`_material`). On the joint's rows,
        not the arm's: the rows are whitened by the declared model's residual, in which the
        friction sought inflates its own joint's level (blind Stribeck seed 11: the true peak
        took joint 3's held-out error from 1.67 to 0.31 N*m and lost to Coulomb on the arm's
        whitened sum; with the Coulomb level found first, the load term of load-Coulomb seed 57
        removed 0.08 % of the arm's whitened residual and was not found).
        Returns the candidate to judge."""
        c = s.candidate
        if c.effect != "coulomb_friction" or c.joint is None:
            return s
        j = c.joint
        shapes = [x for x in scored if x.candidate.joint == j and "fc" in x.candidate.labels
                  and (x.candidate.effect == "load_dependent_coulomb" or (x.candidate.effect == "stribeck_friction"
                       and dict(x.candidate.setting)["velocity"] > STRIBECK_VELOCITIES[0]))]  # the lowest: a Coulomb step's smoothing
        if not shapes:
            return s
        left = {id(x): joint_power_after(x, rnd, self.data.held, self.data.wt_v) for x in [s, *shapes]}
        shape = min(shapes, key=lambda x: left[id(x)])
        rival = left[id(s)]
        if ("viscous_friction", j) not in self.findings.present:
            both = Candidate("coulomb_friction", j, (), ("fc", "fv"),
                             block=lambda d: np.column_stack([coulomb(d, j)[:, 0], d.qd[:, j]]))
            cv = score_candidate(both, rnd, self.data.ident, self.data.held, self.data.wt_i, self.data.wt_v, self.data.n_used, self.data.sample_period)
            rival = min(rival, joint_power_after(cv, rnd, self.data.held, self.data.wt_v)) if isinstance(cv, ScoredCandidate) else rival
        return shape if left[id(shape)] < rival else s

    def _nesting(self, rnd: RoundModel, scored: list[ScoredCandidate], s: ScoredCandidate) -> ScoredCandidate:
        """A joint's offset named by the one effect that holds it: the spring (``q`` and an offset,
        :data:`NESTING`) where its stiffness passes an F-test at ``alpha`` against the offset's
        refit and removes ``min_gain_joint`` of what the offset leaves on its joint's held-out
        rows (the flat penalty per parameter had preferred the offset where the spring's rest
        lies beyond its motion: blind spring seed 6306). Returns the spring, else ``s``."""
        c = s.candidate
        bigger = NESTING.get(c.effect)
        if bigger is None or c.joint is None or c.block is None:
            return s
        big = next((x for x in scored if x.candidate.effect == bigger and x.candidate.joint == c.joint
                    and set(c.labels) < set(x.candidate.labels)), None)
        if big is None or not np.isfinite(big.rss) or not np.isfinite(s.rss):
            return s
        extra = len(big.candidate.labels) - len(c.labels)
        dof = self.data.n_used - rnd.a_i.shape[1] - len(big.candidate.labels)
        f_stat = ((s.rss - big.rss) / extra) / max(big.rss / dof, 1e-300)
        if f_sf(f_stat, extra, dof) > self.opts.alpha:
            return s
        left_small = joint_power_after(s, rnd, self.data.held, self.data.wt_v)
        left_big = joint_power_after(big, rnd, self.data.held, self.data.wt_v)
        return big if left_small - left_big >= self.opts.min_gain_joint * left_small else s

    def _refit_prediction(self, rnd: RoundModel, s: ScoredCandidate) -> tuple[Array | None, Array]:
        """The candidate's held-out columns (None for one fitted exactly) and the held-out
        prediction of the refit with it."""
        if s.exact_prediction is not None:
            return None, s.exact_prediction
        assert s.projection is not None
        beta_c = rnd.beta - np.linalg.solve(rnd.r_mat, s.projection @ s.gamma)
        cv = s.candidate.columns(self.data.held)
        return cv, rnd.a_v @ beta_c + cv @ s.gamma

    def _clears_held_out(self, rnd: RoundModel, s: ScoredCandidate, pred_before: Array, pred_after: Array) -> bool:
        """Gates (a) and (b), on the held-out tenths. A joint's effect is judged by its joint's
        residual (on 6-7 joints a perfect fix of one joint removes about 1/N of the arm's): it
        must remove min_gain_joint of that joint's held-out residual power and cut that joint's
        error by min_error_drop, and the arm's by min_arm_drop; one that acts on every joint's
        row (a delay, a tilt, friction everywhere) min_gain of the whole arm's."""
        opts, nj, yv, best = self.opts, self.data.nj, self.data.yv, s.candidate
        if best.block is None:
            if s.rss_v > (1.0 - opts.min_gain) * rnd.rss_v:
                return False
            if s.power_after is not None and nj > 1:
                # an effect of the arm must show on the arm: what it removes from the joints
                # other than the one it helps most must be min_gain of their power too (a
                # tilt bent to fit one joint's unmodeled position-dependent torque helps that
                # joint alone and leaves the others as they were, or worse)
                drop = rnd.power_before - s.power_after
                top = int(np.argmax(drop))
                rest = float(np.sum(rnd.power_before) - rnd.power_before[top])
                if float(np.sum(drop) - drop[top]) < opts.min_gain * rest:
                    return False
            return True
        rows = (self.data.wt_v > 0) & (np.arange(yv.size) % nj == best.joint)
        own = float(np.sum(rnd.res_v[rows] ** 2))
        if rnd.rss_v - s.rss_v < opts.min_gain_joint * own:
            return False
        if relative_error(yv * rows, pred_after * rows) > (1.0 - opts.min_error_drop) * relative_error(yv * rows, pred_before * rows):
            return False  # it whitens the residual but does not move the error anyone reads
        used = self.data.wt_v > 0
        if relative_error(yv * used, pred_after * used) > (1.0 - opts.min_arm_drop) * relative_error(yv * used, pred_before * used):
            return False  # ... nor the arm's: a joint whose torque is a thousandth of the others
        return True

    def _clears_noise(self, s: ScoredCandidate, pred_before: Array, pred_after: Array) -> bool:
        """Gate (e): what it changes in the prediction is at least min_noise_fraction of the
        torque's own noise (its joint's, or the arm's); far below it, it is not what anyone
        measuring the torque would see."""
        opts, best = self.opts, s.candidate
        change = (pred_after - pred_before).reshape(-1, self.data.nj)
        if best.joint is not None:
            if float(np.sqrt(np.mean(change[:, best.joint] ** 2))) < opts.min_noise_fraction * self.data.noise_sd[best.joint]:
                return False
        elif float(np.sqrt(np.mean(np.sum(change**2, axis=1)))) < opts.min_noise_fraction * float(np.sqrt(np.sum(self.data.noise_sd**2))):
            return False
        return True

    def _clears_exact_fits(self, s: ScoredCandidate) -> bool:
        """Gates (g), (d) and (f), judged by exact fits: the model with the finding added as
        `identify` fits it. A further tilt or delay corrects one found before and is not judged
        again. A candidate that fails any is set aside (reported, not taken)."""
        best, opts = s.candidate, self.opts
        if best.effect in ("gravity_tilt", "time_delay") and any(f.effect == best.effect and f.joint == best.joint for f in self.findings.found):
            return True
        trial = Finding(best.effect, best.joint, candidate_parameters(best, s.gamma), 0.0, 0.0, 0.0)
        fit_with = self.trial_fit(self.findings.found + [trial])
        if self._held_at_bound(best, trial, fit_with):
            return False
        widening = prior_widening(fit_with)
        if self.exact.widening_now is not None and (widening is None or widening > opts.max_prior_widening * self.exact.widening_now):
            # (d) on the identification data: the prior's widening with the finding
            self.findings.conflicting.append({"effect": best.effect, "joint": None if best.joint is None else best.joint + 1,
                                     "parameters": trial.parameters, "before": self.exact.widening_now,
                                     "prior_widened_by": widening if widening is not None and np.isfinite(widening) else None,
                                     "reason": "prior"})
            self.findings.put_aside(best)
            return False
        # (f) on the validation data: its joint's error (the arm's) must not rise there
        # consistently. Tenths of one trajectory share its excitation; a fit's own model
        # error (the modeled values the prior holds where the data are silent) can look
        # like a spring on them and on no other run (a clean 100 Hz blind case)
        res_before, res_with = self._validation_residual(self.findings.found), self._validation_residual(self.findings.found + [trial])
        cols = slice(None) if best.joint is None else [best.joint]
        tau_v = self.data.tau_validation
        on_validation = tuple(relative_error(tau_v[:, cols], tau_v[:, cols] - r[:, cols]) for r in (res_before, res_with))
        t_stat = worse_on_validation(res_before, res_with, best.joint)
        if t_stat > stats.t.isf(opts.veto_alpha, VETO_BLOCKS - 1):
            self.exact.residuals.pop(ExactFits.key_of(self.findings.found + [trial]), None)  # a validation-length array no later round needs
            self.findings.conflicting.append({"effect": best.effect, "joint": None if best.joint is None else best.joint + 1,
                                     "parameters": trial.parameters, "reason": "validation",
                                     "validation_error_before": on_validation[0], "validation_error_with": on_validation[1],
                                     "t": t_stat})
            self.findings.put_aside(best)
            return False
        if self.exact.widening_now is not None:
            self.exact.widening_now = widening
        return True

    def _held_at_bound(self, best: Candidate, trial: Finding, fit_with: IdentificationResult) -> bool:
        """Gate (g): the exact fit holds the finding's friction, rotor inertia or stiffness at
        its bound (the search saw it positive on its blocks, the whole data do not): set aside
        for its sign, as the final fit's check (:meth:`report`) would, before any later round
        builds on a column that explains nothing."""
        fitted = replace(trial, parameters=dict(trial.parameters))
        update_parameters([fitted], fit_with)
        if not sign_reversed([fitted]):
            return False
        self.findings.conflicting.append({"effect": fitted.effect, "joint": fitted.joint + 1, "parameters": fitted.parameters, "reason": "sign"})  # type: ignore[operator]
        self.findings.put_aside(best)
        return True

    def trial_fit(self, found: list[Finding]) -> IdentificationResult:
        """``identify``'s fit of the declared model with ``found`` (as gates d and f see it);
        with nothing found, the declared model's own fit (``armid identify``'s)."""
        if not found:
            return self.model.result0
        key = ExactFits.key_of(found)
        if key not in self.exact.fits:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", PoorExcitationWarning)
                self.exact.fits[key] = trial_fit(self.model.settled, self.data.experiments, found, self.model.load0)
        return self.exact.fits[key]

    def _validation_residual(self, found: list[Finding]) -> Array:
        """That fit's residual at every validation stamp, against the raw torque (n, N)."""
        key = ExactFits.key_of(found)
        if key not in self.exact.residuals:
            self.exact.residuals[key] = self.data.tau_validation - self.trial_fit(found).predict_stamps(self.data.validation_segments)[2]
        return self.exact.residuals[key]

    # --- adding a finding ---
    def _add(self, rnd: RoundModel, scored: list[ScoredCandidate], pick: _Pick) -> None:
        """The picked candidate as a finding (with its look-alike, when one explains nearly as
        much), applied: exactly for a tilt, a gain, a delay; as columns otherwise."""
        s, yv, wt_v = pick.scored, self.data.yv, self.data.wt_v
        best, gamma = s.candidate, s.gamma
        err_before = relative_error(yv * (wt_v > 0), pick.pred_before * (wt_v > 0))
        err_after = relative_error(yv * (wt_v > 0), pick.pred_after * (wt_v > 0))
        finding = Finding(best.effect, best.joint, candidate_parameters(best, gamma), 1.0 - s.rss_v / rnd.rss_v, err_before, err_after)
        alt_name = LOOKALIKES.get(best.effect)
        if alt_name:
            alt = next((x for x in scored if x.candidate.effect == alt_name and x.candidate.joint == best.joint), None)
            if alt is not None and self._explains_nearly_as_much(rnd, alt, s):
                finding.lookalike = alt_name
                finding.separate_by = SEPARATE[frozenset((best.effect, alt_name))].format(j=(best.joint or 0) + 1)
        if best.effect == "gravity_tilt":
            self._apply_tilt(finding, gamma)
        elif best.effect == "torque_gain":
            self._apply_gain(finding, gamma)
        elif best.effect == "time_delay":
            self._apply_delay(finding, gamma)
        else:
            self._add_columns(finding, best, pick.columns_v)

    def _explains_nearly_as_much(self, rnd: RoundModel, alt: ScoredCandidate, s: ScoredCandidate) -> bool:
        """Whether look-alike ``alt`` removes at least 0.9 of what ``s`` removes from the arm's
        held-out residual. A Stribeck or load-dependent friction against its Coulomb look-alike
        is a question of its term on its joint's rows (as :meth:`_friction_shape` names it):
        told apart where Coulomb leaves more than 1/0.9 of what the shape leaves there (the 0.9
        of the Coulomb level both share said nothing of the peak: blind Stribeck seed 11's peak
        took joint 3's held-out power to a thirtieth of Coulomb's and was called a look-alike)."""
        if s.candidate.effect in ("stribeck_friction", "load_dependent_coulomb") and alt.candidate.effect == "coulomb_friction":
            return 0.9 * joint_power_after(alt, rnd, self.data.held, self.data.wt_v) <= joint_power_after(s, rnd, self.data.held, self.data.wt_v)
        return (rnd.rss_v - alt.rss_v) >= 0.9 * (rnd.rss_v - s.rss_v)

    def _apply_tilt(self, finding: Finding, gamma: Array) -> None:
        """A tilt applied exactly, not as its linearisation: the base columns are rebuilt with the
        tilted gravity and the search goes on from there (a linearised tilt leaves a residual
        that springs and gains would chase); a further tilt found later is a correction of this
        one (at most two), merged into the same finding."""
        rotation = rotation_matrix(np.array([gamma[0], gamma[1], 0.0]))
        self.model.robot = replace(self.model.robot, gravity=rotation @ np.asarray(self.model.robot.gravity, float))
        total = np.array([gamma[0], gamma[1]]) + self.model.tilt_total
        earlier = next((f for f in self.findings.found if f.effect == "gravity_tilt"), None)
        if earlier is not None:
            earlier.parameters.update(tilt_x_rad=float(total[0]), tilt_y_rad=float(total[1]))
            earlier.explained = 1.0 - (1.0 - earlier.explained) * (1.0 - finding.explained)
            earlier.error_after = finding.error_after
        else:
            finding.parameters.update(tilt_x_rad=float(total[0]), tilt_y_rad=float(total[1]))
            self.findings.found.append(finding)
        self.model.tilt_total = total
        self.model.tilt_rounds += 1
        if self.model.tilt_rounds >= 3:
            self.findings.present.add(("gravity_tilt", None))
        self.model.base = structural_base(self.model.robot, self.model.effects)  # a tilt makes more of the first links' parameters seen
        self.model.rebuild_columns(self.data)

    def _apply_gain(self, finding: Finding, gamma: Array) -> None:
        """A drive gain applied exactly, like the tilt: the joint's rigid-body columns scaled by the gain."""
        joint = finding.joint
        assert joint is not None
        self.model.gain_scale[joint] *= 1.0 + float(gamma[0])
        self.findings.found.append(finding)
        self.findings.present.add(("torque_gain", joint))
        self.model.rebuild_columns(self.data)

    def _apply_delay(self, finding: Finding, gamma: Array) -> None:
        """A delay applied exactly, like the tilt: the data are shifted by the delay and the
        search goes on; a further delay of the same kind found later corrects this one (the
        linearised estimate is biased by the fit it was taken about; at most two corrections)."""
        joint = finding.joint
        key = ("time_delay", joint)
        d = float(gamma[0])
        self.data.ident, self.data.held = self.data.ident.lagged(joint, d), self.data.held.lagged(joint, d)
        self.model.delay_total[joint] = self.model.delay_total.get(joint, 0.0) + d
        earlier = next((f for f in self.findings.found if f.effect == "time_delay" and f.joint == joint), None)
        if earlier is not None:
            earlier.parameters["delay_s"] = self.model.delay_total[joint]
            earlier.explained = 1.0 - (1.0 - earlier.explained) * (1.0 - finding.explained)
            earlier.error_after = finding.error_after
        else:
            self.findings.found.append(finding)
        self.model.delay_rounds[joint] = self.model.delay_rounds.get(joint, 0) + 1
        if self.model.delay_rounds[joint] >= 3:
            self.findings.present.add(key)
        self.model.rebuild_columns(self.data)
        self.model.extra_i = np.column_stack([np.zeros((self.data.yi.size, 0))] + [c.columns(self.data.ident) for c in self.model.chosen])
        self.model.extra_v = np.column_stack([np.zeros((self.data.yv.size, 0))] + [c.columns(self.data.held) for c in self.model.chosen])

    def _add_columns(self, finding: Finding, best: Candidate, columns_v: Array | None) -> None:
        """A finding linear in its parameters: its columns join the model's."""
        assert columns_v is not None
        ci = best.columns(self.data.ident)
        self.findings.found.append(finding)
        self.model.chosen.append(best)
        self.findings.present.add((best.effect, best.joint))
        if best.effect in ("stribeck_friction", "load_dependent_coulomb") and "fc" in best.labels:  # found with its Coulomb level
            self.findings.present.add(("coulomb_friction", best.joint))
        if best.joint is None and best.effect == "coulomb_friction":  # friction on every joint it covers
            self.findings.present |= {(e, int(label[len(p) :]) - 1) for label in best.labels
                             for e, p in (("coulomb_friction", "fc"), ("viscous_friction", "fv"), ("torque_offset", "offset")) if label.startswith(p)}
        self.model.extra_i = np.column_stack([self.model.extra_i, ci])
        self.model.extra_v = np.column_stack([self.model.extra_v, columns_v])

    # --- before and after ---
    def report(self) -> Diagnosis:
        """Before and after, fitted as `identify` fits (parallel filtering, every equation, the
        declared Coulomb smoothing chosen on the data, weighted least squares): before is the
        declared model exactly as `armid identify` gives it, after the same with the findings
        added to the model (findings_model), so the two differ by the findings alone."""
        found, _ = merge_offset_into_spring(self.findings.found, self.model.chosen)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PoorExcitationWarning)
            refine_delays(self.model.settled, found, self.data.experiments, self.model.load0)  # the declared settings as chosen: a delay's fit per try
            result1 = self._fit_findings(found)
            # friction, inertia or a spring the whole fit holds at its bound (the search saw it
            # positive on its blocks): it explains nothing, so it is not a finding; the rest refitted
            reversed_sign = sign_reversed(found)
            if reversed_sign:
                self.findings.conflicting += [{"effect": f.effect, "joint": f.joint + 1, "parameters": dict(f.parameters), "reason": "sign"}
                                     for f in reversed_sign if f.joint is not None]
                # a Stribeck or load term held at 0 leaves the Coulomb level it came with: that
                # friction stays, in its place in the order found (the Coulomb itself)
                found = [g for g in (coulomb_level(f) if f in reversed_sign else f for f in found) if g is not None]
                result1 = self._fit_findings(found)
            found, result1, negligible = self._material(found, result1)
        self.final_fit = result1
        diagnosis = self._measured(found, result1)
        diagnosis.negligible, diagnosis.notes = negligible, self.findings.notes
        return diagnosis

    def _material(self, found: list[Finding], result1: IdentificationResult) -> tuple[list[Finding], IdentificationResult, list[dict[str, Any]]]:
        """Each finding judged by the validation error it removes (MATERIALITY): added in the
        order found to the declared model and the findings kept before it, fitted as `identify`
        fits; one that removes less than MATERIALITY of the error's power above the validation's
        noise floor is negligible, reported with its torque's rms at the validation stamps and
        left out; one that raises the error is set aside, as by gate (f). A Stribeck peak or a
        load-dependent term is judged so after its Coulomb level, on its joint's error and noise
        (the friction's shape is its joint's question: blind Stribeck seed 13's wrist peak took
        its joint from 1.18 to 0.88 of its noise and the arm's error, which the shoulder's noise
        sets, by 0.01 %): where it is negligible the finding is that Coulomb friction (on the
        nearly noise-free PUMA 560 example a peak of 0.06 % of the Coulomb level fitted the
        held-out blocks better, and was named). The validation only removes findings here: it
        never ranks them. A noise floor read above the error the findings reach (the PUMA 560
        example's 5.8 % for 1.57 %: friction's steps are above any cut-off) is no floor; the
        whole error's power is judged then."""
        segments = self.data.validation_segments
        kept: list[Finding] = []
        fit_kept = self.model.result0
        (_, tau_v, pred), error = fit_kept.predict_stamps(segments), validation_error(fit_kept)
        negligible: list[dict[str, Any]] = []
        floor = validation_noise_floor(self.data.validation)["relative_error"] or 0.0
        if floor >= validation_error(result1):  # no model beats the noise: the estimate took the torque's own steps for noise
            floor = 0.0
        for f in found:
            fit = result1 if len(kept) == len(found) - 1 else self._fit_findings(kept + [f])
            error_with, pred_with = validation_error(fit), fit.predict_stamps(segments)[2]
            level = coulomb_level(f)
            if level is not None and error_with < error:  # its peak or load term judged as a finding after its Coulomb level
                fit_level = self._fit_findings(kept + [level])
                error_level, pred_level = validation_error(fit_level), fit_level.predict_stamps(segments)[2]
                joint_errors = joint_validation_errors(tau_v, (pred_level, pred_with), joint_noise_floors(self.data.validation), f.joint)  # type: ignore[arg-type]
                if not material_drop(*joint_errors):
                    rms_term = float(np.sqrt(np.mean((pred_with - pred_level)[:, f.joint] ** 2)))
                    negligible.append({"effect": f.effect, "joint": f.joint + 1, "parameters": dict(f.parameters), "torque_rms": rms_term,  # type: ignore[operator]
                                       "validation_error_before": error_level, "validation_error_with": error_with, "kept": "coulomb_friction",
                                       "joint_validation_error_before": joint_errors[0], "joint_validation_error_with": joint_errors[1]})
                    if f.effect == "stribeck_friction":  # a peak the data show, too small to matter here: a look-alike
                        level.lookalike, level.separate_by = f.effect, SEPARATE[frozenset((f.effect, level.effect))].format(j=f.joint + 1)  # type: ignore[operator]
                    f, fit, error_with, pred_with = level, fit_level, error_level, pred_level
            change = np.sqrt(np.mean((pred_with - pred) ** 2, axis=0))
            rms = float(change[f.joint] if f.joint is not None else change.max())
            what = {"effect": f.effect, "joint": None if f.joint is None else f.joint + 1, "parameters": dict(f.parameters)}
            if error_with >= error:  # not small: wrong beyond the run it was found on
                self.findings.conflicting.append({**what, "reason": "validation", "validation_error_before": error, "validation_error_with": error_with})
            elif material_drop(error, error_with, floor):
                f.validation_before, f.validation_after, f.torque_rms = error, error_with, rms
                kept.append(f)
                fit_kept, error, pred = fit, error_with, pred_with
            else:
                negligible.append({**what, "torque_rms": rms, "validation_error_before": error, "validation_error_with": error_with})
        update_parameters(kept, fit_kept)  # the kept findings' parameters as their own fit gives them (the trials moved them)
        return kept, fit_kept, negligible

    def _fit_findings(self, found: list[Finding]) -> IdentificationResult:
        """The declared model with ``found`` added, fitted on all the identification data."""
        model, model_options = findings_model(self.model.robot0, found)
        # the prior as wide as the declared model's fit found it: a finding whose columns lean
        # on poorly excited parameters (a tilt on the first moments) moves least squares away
        # from the modeled values and would widen the prior for the whole model; on the KUKA
        # LWR4+ (1 -> 3) that cost more on another trajectory than the tilt gained
        if self.exact.widening_now is not None:
            model_options = replace(model_options, prior_widening=min(prior_widening(self.model.result0) or np.inf, self.exact.widening_now))
        result = identify(model, self.data.experiments, self.data.validation, model_options) if found else self.model.result0
        update_parameters(found, result)
        return result

    def _measured(self, found: list[Finding], result1: IdentificationResult) -> Diagnosis:
        """The diagnosis: before and after as anyone can check them, the model at every
        validation sample against the raw torque (and on the equations that move)."""
        valid, result0 = self.data.valid, self.model.result0
        st = [s for p in self.data.validation for s in p.segments]
        t_s, tau_s, before_stamps = result0.predict_stamps(st)
        _, _, after_stamps = result1.predict_stamps(st)
        t_v = valid.t if valid.t is not None else np.arange(valid.q.shape[0]) * valid.period
        before_pred = result0.predict_times(t_v, valid.q, valid.qd, valid.qdd)
        after_pred = result1.predict_times(t_v, valid.q, valid.qd, valid.qdd)
        used_v = moving_equations(valid, self.opts)
        before = summary(tau_s, before_stamps)
        after = summary(tau_s, after_stamps)
        before["moving_equations"] = masked_summary(valid.tau, before_pred, used_v)
        after["moving_equations"] = masked_summary(valid.tau, after_pred, used_v)
        noise = validation_noise_floor(self.data.validation)
        return Diagnosis(found, self.findings.absorbed, before, after, [f"{e.effect}@{e.joint + 1}" for e in self.model.effects], self.findings.rounds,
                         (valid.tau, before_pred), (valid.tau, after_pred), (t_v, valid.q, valid.qd, valid.qdd), used_v,
                         (np.asarray(t_s), tau_s, after_stamps), noise, self.findings.conflicting,
                         extrapolated_findings(found, self.data.ident_all.q, valid.q))

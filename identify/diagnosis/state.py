"""The diagnosis search's state, one record per idea: the gates' settings
(:class:`DiagnoseOptions`), the data (:class:`SearchData`), the model so far
(:class:`ModelSoFar`, and :class:`RoundView`, what the candidates read of it), what was found
so far (:class:`FindingsSoFar`) and the exact fits the gates judge by (:class:`ExactFits`).
The search itself (:mod:`identify.diagnosis.search`) holds one of each.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..effects import LinearEffect
from ..errors import PoorExcitationWarning
from ..identifiability import BaseParameters
from ..identification import (
    IdentificationResult,
    base_torque,
    column_count,
    declared_effects,
    identify,
    rigid_parameters,
    stacked_regressor,
    structural_base,
)
from ..preprocess import Prepared, Segment
from ..robot import Robot
from ..spatial import Array
from .candidates import Candidate
from .data import StackedData
from .report import Finding


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
    # torque smooths the step of Coulomb friction over the filter's span, and a declared
    # friction's column (the model's, on the filtered motion) does not (the candidates' friction
    # columns are filtered as the torque is: diagnosis_candidates.coulomb)
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


def moving_equations(d: StackedData, opts: DiagnoseOptions) -> Array:
    """(n, N): the equations whose joint moves clear of rest and of a reversal."""
    return np.abs(d.qd) >= np.maximum(opts.min_speed, np.abs(d.qdd) * opts.reversal_margin_s)


def declared_fit(robot: Robot, experiments: list[Prepared], validation: list[Prepared]) -> IdentificationResult:
    """The declared model exactly as ``armid identify`` fits it ("before")."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoorExcitationWarning)
        return identify(robot, experiments, validation)


@dataclass(eq=False)
class SearchData:
    """The data as the search sees them: the identification data stacked (all of it, and its
    even tenths to fit on and odd ones to rank by, both shifted by the delays found), their
    targets ``y`` and row weights (whitened by each joint's noise, zero at rest or reversing),
    and the validation, at its stamps, which only vetoes and measures."""

    experiments: list[Prepared]
    validation: list[Prepared]
    ident_all: StackedData
    valid: StackedData
    ident: StackedData
    held: StackedData
    nj: int
    sample_period: float  # the input's, before decimation
    validation_segments: list[Segment]
    tau_validation: Array
    noise_sd: Array  # (N,) each joint's raw torque noise in the identification data
    wt_i: Array = field(default_factory=lambda: np.zeros(0))
    wt_v: Array = field(default_factory=lambda: np.zeros(0))
    n_used: int = 0

    @property
    def yi(self) -> Array:
        return self.ident.y

    @property
    def yv(self) -> Array:
        return self.held.y

    def whiten(self, wi: Array, opts: DiagnoseOptions) -> None:
        """Per-joint noise levels from the base fit (columns ``wi``) whiten the rows (as
        weighted least squares); the equations of a joint at rest or reversing weigh nothing
        (:func:`moving_equations`)."""
        nj, yi, yv = self.nj, self.yi, self.yv
        moving = moving_equations(self.ident, opts).reshape(-1)
        beta0 = np.linalg.lstsq(wi[moving], yi[moving], rcond=None)[0]
        res0 = np.where(moving, yi - wi @ beta0, np.nan).reshape(-1, nj)
        sigma = np.sqrt(np.nanmean(res0**2, axis=0))
        sigma = np.maximum(np.nan_to_num(sigma, nan=1.0), 1e-9 * max(1.0, float(np.nanmax(np.abs(res0)))))
        used_i, used_v = moving_equations(self.ident, opts), moving_equations(self.held, opts)
        self.wt_i = (np.tile(1.0 / sigma, yi.size // nj) * used_i.reshape(-1))
        self.wt_v = (np.tile(1.0 / sigma, yv.size // nj) * used_v.reshape(-1))
        self.n_used = int(used_i.sum())


@dataclass(eq=False)
class ModelSoFar:
    """The model the search builds on: the declared model's fit ("before", its load, its
    effects and settings), the gravity as tilted, the drive gains and delays found, the base
    parameters' columns on the data and the findings' columns beside them."""

    robot0: Robot  # the robot file's
    robot: Robot  # with the gravity as tilted so far
    result0: IdentificationResult  # the declared model's fit, as `armid identify` gives it
    load0: Array  # a declared load-dependent friction's load: that fit's rigid-body parameters
    effects: list[LinearEffect]
    base: BaseParameters
    n_cols: int
    gain_scale: Array  # joint j measures gain_scale[j] times the model's torque (declared, then found)
    modeled: Array | None  # the robot file's modeled parameters, None where it lacks some
    settled: Robot  # the declared effects' settings fixed at what result0 chose
    wi: Array = field(default_factory=lambda: np.zeros((0, 0)))  # the base columns on the fitting tenths
    wv: Array = field(default_factory=lambda: np.zeros((0, 0)))  # ... on the held-out tenths
    extra_i: Array = field(default_factory=lambda: np.zeros((0, 0)))  # the findings' columns alike
    extra_v: Array = field(default_factory=lambda: np.zeros((0, 0)))
    chosen: list[Candidate] = field(default_factory=list)  # the findings added as columns
    tilt_total: Array = field(default_factory=lambda: np.zeros(2))
    tilt_rounds: int = 0
    delay_total: dict[int | None, float] = field(default_factory=dict)
    delay_rounds: dict[int | None, int] = field(default_factory=dict)

    @classmethod
    def declared(cls, robot: Robot, result0: IdentificationResult) -> ModelSoFar:
        """The declared model from its fit: its settings, its declared drive gains and its load
        (a declared load-dependent friction's: that fit's own rigid-body torque, here and in
        every refit of a candidate, one fit each instead of identify's fixed-point passes)."""
        from .refit import settled_robot

        load0 = rigid_parameters(result0)
        effects = declared_effects(robot, load0)
        gain_scale = np.ones(robot.n_joints) if result0.torque_scale is None else np.array(result0.torque_scale, float)
        phi0 = robot.modeled_parameters()
        return cls(robot, robot, result0, load0, effects, structural_base(robot, effects), column_count(robot, effects), gain_scale,
                   None if np.isnan(phi0).any() else phi0, settled_robot(robot, result0))

    def base_columns(self, d: StackedData) -> Array:
        """The base parameters' columns of ``d`` with the gravity as tilted so far and the drive gains found so far."""
        cols = stacked_regressor(self.robot, self.effects, d.q, d.qd, d.qdd)[:, self.base.independent]
        return cols if np.all(self.gain_scale == 1.0) else cols * np.tile(self.gain_scale, d.q.shape[0])[:, None]

    def base_prediction(self, d: StackedData, beta: Array) -> Array:
        """(n, N) the torque of base parameters ``beta`` at the samples of ``d``, as
        :meth:`base_columns` ``@ beta`` gives it, without a copy of the columns: a delay's
        candidate predicts on each joint's motion shifted either way, every round."""
        tau = base_torque(self.robot, self.effects, self.base.independent, beta, d.q, d.qd, d.qdd)
        return tau if np.all(self.gain_scale == 1.0) else tau * self.gain_scale

    def rebuild_columns(self, data: SearchData) -> None:
        """The base columns again, after a tilt, a gain or a delay changed them."""
        self.wi, self.wv = self.base_columns(data.ident), self.base_columns(data.held)


@dataclass(eq=False)
class RoundView:
    """What the candidates' columns read of the model so far
    (:class:`~identify.diagnosis.candidates.CurrentModel`), set each round: its base
    parameters (and the same without friction's steps, for a delay's derivative), its standard
    parameters and a load-dependent friction's load. A column is computed when it is asked
    for, with the model as it is then (a tilt, gain or delay found since included)."""

    model: ModelSoFar
    beta: Array = field(default_factory=lambda: np.zeros(0))
    smooth: Array = field(default_factory=lambda: np.zeros(0))
    phi: Array = field(default_factory=lambda: np.zeros(0))
    load: tuple[float, ...] = ()

    def predict(self, d: StackedData) -> Array:
        return self.model.base_prediction(d, self.beta)

    def predict_smooth(self, d: StackedData) -> Array:
        return self.model.base_prediction(d, self.smooth)


@dataclass(eq=False)
class FindingsSoFar:
    """What the search has said so far: the findings, the candidates absorbed by the model,
    those set aside (with why, in ``conflicting``), the effects no longer offered (declared,
    found or set aside: ``present``), notes, and each round's best five."""

    present: set[tuple[str, int | None]]
    notes: list[str] = field(default_factory=list)
    found: list[Finding] = field(default_factory=list)
    absorbed: list[dict[str, Any]] = field(default_factory=list)
    absorbed_keys: set[tuple[str, int | None]] = field(default_factory=set)
    set_aside: set[tuple[str, int | None]] = field(default_factory=set)
    conflicting: list[dict[str, Any]] = field(default_factory=list)
    rounds: list[list[tuple[str, float]]] = field(default_factory=list)

    def put_aside(self, c: Candidate) -> None:
        """``c``'s effect on its joint set aside: offered no more."""
        self.present.add((c.effect, c.joint))
        self.set_aside.add((c.effect, c.joint))


@dataclass(eq=False)
class ExactFits:
    """The exact fits of the declared model with findings (gates d and f), and their residuals
    at the validation stamps, by the findings' effects, joints and parameters; and how far the
    prior widens with the findings taken so far (gate d's reference)."""

    widening_now: float | None
    fits: dict[str, IdentificationResult] = field(default_factory=dict)
    residuals: dict[str, Array] = field(default_factory=dict)

    @staticmethod
    def key_of(found: list[Finding]) -> str:
        return repr([(f.effect, f.joint, sorted(f.parameters.items())) for f in found])

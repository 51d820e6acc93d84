"""Khosla's off-line strategy: single-link experiments from the last link to the first.

Property 4 (eq. 17): the torque of joint k depends only on the parameters of links k..N.
When joint k alone moves, row k of eq. (18) is

.. math:: \\tau_k = M_{k,k}\\,\\phi_k + M_{k,>k}\\,\\phi_{>k}

and links k+1..N were identified by the experiments before (in some linear combinations
``F phi = beta_prev``). Row k splits into what those combinations already give and what
is new:

.. math:: M_{k,>k}\\phi_{>k} = G\\,\\beta_{prev} + M_{k,>k}(I - F^+F)\\phi_{>k},
          \\qquad G = M_{k,>k} F^+

so the experiment identifies the base parameters of ``[M_kk | M_k,>k (I - F^+F)]``
(Khosla's combined entries such as ``m5 + m4``, Table 2) from ``tau_k - G beta_prev``. The
uncertainty of ``beta_prev`` is carried forward: the covariance of all estimates so far is
kept and updated, so a standard deviation at link 1 includes what links 2..N left open.

The structure (which combinations) is taken from the experiment's ideal motion: the joints
that moved, the others at their median position, so that a held joint's small tracking
error does not create combinations of noise; the estimate uses the measured motion.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .estimation import correlation_length, lag_window_covariance
from .excitation import experiment_columns, experiment_regressor
from .identifiability import base_parameters, combination_ranges, identified_by_data, physical_ranges, preferred_order
from .identification import IdentificationResult, declared_effects
from .plausibility import moving_joints
from .preprocess import Prepared
from .robot import Robot
from .spatial import Array

MIN_SPEED = 0.02
REVERSAL_MARGIN_S = 0.025
"""Samples of the moving joint slower than this (rad/s), or within this time of a velocity
reversal (``|qd| < |qdd| t``), are left out: friction there is anything up to breakaway,
and a filtered torque smooths the Coulomb step that ``sign(qd)`` does not (as in
:mod:`identify.diagnosis`)."""


@dataclass(frozen=True)
class Functional:
    """A linear combination ``row @ phi`` that an experiment identified (columns as
    :func:`~identify.excitation.experiment_columns` names them)."""

    link: int  # 0-based link of the experiment that identified it
    expression: str
    row: Array
    modeled: float


@dataclass
class SequenceResult:
    robot: Robot
    names: list[str]
    functionals: list[Functional]
    beta: Array
    covariance: Array
    steps: list[dict[str, Any]] = field(default_factory=list)
    modeled: Array | None = None
    """Every column's initial value (the robot file's inertials, zero for effects)."""

    @property
    def std(self) -> Array:
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))

    def value_of(self, row: Array, rtol: float = 1e-6) -> tuple[float, float] | None:
        """Estimate and std of ``row @ phi`` when the experiments identify it, else None."""
        f = np.array([fn.row for fn in self.functionals])
        c, *_ = np.linalg.lstsq(f.T, row, rcond=None)
        if np.linalg.norm(f.T @ c - row) > rtol * max(float(np.linalg.norm(row)), 1e-300):
            return None
        return float(c @ self.beta), float(np.sqrt(max(c @ self.covariance @ c, 0.0)))

    def parameters(self) -> Array:
        """Every column's value, for predictions (eq. 18): the identified combinations met
        exactly (their minimum-norm solution), the modeled values in every direction the
        experiments left open (a single-link run of joint k is predicted by what links k..N
        identified, property 4; what it cannot see comes from the robot file)."""
        f = np.array([fn.row for fn in self.functionals])
        f_pinv = np.linalg.pinv(f)
        phi0 = np.zeros(len(self.names)) if self.modeled is None else self.modeled
        return np.asarray(f_pinv @ self.beta + (np.eye(len(self.names)) - f_pinv @ f) @ phi0)

    def predict(self, q: Array, qd: Array, qdd: Array) -> Array:
        """Every joint's torque (samples, N) at these kinematics, with :meth:`parameters`."""
        n = self.robot.n_joints
        w = experiment_regressor(self.robot, tuple(range(n)), q, qd, qdd)
        return np.asarray((w @ self.parameters()).reshape(-1, n))

    def physical_ranges(self) -> Array:
        """Each combination's physical range: its coefficients applied to its columns' ranges
        (:func:`~identify.identifiability.combination_ranges`), or its modeled magnitude."""
        if not self.functionals:
            return np.zeros(0)
        columns = physical_ranges(self.robot, self.names, self.modeled)
        rows = np.array([fn.row for fn in self.functionals])
        return combination_ranges(rows, columns, np.array([fn.modeled for fn in self.functionals]))

    def identified(self) -> Array:
        """Whether these data identify each combination: three of its standard deviations
        within its physical range (:func:`~identify.identifiability.identified_by_data`)."""
        return identified_by_data(self.std, self.physical_ranges())

    def table(self) -> list[dict[str, Any]]:
        """Khosla's Tables 2-4: link, parameter (or combined entry), initial value, estimate, std,
        and whether the data identify it against its physical range."""
        std, ranges = self.std, self.physical_ranges()
        ok = identified_by_data(std, ranges)
        return [{"link": fn.link + 1, "parameter": fn.expression, "modeled": fn.modeled, "estimate": float(self.beta[k]),
                 "std": float(std[k]), "identified": bool(ok[k]), "physical_range": float(ranges[k])}
                for k, fn in enumerate(self.functionals)]

    def compare(self, whole: IdentificationResult) -> list[dict[str, Any]]:
        """Each base parameter of a whole-arm identification beside the single-link sequence's value of it."""
        out = []
        exprs = whole.base.expressions()
        n_cols = len(self.names)
        for k, col in enumerate(whole.base.independent):
            row = np.zeros(n_cols)
            if whole.names[col] not in self.names:
                continue
            row[self.names.index(whole.names[col])] = 1.0
            for d, dcol in enumerate(whole.base.dependent):
                if whole.names[dcol] in self.names:
                    row[self.names.index(whole.names[dcol])] += whole.base.regrouping[k, d]
            got = self.value_of(row)
            out.append({"expression": exprs[k], "whole_arm": float(whole.estimate.beta[k]), "whole_arm_std": float(whole.estimate.std[k]),
                        "single_link": None if got is None else got[0], "single_link_std": None if got is None else got[1]})
        return out

    def to_json(self) -> dict[str, Any]:
        return {"robot": self.robot.name, "order": [s["link"] for s in self.steps], "steps": self.steps, "table": self.table()}


def _ideal(q: Array, moving: Array) -> Array:
    """Positions with the held joints at their median: the experiment as designed."""
    out = q.copy()
    out[:, ~moving] = np.median(q[:, ~moving], axis=0)
    return out


def modeled_effect_values(robot: Robot) -> Array:
    """Each declared effect column's modeled value, in :func:`declared_effects`' order: the
    robot file's ``modeled`` (a datasheet's reflected rotor inertia, a known friction), else 0."""
    given = {(one.effect, int(one.joint or 0) - 1): float(one.options["modeled"])
             for eff in robot.effects if "modeled" in eff.options for one in eff.per_joint(robot.n_joints)}
    return np.array([v for e in declared_effects(robot) for v in [given.get((e.effect, e.joint), 0.0)] + [0.0] * (len(e.parameter_names) - 1)])


def held_motion_torque(w_new: Array, a: Array, rows: Array, phi0: Array) -> Array:
    """What the held joints' tracking error adds to the moving joint's torque through the
    directions this experiment cannot separate, at their modeled values (as
    :meth:`SequenceResult.parameters` predicts them).

    The combinations come from the ideal motion, where ``w_new = a @ rows`` exactly; the
    measured motion differs by the held joints' small motion, and ``(w_new - a @ rows) phi``
    is torque no combination carries. Left in the data, the fit absorbed it: on the demo's
    link-3 runs, joint 2 gives way by 1-3 mrad, ``Izz3`` multiplies ``qdd2 + qdd3`` and ``ia3``
    only ``qdd3``; with torques exactly the model's, fv3 came out 0.78 sigma high."""
    known = np.nan_to_num(phi0)  # a link the robot file does not model: 0, as before any estimate
    return np.asarray(w_new @ known - a @ (rows @ known))


def single_link_sequence(robot: Robot, experiments: dict[int, list[Prepared]], modeled: Array | None = None) -> SequenceResult:
    """Identify link by link, last to first; ``experiments[k]`` moved joint k (0-based) alone.

    ``modeled`` are the initial values of every column (default: the robot file's
    inertial values, zero for effects) shown beside the estimates.
    """
    n = robot.n_joints
    _, names = experiment_columns(robot, (0,))
    p = len(names)
    phi0 = np.zeros(p)
    phi0[: robot.n_parameters] = robot.modeled_parameters()
    phi0[robot.n_parameters :] = modeled_effect_values(robot)
    if modeled is not None:
        phi0 = np.asarray(modeled, float)
    functionals: list[Functional] = []
    beta = np.zeros(0)
    cov = np.zeros((0, 0))
    steps = []
    order_all = preferred_order(n, p - robot.n_parameters)
    for k in sorted(experiments, reverse=True):
        segs = [s for prep in experiments[k] for s in prep.segments]
        if not segs:
            continue
        q = np.concatenate([s.q for s in segs])
        qd = np.concatenate([s.qd for s in segs])
        qdd = np.concatenate([s.qdd for s in segs])
        y = np.concatenate([s.tau[:, k] for s in segs])
        sliding = np.abs(qd[:, k]) >= np.maximum(MIN_SPEED, np.abs(qdd[:, k]) * REVERSAL_MARGIN_S)
        q, qd, qdd, y = q[sliding], qd[sliding], qdd[sliding], y[sliding]
        cols = list(range(p))  # the projection may mix in any column that a previous step named
        moving = moving_joints(q)
        moving[k] = True
        w = experiment_regressor(robot, (k,), q, qd, qdd)
        qi = _ideal(q, moving)
        w_ideal = experiment_regressor(robot, (k,), qi, np.where(moving, qd, 0.0), np.where(moving, qdd, 0.0))
        if functionals:
            f = np.array([fn.row for fn in functionals])
            f_pinv = np.linalg.pinv(f)
            null = np.eye(p) - f_pinv @ f
            g = w @ f_pinv
        else:
            null, g = np.eye(p), np.zeros((w.shape[0], 0))
        w_new, w_new_ideal = w @ null, w_ideal @ null
        position = {c: j for j, c in enumerate(cols)}
        # earlier steps' rows hold their regrouping to 1e-10 (``base_parameters`` rounds below
        # it), so what they leave of a direction they took is zero here, not a new combination:
        # on the KUKA's link 1, Izz5 and Izz6 at 1.2e-10 of the largest column came out at -5e7
        base = base_parameters(w_new_ideal[:, cols], [names[c] for c in cols], [position[c] for c in order_all if c in position], rtol=1e-7, zero_rtol=1e-7)
        indep = [cols[j] for j in base.independent]
        a = w_new[:, indep]
        rows = base.projection()  # each combination's row over every column (``cols`` is all of them)
        y_new = y - g @ beta - held_motion_torque(w_new, a, rows, phi0)
        b_new, *_ = np.linalg.lstsq(a, y_new, rcond=None)
        resid = y_new - a @ b_new
        ata_inv = np.linalg.pinv(a.T @ a)
        block = 2 * correlation_length(resid)
        own = lag_window_covariance(ata_inv, a, resid, block)
        h = ata_inv @ a.T @ g  # d b_new / d beta_prev (with a minus sign)
        c_new = own + h @ cov @ h.T
        cross = -h @ cov
        cov = np.block([[cov, cross.T], [cross, c_new]])
        beta = np.concatenate([beta, b_new])
        exprs = base.expressions()
        for j, row in enumerate(rows):
            functionals.append(Functional(k, exprs[j], row, float(row @ phi0)))
        steps.append({"link": k + 1, "samples": int(a.shape[0]), "covariance_block_samples": block, "identified": len(indep), "moving_joints": [int(j) + 1 for j in np.flatnonzero(moving)],
                      "residual_rms": float(np.sqrt(np.mean(resid**2))), "relative_error": float(np.linalg.norm(resid) / max(float(np.linalg.norm(y)), 1e-300))})
    return SequenceResult(robot, names, functionals, beta, cov, steps, phi0)

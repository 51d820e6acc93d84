"""The errors anyone can check (INTERFACES.md metrics): the model at each input sample against
the raw torque, on its identification data (``fit``), on validation data, and on its own data
where that data was not fitted (``held_out``: cross-fitted over ten folds).

A model's fit error is measured on the samples it was fitted to, so it is smaller than what
the model shows on a repeat of its runs; a check of the model against new data (``armid
check``) that took it as the model's own level would call an unchanged arm changed. Each run
is cut into a hundred consecutive blocks dealt to ten folds in turn (block ``k`` to fold
``k mod 10``): each fold is spread over the whole run, so a fit without it has seen every
kind of motion the run holds, and its error at the fold's own samples is the model's error on
new data of the same motion (KUKA LWR4+ ``measurements_1``: fit 1.96 %, held out 2.14 %,
the second recording of the same trajectory 2.03 %). Contiguous tenths instead measure
extrapolation to unseen motion (2.89 % there), which ``armid check`` names apart. The ten
fits reuse one pass over the data: each fold's equations are factored once
(``W_f = Q_f R_f``) and a fit without fold ``f`` stacks the other nine triangles (the Gram
matrix of their rows is the sum of theirs).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import IdentificationError
from .estimation import JointFactors, LeastSquares, factor_columns
from .metrics import summary
from .preprocess import Prepared, Segment
from .spatial import Array

if TYPE_CHECKING:
    from .identification import IdentificationResult

FOLDS = 10
"""How many fits, each without one fold."""
BLOCKS = 100
"""How many consecutive blocks each run is cut into, dealt to the folds in turn."""

Refit = Callable[[JointFactors], LeastSquares]
"""The identification's estimator (its weighting and prior) applied to other factors of the same columns."""


def fold_of(t: Array, start: float, stop: float) -> Array:
    """The fold (0..9) of each time: its block of the span ``[start, stop]``, modulo the folds."""
    span = max(stop - start, 1e-300)
    return np.clip(((np.asarray(t, float) - start) / span * BLOCKS).astype(int), 0, BLOCKS - 1) % FOLDS


def equation_folds(segments: list[Segment]) -> Array:
    """The fold of each equation least squares sees, by its time in its own segment
    (``regression_system``'s order: segment after segment, the kept samples of each)."""
    out = []
    for seg in segments:
        kept = seg.t[seg.parallel.kept(seg.n_samples)]
        out.append(fold_of(kept, float(seg.t[0]), float(seg.t[-1])))
    return np.concatenate(out) if out else np.zeros(0, int)


def held_out_error(result: IdentificationResult, system: Array, segments: list[Segment], refit: Refit) -> dict[str, Any] | None:
    """The cross-fitted error of ``result``'s model on its own ``segments`` (``summary``'s
    metrics plus ``"folds"``), each fold predicted by ``refit`` of the other nine (the same
    base columns, weighting and prior; without the bounds ``--nonnegative`` may add).
    ``system`` is the regression system the result was fitted on. None where a fit without
    some fold has a base parameter the other nine do not excite."""
    fold = equation_folds(segments)
    keep = np.append(result.base.independent, system.shape[1] - 1)
    triangles = []
    for f in range(FOLDS):
        rows = fold == f
        triangles.append(factor_columns([np.ascontiguousarray(system[j][keep][:, rows]) for j in range(system.shape[0])]))
    taus, hats = [], []
    for f in range(FOLDS):
        others = [triangles[g] for g in range(FOLDS) if g != f]
        stacked = JointFactors([np.vstack([o.r[j] for o in others]) for j in range(system.shape[0])],
                               np.sum([o.counts for o in others], axis=0))
        try:
            estimate = refit(stacked)
        except IdentificationError:
            return None
        model = replace(result, estimate=estimate, _at_stamps={})
        for seg in segments:
            st = seg.at_stamps
            mine = fold_of(st.t, float(seg.t[0]), float(seg.t[-1])) == f
            if not mine.any():
                continue
            block = replace(st, t=st.t[mine], q=st.q[mine], qd=st.qd[mine], qdd=st.qdd[mine], tau=st.tau[mine])
            taus.append(block.tau)
            hats.append(block.as_measured(model.predict_times(block.t, block.q, block.qd, block.qdd)))
    if not taus:
        return None
    out = summary(np.concatenate(taus), np.concatenate(hats))
    out["folds"] = FOLDS
    return out


def measure_errors(result: IdentificationResult, system: Array, segments: list[Segment], validation: list[Prepared] | None,
                   refit: Refit, held_out: bool = True) -> None:
    """The fit, held-out (unless not ``held_out``) and validation errors, into ``result``."""
    _, tau_raw, tau_hat_raw = result.predict_stamps(segments)
    result.fit = summary(tau_raw, tau_hat_raw)
    result.fit["equations"] = int(system.shape[2])
    if held_out:
        result.held_out = held_out_error(result, system, segments, refit)
        if result.held_out is None:
            result.notes.append("held-out error: not measured (a fit without one of its ten folds leaves a base parameter unexcited)")
    if validation:
        segs = [s for p in validation for s in p.segments]
        _, tau, tau_hat = result.predict_stamps(segs)
        result.validation = summary(tau, tau_hat)
        result.validation_samples = int(tau.shape[0])
        rows = sum(p.rows for p in validation)
        result.validation["samples"] = int(tau.shape[0])
        result.validation["input_samples"] = int(rows)
        result.validation["left_out"] = int(rows - tau.shape[0])
        result.notes += [f"validation: {s}" for p in validation for s in p.notes]

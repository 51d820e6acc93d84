"""How the diagnosis judges a finding on the validation data (:mod:`identify.diagnosis`).

Gate (f): a finding must not raise its joint's (the arm's) squared error over most of the
validation's consecutive tenths (:func:`worse_on_validation`). The materiality: each finding,
added in the order found, must remove ``MATERIALITY`` of the validation error's power above
its noise floor (:func:`material_drop`; a friction's shape on its own joint,
:func:`joint_validation_errors`).
"""

from __future__ import annotations

import numpy as np

from ..identification import IdentificationResult
from ..spatial import Array
from .report import MATERIALITY


def material_drop(before: float, after: float, floor: float) -> bool:
    """A drop of a relative error that removes MATERIALITY of its power above the noise floor."""
    return before**2 - after**2 >= MATERIALITY * max(before**2 - floor**2, 0.0)


def joint_validation_errors(tau: Array, predictions: tuple[Array, Array], floors: Array, j: int) -> tuple[float, float, float]:
    """Joint j's relative error under each of two predictions at the validation stamps, and
    its noise floor (0 where the better prediction reaches below it: then it is no floor)."""
    norm = max(float(np.sqrt(np.sum(tau[:, j] ** 2))), 1e-300)
    before, after = (float(np.sqrt(np.sum((tau[:, j] - p[:, j]) ** 2))) / norm for p in predictions)
    floor = float(floors[j]) / norm
    return before, after, floor if floor < after else 0.0


def validation_error(result: IdentificationResult) -> float:
    """``result``'s relative_error on the validation data (INTERFACES.md 'Metrics')."""
    assert result.validation is not None
    return float(result.validation["relative_error"])


VETO_BLOCKS = 10
"""Gate (f) judges a finding on the validation data's consecutive tenths."""


def worse_on_validation(before: Array, after: Array, joint: int | None, blocks: int = VETO_BLOCKS) -> float:
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

"""Differentiating recorded signals: Khosla's 5-point least-squares filter (section 5.1).

A parabola fitted by least squares to five points spaced ``T`` gives the derivative

.. math:: f'(x) = \\frac{-2 f(x-2T) - f(x-T) + f(x+T) + 2 f(x+2T)}{10 T}

exact on polynomials of degree 2; its white-noise gain is ``sqrt(10)/(10 T)``, 0.45 of a
central difference's ``sqrt(2)/(2 T)``. The causal form is the same filter two samples
late, ``f'(x - 2T)`` from ``f(x - 4T) .. f(x)``, for on-line use.
"""

from __future__ import annotations

import numpy as np

from .spatial import Array

FIVE_POINT_TAPS = np.array([-2.0, -1.0, 0.0, 1.0, 2.0]) / 10.0
"""Coefficients of f(x-2T) .. f(x+2T), to be divided by T."""

FIVE_POINT_DELAY_SAMPLES = 2
"""Delay of the causal form, in samples."""


def five_point_derivative(x: Array, period_s: float, causal: bool = False) -> Array:
    """Derivative along axis 0 by the 5-point least-squares filter (Khosla 5.1).

    ``x`` is (n, ...) sampled every ``period_s``. Non-causal: ``out[k]`` estimates the
    derivative at sample ``k`` and the first and last 2 samples are NaN. Causal:
    ``out[k]`` estimates the derivative at sample ``k - 2`` from ``x[k-4..k]`` and the first
    4 samples are NaN.
    """
    x = np.asarray(x, dtype=float)
    out = np.full(x.shape, np.nan)
    n = x.shape[0]
    if n < 5:
        return out
    d = (-2.0 * x[:-4] - x[1:-3] + x[3:-1] + 2.0 * x[4:]) / (10.0 * period_s)
    if causal:
        out[4:] = d
    else:
        out[2:-2] = d
    return out

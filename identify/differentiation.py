"""Differentiating recorded signals: Khosla's 5-point least-squares filter (section 5.1).

A parabola fitted by least squares to five points spaced ``T`` gives the derivative

.. math:: f'(x) = \\frac{-2 f(x-2T) - f(x-T) + f(x+T) + 2 f(x+2T)}{10 T}

exact on polynomials of degree 2; its white-noise gain is ``sqrt(10)/(10 T)``, 0.45 of a
central difference's ``sqrt(2)/(2 T)``. The causal form is the same filter two samples
late, ``f'(x - 2T)`` from ``f(x - 4T) .. f(x)``, for on-line use.

Its price is a droop: a harmonic at ``x = omega T`` comes out with gain
``(2 sin x + 4 sin 2x) / (10 x) = 1 - 17 x^2 / 30 + O(x^4)``, 0.08 % at 3 Hz sampled at
2 ms. Acceleration that low reads every inertia that much too high, which on a long 2 ms
recording is several standard deviations of the best-determined ones (the arm's largest
inertia combination: 0.08 % error against a 0.03 % standard deviation). The off-line
pipeline therefore uses :func:`sharpened_five_point_derivative`, the same filter
Richardson-extrapolated from spacings T and 2T, flat to ``O(x^4)`` (1e-6 at 3 Hz) for
27 % more white-noise gain.
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


SHARPENED_TAPS = np.array([1.0, 0.0, -7.5, -4.0, 0.0, 4.0, 7.5, 0.0, -1.0]) / 30.0
"""``(4 D_T - D_2T) / 3`` of the 5-point filter at spacings T and 2T, as coefficients of
f(x-4T) .. f(x+4T) (to be divided by T): the ``x^2`` droop of both cancels."""


def sharpened_five_point_derivative(x: Array, period_s: float) -> Array:
    """Derivative along axis 0 by Khosla's 5-point filter (5.1) at spacings T and 2T,
    combined as ``(4 D_T - D_2T) / 3`` (Richardson): exact on polynomials of degree 4, and
    its gain in the excitation band is 1 to ``O((omega T)^4)`` where the plain filter's is
    ``1 - 17 (omega T)^2 / 30``. The first and last 4 samples are NaN."""
    x = np.asarray(x, dtype=float)
    out = np.full(x.shape, np.nan)
    n = x.shape[0]
    if n < 9:
        return out
    out[4:-4] = sum(c * x[k : n - 8 + k] for k, c in enumerate(SHARPENED_TAPS) if c) / period_s
    return out

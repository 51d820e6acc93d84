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

The family, one module (each member differs on purpose, and each output depends on which):

- :func:`five_point_derivative`: Khosla's filter itself (and its causal form); what the
  low-pass choice measures acceleration noise with (twice applied), as it was calibrated.
- :func:`sharpened_five_point_derivative`: the same at spacings T and 2T (Richardson).
- :func:`uniform_derivative`: the off-line pipeline's, on a uniform grid: the sharpened
  filter inside, a least-squares cubic over nine samples at each end, where it has none.
- :func:`local_polynomial` / :func:`derivatives_on_times`: on the records' own, uneven time
  stamps (the payload estimator's; its stream form is
  :class:`identify.payload.filter.StreamFilter`).
- :func:`central_difference`: ``np.gradient`` on stamps or a period, for a smooth model
  prediction (the diagnosis's time-delay column), where the filters' latency and
  end samples would cost more than noise gain matters.
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


def uniform_derivative(x: Array, period: float, order: int = 1, source: Array | None = None) -> Array:
    """The identification pipeline's derivative of ``x`` (n, ...) sampled every ``period``:
    :func:`sharpened_five_point_derivative` inside (the plain filter's in-band droop would read every
    inertia too high); at the four samples at each end,
    where it has no neighbours, derivative ``order`` of a least-squares cubic over the nine
    samples of ``source`` there (``x`` itself for a first derivative, the positions for a
    second)."""
    d = sharpened_five_point_derivative(x, period)
    base = x if source is None else source
    if base.shape[0] >= 9:
        d[:4], d[-4:] = (cubic_end(base, end, order, period) for end in ("head", "tail"))
    elif base.shape[0] >= 2:
        d = np.gradient(x, period, axis=0)
    return d


def cubic_end(x: Array, end: str, order: int, period: float) -> Array:
    """Derivative ``order`` at the first (``"head"``) or last (``"tail"``) four samples of ``x``
    (n, ...), n >= 9, of the least-squares cubic over the nine samples there: what
    ``scipy.signal.savgol_filter(x, 9, 3, deriv=order, delta=period, axis=0, mode="interp")``
    gives there, by its own operations (``_fit_edge``: a scaled Vandermonde, LAPACK's ``gelsd``),
    so the same numbers to the bit, without importing ``scipy.signal`` (0.6 s of a process)."""
    from scipy.linalg import lstsq

    n = x.shape[0]
    start, first = (0, 0) if end == "head" else (n - 9, 5)
    window = np.asarray(x[start : start + 9], dtype=np.float64)
    xs = np.arange(0, 9, dtype=np.float64)
    powers = np.flip(np.arange(4, dtype=np.float64))
    lhs = xs[:, None] ** powers[None, :]
    scale = np.sqrt(np.sum(lhs * lhs, axis=0))
    lhs /= scale
    c = lstsq(lhs, window.reshape(9, -1), cond=9 * np.finfo(np.float64).eps)[0]
    c = (c.T / scale).T
    if order > 0:
        c = np.asarray(c[:-order], copy=True)
        for k in range(order):
            c *= np.arange(3 - k, order - k - 1, -1, dtype=np.float64).reshape((4 - order, 1))
    at = np.arange(first, first + 4, dtype=c.dtype).reshape(-1, 1)
    values = np.zeros_like(at)
    for j in range(c.shape[0]):
        values = values * at + c[j, ...]
    return (values / period**order).reshape((4, *x.shape[1:]))


def central_difference(x: Array, period: float, t: Array | None = None) -> Array:
    """d(x)/dt along axis 0 by central differences (one-sided at the ends): on the stamps
    ``t`` where they are given and strictly increasing, else every ``period``; zeros for
    fewer than two samples."""
    if x.shape[0] < 2:
        return np.zeros_like(x)
    return np.gradient(x, t, axis=0) if t is not None and np.all(np.diff(t) > 0) else np.gradient(x, period, axis=0)


HALF_WINDOW_S, POLY_DEGREE, MIN_WINDOW_POINTS = 0.05, 4, 7
"""Derivatives: the degree-4 least-squares polynomial through the records within 50 ms of
each one (at least 7 of them: records at 100 Hz and faster)."""


def local_polynomial(t: Array, x: Array, centres: Array | None = None, half_window_s: float = HALF_WINDOW_S,
                     degree: int = POLY_DEGREE, span: tuple[float, float] | None = None,
                     origin: float | None = None) -> tuple[Array, Array, Array, Array]:
    """Value, first and second derivative of ``x`` (n, ...) at the times of ``centres``
    (indices into ``t``; default all) from the least-squares polynomial of ``degree`` through
    every record within ``half_window_s`` of the centre, on the records' own time stamps
    (Savitzky-Golay over a fixed span of time, and right on uneven steps).

    A window of fixed *time*, not of a fixed number of records: the filter's response, hence
    its bias, is the same at 1 kHz and at 100 Hz. Degree 4 on +-50 ms gets a 1 Hz
    acceleration within 2e-4 of its amplitude at 100 Hz to 1 kHz, jittered or not (the
    twice-applied 5-point filter at 10 ms: 4.5e-3, which biased the payload's mass by 1 %). Returns ``(x0, x1, x2, ok)``; where ``ok`` is false (the window
    runs past either end of ``span``, by default ``t[0], t[-1]``, or holds fewer than
    ``MIN_WINDOW_POINTS`` records or fewer than two on a side) the values are NaN. Times are
    taken relative to ``origin`` (default ``t[0]``): the same origin, the same windows to the
    last bit however the records are batched.
    """
    t = np.asarray(t, float)
    x = np.asarray(x, float)
    n = t.size
    centres = np.arange(n) if centres is None else np.asarray(centres, int)
    shape = (centres.size, *x.shape[1:])
    out = [np.full(shape, np.nan) for _ in range(3)]
    ok = np.zeros(centres.size, bool)
    if n == 0 or centres.size == 0:
        return out[0], out[1], out[2], ok
    t0 = float(t[0]) if origin is None else origin
    first, last = (t[0], t[-1]) if span is None else span
    first, last = first - t0, last - t0
    t = t - t0  # stamps as seconds since 1970 keep their own rounding, not a billion seconds of it
    xf = x.reshape(n, -1)
    tc = t[centres]
    lo = np.searchsorted(t, tc - half_window_s, "left")
    hi = np.searchsorted(t, tc + half_window_s, "right")
    ok = (tc - half_window_s >= first) & (tc + half_window_s <= last) & (hi - lo >= MIN_WINDOW_POINTS)
    ok &= (centres - lo >= 2) & (hi - 1 - centres >= 2)
    good = np.flatnonzero(ok)
    if good.size == 0:
        return out[0], out[1], out[2], ok
    width = int((hi - lo)[good].max())
    powers = np.arange(degree + 1)
    chunk = max(1, 200_000 // (width * (degree + 1 + xf.shape[1])))
    res = np.empty((good.size, 3, xf.shape[1]))
    for a in range(0, good.size, chunk):
        g = good[a : a + chunk]
        j = lo[g, None] + np.arange(width)[None, :]
        inside = j < hi[g, None]
        j = np.minimum(j, n - 1)
        s = np.where(inside, (t[j] - tc[g, None]) / half_window_s, 0.0)
        v = (s[..., None] ** powers) * inside[..., None]  # (c, w, d+1), zero outside the window
        lhs = np.einsum("cwa,cwb->cab", v, v)
        rhs = np.einsum("cwa,cwk->cak", v, xf[j])
        coef = np.linalg.solve(lhs, rhs)[:, :3]
        res[a : a + chunk] = coef
    res[:, 1] /= half_window_s
    res[:, 2] *= 2.0 / half_window_s**2
    for k in range(3):
        out[k][good] = res[:, k].reshape((good.size, *x.shape[1:]))
    return out[0], out[1], out[2], ok


def derivatives_on_times(t: Array, x: Array) -> tuple[Array, Array]:
    """Non-causal velocity and acceleration of a recording (n, N) on its own time stamps
    (:func:`local_polynomial`); NaN within the half window of either end."""
    _, x1, x2, _ = local_polynomial(t, x)
    return x1, x2

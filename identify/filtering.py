"""Filtering chosen from the data: the excitation band, the noise level, the parallel filter.

Real logs are sampled 50-500 times faster than their excitation (Fourier excitations run at
0.05-0.3 Hz, logs at 100 Hz-1 kHz). Differentiating them twice by Khosla's 5-point filter
(5.1), whose white-noise gain is ``sqrt(10)/(10 T)``, then buries the acceleration in noise.
IDIM-LS practice (Gautier & Khalil; FIGAROH, BIRDy, FloBaRoID) is:

1. low-pass the kinematics with a zero-phase filter whose cut-off sits a few times above the
   excitation's highest harmonic, then differentiate (here: the 5-point filter);
2. filter *every column of the regressor and the torque* by the same low-pass ("parallel
   filtering"), so that no gain or phase separates the two sides of eq. (18) - including the
   Coulomb step, which a filter smooths in the torque and a sign function would keep sharp;
3. decimate both where the data are far oversampled.

:func:`choose_filter` finds the band from the spectrum of ``q`` (the highest frequency
where the position spectrum stands clear of its own noise floor), and the noise level from
what lies above the cut-off.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from .spatial import Array

CUTOFF_PER_BAND = 4.0
"""Cut-off = this times the excitation's band edge (a few times its highest harmonic)."""
BAND_THRESHOLD = 1e4
"""A frequency belongs to the excitation while the position spectrum exceeds its noise floor
(median over the top quarter of the spectrum) by this factor (40 dB)."""
PEAK_RANGE = 1e-8
"""... and within 80 dB of the spectrum's peak."""
MIN_CUTOFF_HZ = 1.0
"""Never below this: slower cut-offs smear start/stop transients over seconds."""
SAMPLES_PER_CUTOFF = 10.0
"""Decimate to at least this many samples per period of the cut-off (5x Nyquist)."""
MAX_CUTOFF_FRACTION = 0.4
"""At most this fraction of the Nyquist frequency (above it a low-pass does nothing useful)."""


@dataclass(frozen=True)
class ParallelFilter:
    """A zero-phase Butterworth low-pass at ``cutoff_hz`` (``None``: no filter) applied alike
    to the regressor's columns and the torque, then every ``decimation``-th sample kept, and
    ``edge`` samples left out at both ends (the forward-backward filter's transients)."""

    period_s: float
    cutoff_hz: float | None = None
    decimation: int = 1
    order: int = 4
    trim: int = 4  # the differentiators' own edges (two samples each, applied twice)

    @property
    def edge(self) -> int:
        """Samples at each end where the differentiators' edges and the zero-phase filter's
        start-up transient live."""
        if self.cutoff_hz is None:
            return self.trim
        return max(self.trim, int(np.ceil(1.5 / (self.cutoff_hz * self.period_s))))

    @property
    def settling(self) -> int:
        """Samples over which the zero-phase filter's response to a cut in its input dies
        out to 1e-13: its slowest pole decays at ``2 pi fc sin(pi / 2 order)`` per second."""
        if self.cutoff_hz is None:
            return 0
        rate = 2 * np.pi * self.cutoff_hz * np.sin(np.pi / (2 * self.order))
        return int(np.ceil(np.log(1e13) / (rate * self.period_s)))

    def smooth(self, x: Array, axis: int = 0) -> Array:
        """The low-pass alone along ``axis`` (zero phase, padded by odd reflection)."""
        if self.cutoff_hz is None:
            return np.asarray(x, dtype=float)
        return lowpass(x, self.period_s, self.cutoff_hz, self.order, axis=axis)

    def apply(self, x: Array, axis: int = 0) -> Array:
        """Low-pass, drop the edges, decimate: the equations that least squares sees."""
        y = self.smooth(x, axis)
        return np.take(y, self.kept(y.shape[axis]), axis=axis)

    def kept(self, n: int) -> Array:
        """Indices of the samples :meth:`apply` keeps out of ``n``."""
        edge = self.edge if n > 2 * self.edge else 0
        return np.arange(edge, n - edge, self.decimation)


def lowpass(x: Array, period_s: float, cutoff_hz: float, order: int = 4, axis: int = 0) -> Array:
    """Zero-phase Butterworth low-pass along ``axis`` (forward-backward, no delay).

    Each end is extended over four periods of the cut-off by a quintic fitted to the two periods before it, so
    that position, velocity *and acceleration* carry on through the ends (an odd reflection
    would force the curvature to zero there, which differentiation turns into large
    acceleration errors); short signals are returned unfiltered.
    """
    from .kernels.filter import forward_backward

    nyquist = 0.5 / period_s
    if not 0.0 < cutoff_hz < nyquist:
        raise ValueError(f"low-pass cut-off {cutoff_hz:g} Hz must lie in (0, {nyquist:g}) Hz, the Nyquist frequency of this recording")
    sos = _butter_sos(order, cutoff_hz / nyquist)
    x = np.moveaxis(np.asarray(x, dtype=float), axis, 0)
    n = x.shape[0]
    if n <= 3 * (2 * len(sos) + 1):
        return np.moveaxis(x.copy(), 0, axis)
    span = int(np.ceil(1.0 / (cutoff_hz * period_s)))
    fit = min(n, max(8, 2 * span))
    pad = 4 * span
    flat = x.reshape(n, -1)
    head = _extrapolate(flat[:fit][::-1], pad)[::-1]
    tail = _extrapolate(flat[n - fit :], pad)
    edge = min(pad, 3 * (2 * len(sos) + 1))
    y = _odd_extended(head, flat, tail, edge)
    forward_backward(sos, _steady_state(order, cutoff_hz / nyquist), y)  # scipy's sosfiltfilt, to the bit
    return np.moveaxis(y[edge + pad : edge + pad + n].reshape(x.shape), 0, axis)


@functools.lru_cache(maxsize=64)
def _butter_sos(order: int, wn: float) -> Array:
    """The Butterworth design (second-order sections), once per order and cut-off: the
    diagnosis filters thousands of candidate columns through the same filter, and designing it
    cost more than filtering a column. Read-only: every caller shares it."""
    from .butterworth import butter_lowpass_sos

    sos = np.asarray(butter_lowpass_sos(order, wn), dtype=float)
    sos.flags.writeable = False
    return sos


@functools.lru_cache(maxsize=64)
def _steady_state(order: int, wn: float) -> Array:
    """The cascade's steady-state delay line for a unit step (``sosfilt_zi``), once per design."""
    from .butterworth import sos_steady_state

    zi = np.asarray(sos_steady_state(_butter_sos(order, wn).copy()), dtype=float)
    zi.flags.writeable = False
    return zi


def _odd_extended(head: Array, flat: Array, tail: Array, edge: int) -> Array:
    """``[head; flat; tail]`` (m, k) with ``edge`` rows before and after, reflected about its
    end values (``sosfiltfilt``'s ``padtype="odd"``), written once into a new array that the
    filter then overwrites (two concatenations of a 250-column candidate array cost more than
    the filter)."""
    m = head.shape[0] + flat.shape[0] + tail.shape[0]
    y = np.empty((m + 2 * edge, flat.shape[1]))
    mid = y[edge : edge + m]
    mid[: head.shape[0]], mid[head.shape[0] : m - tail.shape[0]], mid[m - tail.shape[0] :] = head, flat, tail
    y[:edge] = 2 * mid[:1] - mid[edge:0:-1]
    y[edge + m :] = 2 * mid[-1:] - mid[-2 : -(edge + 2) : -1]
    return y


def _extrapolate(x: Array, count: int, degree: int = 5) -> Array:
    """``count`` samples after the end of ``x`` (m, k) from a least-squares quintic over it."""
    m = x.shape[0]
    s = np.arange(m, dtype=float) / m
    coef = np.polynomial.polynomial.polyfit(s, x, min(degree, m - 1))
    ahead = (m + np.arange(count, dtype=float)) / m
    return np.asarray(np.polynomial.polynomial.polyval(ahead, coef).T, dtype=float).reshape(count, -1)


@dataclass(frozen=True)
class Band:
    """What the spectrum of a recording's positions says."""

    band_hz: float  # highest frequency the excitation occupies
    cutoff_hz: float | None  # chosen zero-phase low-pass cut-off (None: none needed)
    decimation: int
    period_s: float
    reason: str


def excitation_band(q: Array, period_s: float) -> float:
    """Highest frequency (Hz) at which the positions' spectrum stands ``BAND_THRESHOLD`` above
    its noise floor, over all joints that move.

    Each joint is detrended and Hann-windowed; the noise floor is the median of its power
    spectrum over the top quarter of the band (white: quantisation, sensor noise).
    """
    q = np.asarray(q, dtype=float)
    n = q.shape[0]
    if n < 16:
        return 0.5 / period_s
    t = np.arange(n)
    window = np.hanning(n)
    freqs = np.fft.rfftfreq(n, period_s)
    edge = 0.0
    for j in range(q.shape[1]):
        x = q[:, j]
        if np.ptp(x) < 1e-6:
            continue
        x = x - np.polyval(np.polyfit(t, x, 1), t)
        power = np.abs(np.fft.rfft(x * window)) ** 2
        floor = float(np.median(power[3 * power.size // 4 :]))
        # 40 dB above the noise floor, and within 80 dB of the peak (noise-free data has
        # no floor to speak of: the window's leakage would pass for excitation)
        level = max(BAND_THRESHOLD * floor, PEAK_RANGE * float(power[1:].max()))
        above = np.flatnonzero(power[1:] > level) + 1
        if above.size:
            edge = max(edge, float(freqs[above[-1]]))
    return edge if edge > 0 else float(freqs[min(1, freqs.size - 1)])


def choose_filter(q: Array, period_s: float) -> Band:
    """The parallel filter for a recording sampled every ``period_s`` (module docstring)."""
    nyquist = 0.5 / period_s
    band = excitation_band(q, period_s)
    cutoff = max(CUTOFF_PER_BAND * band, MIN_CUTOFF_HZ)
    if cutoff >= MAX_CUTOFF_FRACTION * nyquist:
        return Band(band, None, 1, period_s,
                    f"excitation up to {band:.3g} Hz; {CUTOFF_PER_BAND:g}x that is beyond {MAX_CUTOFF_FRACTION:g} of the "
                    f"Nyquist frequency {nyquist:.4g} Hz: no low-pass")
    decimation = max(1, int(np.floor(1.0 / (period_s * SAMPLES_PER_CUTOFF * cutoff))))
    return Band(band, cutoff, decimation, period_s,
                f"excitation up to {band:.3g} Hz (position spectrum 40 dB above its noise floor); zero-phase "
                f"{cutoff:.3g} Hz low-pass ({CUTOFF_PER_BAND:g}x, at least {MIN_CUTOFF_HZ:g} Hz) on the kinematics, "
                f"the regressor and the torque alike; decimated {decimation}:1 to {1.0 / (period_s * decimation):.4g} Hz")


def noise_level(x: Array, filt: ParallelFilter) -> Array:
    """Per-column standard deviation of what the low-pass removes (the measurement noise
    above the cut-off), or NaN without a filter."""
    if filt.cutoff_hz is None:
        return np.full(np.shape(x)[1], np.nan)
    r = np.asarray(x, float) - filt.smooth(x)
    e = filt.edge
    r = r[e : r.shape[0] - e] if r.shape[0] > 2 * e + 2 else r
    return np.asarray(np.std(r, axis=0), dtype=float)

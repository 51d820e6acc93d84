"""What the identification computes without importing ``scipy.signal`` (issue 65: its import was
a sixth of an ``armid identify`` process) is scipy's to the bit: the Butterworth design and its
steady state (:mod:`identify.butterworth`) and the cubic at the ends of the derivative
(:func:`identify.differentiation.cubic_end`), against scipy itself."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import butter, savgol_filter, sosfilt_zi

from armid.identify.butterworth import butter_lowpass_sos, sos_steady_state
from armid.identify.differentiation import cubic_end, uniform_derivative

CUTOFFS = [*np.logspace(-4, np.log10(0.999), 60), 0.5, 2 * 10 / 500, 2 * 2.02 / 500, 2 * 7.5 / 100]


@pytest.mark.parametrize("order", range(1, 9))
def test_the_butterworth_design_is_scipys(order: int) -> None:
    for wn in CUTOFFS:
        sos = butter_lowpass_sos(order, float(wn))
        reference = butter(order, float(wn), output="sos")
        assert np.array_equal(sos, reference), (order, wn)
        assert np.array_equal(sos_steady_state(sos), sosfilt_zi(reference)), (order, wn)


def test_a_cut_off_outside_the_band_is_refused() -> None:
    for wn in (0.0, 1.0, 1.5, -0.1):
        with pytest.raises(ValueError):
            butter_lowpass_sos(4, wn)


@pytest.mark.parametrize("shape", [(9,), (9, 6), (20, 3), (1000, 7), (50, 2, 3)])
def test_the_ends_of_the_derivative_are_savgol_filters(shape: tuple[int, ...]) -> None:
    rng = np.random.default_rng(len(shape) * 100 + shape[0])
    for order in (0, 1, 2):
        for period in (0.002, 0.01, 1 / 3):
            x = rng.normal(size=shape).cumsum(axis=0) * rng.uniform(0.1, 100)
            reference = savgol_filter(x, 9, 3, deriv=order, delta=period, axis=0, mode="interp")
            assert np.array_equal(cubic_end(x, "head", order, period), reference[:4])
            assert np.array_equal(cubic_end(x, "tail", order, period), reference[-4:])


def test_the_derivative_takes_its_ends_from_the_cubic() -> None:
    t = np.arange(200) * 0.01
    x = np.column_stack([np.sin(t), t**3])
    d = uniform_derivative(x, 0.01)
    reference = savgol_filter(x, 9, 3, deriv=1, delta=0.01, axis=0, mode="interp")
    assert np.array_equal(d[:4], reference[:4]) and np.array_equal(d[-4:], reference[-4:])

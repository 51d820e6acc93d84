"""The compiled part of the zero-phase low-pass (:func:`identify.filtering.lowpass`).

The diagnosis filters every candidate column at the input's full rate (a joint's 119 cogging
periods at 50,000 samples are 238 columns), and ``scipy.signal.sosfiltfilt`` along the
samples of an (n, k) array copied each column into a contiguous row and back, twice per
pass: the copies cost as much as the filtering and made the filter a third of a diagnosis.
This kernel runs the same recursion on the (n, k) array in place, the k columns side by side
in SIMD lanes. Each column sees exactly scipy's operations in scipy's order (its
``_sosfilt`` loop: transposed direct form II per second-order section), so the result is
scipy's to the bit (``tests/test_differentiation_and_data.py``). It releases the interpreter's
lock: the diagnosis filters its joints' candidates in threads side by side (identify.kernels.threads).
"""

from __future__ import annotations

import numba
import numpy as np

_njit = numba.njit(cache=True, nogil=True, error_model="numpy", boundscheck=False)


@_njit
def _pass(sos: np.ndarray, state: np.ndarray, x: np.ndarray, start: int, step: int) -> None:
    """One direction of the cascade over the rows of ``x`` (m, k), in place, from row
    ``start`` by ``step`` (1 forward, -1 backward); ``state`` (sections, 2, k) is the filter's
    delay line, updated."""
    m, k = x.shape
    n = start
    for _ in range(m):
        for s in range(sos.shape[0]):
            b0, b1, b2, a1, a2 = sos[s, 0], sos[s, 1], sos[s, 2], sos[s, 4], sos[s, 5]
            for i in range(k):
                x_cur = x[n, i]
                x_new = b0 * x_cur + state[s, 0, i]
                state[s, 0, i] = b1 * x_cur - a1 * x_new + state[s, 1, i]
                state[s, 1, i] = b2 * x_cur - a2 * x_new
                x[n, i] = x_new
        n += step


@_njit
def forward_backward(sos: np.ndarray, zi: np.ndarray, x: np.ndarray) -> None:
    """``sosfiltfilt``'s two passes on the already padded ``x`` (m, k) along its rows, in
    place: forward from the steady state ``zi`` (sections, 2) scaled by the first row, then
    backward from it scaled by the forward pass's last row."""
    m, k = x.shape
    state = np.empty((sos.shape[0], 2, k))
    for row, start, step in ((0, 0, 1), (m - 1, m - 1, -1)):
        for s in range(sos.shape[0]):
            for i in range(k):
                state[s, 0, i] = zi[s, 0] * x[row, i]
                state[s, 1, i] = zi[s, 1] * x[row, i]
        _pass(sos, state, x, start, step)

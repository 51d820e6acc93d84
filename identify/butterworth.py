"""The Butterworth low-pass design of the zero-phase filter (:func:`identify.filtering.lowpass`):
scipy's ``butter(order, wn, output="sos")`` and ``sosfilt_zi``, in scipy's own operations and
order so that every coefficient is scipy's to the bit (``tests/test_scipy_ports.py``
compares them over orders and cut-offs). Done here because importing ``scipy.signal`` for them
cost more than a whole identification's filtering: 0.6 s of an ``armid identify`` process on the
2-core machine, most of it the docstrings of ``scipy.stats``, which ``scipy.signal`` imports.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .spatial import Array


def butter_lowpass_sos(order: int, wn: float) -> Array:
    """``scipy.signal.butter(order, wn, output="sos")``: the analog prototype's poles, the
    pre-warped cut-off, the bilinear transform and the pairing into second-order sections
    (nearest zeros to the poles closest to the unit circle, last section first), in scipy's
    own operations and order."""
    if not 0.0 < wn < 1.0:
        raise ValueError("Digital filter critical frequencies must be 0 < Wn < 1")
    m = np.arange(-order + 1, order, 2, dtype=np.float64)
    p = -np.exp(1j * np.pi * m / (2 * order))
    z = np.asarray([], dtype=np.float64)
    warped = float(2 * 2.0 * np.tan(np.pi * np.asarray(wn, dtype=np.float64) / 2.0))
    degree = p.shape[0] - z.shape[0]
    z, p, k = warped * z, warped * p, 1.0 * warped**degree  # lp2lp_zpk
    z_z, p_z = (4.0 + z) / (4.0 - z), (4.0 + p) / (4.0 - p)  # bilinear_zpk at fs = 2
    z_z = np.concatenate((z_z, -np.ones(degree)))
    k_z = k * np.real(np.prod(4.0 - z) / np.prod(4.0 - p))
    return _zpk2sos(z_z, p_z, k_z)


def _zpk2sos(z: Array, p: Array, k: Any) -> Array:
    """scipy's ``zpk2sos`` for a digital filter with ``pairing="nearest"``."""
    k = np.asarray(k)
    p = np.concatenate((p, np.zeros(max(len(z) - len(p), 0))))
    z = np.concatenate((z, np.zeros(max(len(p) - len(z), 0))))
    n_sections = (max(len(p), len(z)) + 1) // 2
    if len(p) % 2 == 1:
        p = np.concatenate((p, [0.0]))
        z = np.concatenate((z, [0.0]))
    z = np.concatenate(_cplxreal(z))
    p = np.concatenate(_cplxreal(p))
    k = k.real

    def idx_worst(p: Array) -> Any:
        return np.argmin(np.abs(1 - np.abs(p)))

    sos = np.zeros((n_sections, 6))
    for si in range(n_sections - 1, -1, -1):
        p1_idx = idx_worst(p)
        p1 = p[p1_idx]
        p = np.delete(p, p1_idx)
        if np.isreal(p1) and np.isreal(p).sum() == 0:
            z1_idx = _nearest_idx(z, p1, "real")
            z1 = z[z1_idx]
            z = np.delete(z, z1_idx)
            sos[si] = _single_sos([z1, 0], [p1, 0], 1)
        elif len(p) + 1 == len(z) and not np.isreal(p1) and np.isreal(p).sum() == 1 and np.isreal(z).sum() == 1:
            z1_idx = _nearest_idx(z, p1, "complex")
            z1 = z[z1_idx]
            z = np.delete(z, z1_idx)
            sos[si] = _single_sos([z1, z1.conj()], [p1, p1.conj()], 1)
        else:
            if np.isreal(p1):
                prealidx = np.flatnonzero(np.isreal(p))
                p2_idx = prealidx[idx_worst(p[prealidx])]
                p2 = p[p2_idx]
                p = np.delete(p, p2_idx)
            else:
                p2 = p1.conj()
            if len(z) > 0:
                z1_idx = _nearest_idx(z, p1, "any")
                z1 = z[z1_idx]
                z = np.delete(z, z1_idx)
                if not np.isreal(z1):
                    sos[si] = _single_sos([z1, z1.conj()], [p1, p2], 1)
                elif len(z) > 0:
                    z2_idx = _nearest_idx(z, p1, "real")
                    z2 = z[z2_idx]
                    z = np.delete(z, z2_idx)
                    sos[si] = _single_sos([z1, z2], [p1, p2], 1)
                else:
                    sos[si] = _single_sos([z1], [p1, p2], 1)
            else:
                sos[si] = _single_sos([], [p1, p2], 1)
    sos[0][:3] *= k
    return sos


def _cplxreal(z: Array) -> tuple[Array, Array]:
    """scipy's ``_cplxreal``: the complex values of ``z`` (one of each conjugate pair) and its real ones."""
    z = np.atleast_1d(z)
    if z.size == 0:
        return z, z
    tol = 100 * np.finfo((1.0 * z).dtype).eps
    z = z[np.lexsort((abs(z.imag), z.real))]
    real_indices = abs(z.imag) <= tol * abs(z)
    zr = z[real_indices].real
    if len(zr) == len(z):
        return np.array([]), zr
    z = z[~real_indices]
    zp = z[z.imag > 0]
    zn = z[z.imag < 0]
    if len(zp) != len(zn):
        raise ValueError("Array contains complex value with no matching conjugate.")
    same_real = np.diff(zp.real) <= tol * abs(zp[:-1])
    diffs = np.diff(np.concatenate(([0], same_real, [0])))
    run_starts = np.nonzero(diffs > 0)[0]
    run_stops = np.nonzero(diffs < 0)[0]
    for i in range(len(run_starts)):
        start = run_starts[i]
        stop = run_stops[i] + 1
        for chunk in (zp[start:stop], zn[start:stop]):
            chunk[...] = chunk[np.lexsort([abs(chunk.imag)])]
    if any(abs(zp - zn.conj()) > tol * abs(zn)):
        raise ValueError("Array contains complex value with no matching conjugate.")
    return (zp + zn.conj()) / 2, zr


def _nearest_idx(fro: Array, to: Any, which: str) -> Any:
    """scipy's ``_nearest_real_complex_idx``."""
    order = np.argsort(np.abs(fro - to))
    if which == "any":
        return order[0]
    mask = np.isreal(fro[order])
    if which == "complex":
        mask = ~mask
    return order[np.nonzero(mask)[0][0]]


def _single_sos(z: list[Any], p: list[Any], k: float) -> Array:
    """scipy's ``_single_zpksos``: one section from its zeros and poles."""
    sos = np.zeros(6)
    zz, pp = np.asarray(z), np.asarray(p)
    kk = np.atleast_1d(np.asarray(k, dtype=np.result_type(np.real(zz), np.real(pp), k)))
    b = np.multiply(kk, _poly(zz))
    a = np.atleast_1d(np.asarray(_poly(pp)))
    sos[3 - len(b) : 3] = b
    sos[6 - len(a) : 6] = a
    return sos


def _poly(zeros: Array) -> Array:
    """scipy.signal's ``poly``: the monic polynomial with these roots, real where they pair."""
    zeros = np.atleast_1d(np.asarray(zeros))
    if zeros.shape[0] == 0:
        return np.asarray(1.0, dtype=np.real(zeros).dtype)
    a = np.ones((1,), dtype=zeros.dtype)
    one = np.ones_like(zeros[0])
    for zero in zeros:
        a = np.convolve(a, np.stack((one, -zero)), mode="full")
    if np.iscomplexobj(a):
        roots = np.asarray(zeros, dtype=np.complex128)
        if np.all(np.sort(np.imag(roots)) == np.sort(np.imag(np.conj(roots)))):
            a = np.asarray(np.real(a), copy=True)
    return a


def sos_steady_state(sos: Array) -> Array:
    """``scipy.signal.sosfilt_zi``: each section's delay line in the steady state of a unit
    step (``lfilter_zi``: ``(I - A^T) zi = b[1:] - a[1:] b[0]``), scaled by the gain of the
    sections before it; scipy's operations, as :func:`butter_lowpass_sos`."""
    zi = np.empty((sos.shape[0], 2), dtype=sos.dtype)
    scale = 1.0
    for section in range(sos.shape[0]):
        b, a = sos[section, :3], sos[section, 3:]
        zi[section, ...] = scale * _lfilter_zi(b, a)
        scale *= np.sum(b) / np.sum(a)
    return zi


def _lfilter_zi(b: Array, a: Array) -> Array:
    while a.shape[0] > 1 and a[0] == 0.0:
        a = a[1:]
    if a[0] != 1.0:
        b = b / a[0]
        a = a / a[0]
    n = max(a.shape[0], b.shape[0])
    companion = np.zeros((n - 1, n - 1), dtype=(-a[1:] / (1.0 * a[0:1])).dtype)
    companion[0, :] = -a[1:] / (1.0 * a[0:1])
    companion[np.arange(1, n - 1), np.arange(0, n - 2)] = 1
    i_minus_a = np.asarray(np.eye(n - 1) - companion.T, dtype=np.result_type(a, b))
    return np.linalg.solve(i_minus_a, b[1:] - a[1:] * b[0])

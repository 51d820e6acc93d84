"""The error metrics every report uses (INTERFACES.md, 'Metrics'), in torque units."""

from __future__ import annotations

from typing import Any

import numpy as np

from .spatial import Array


def relative_error(tau: Array, tau_hat: Array) -> float:
    """``||tau - tau_hat||_F / ||tau||_F`` over all joints and samples."""
    return float(np.linalg.norm(tau - tau_hat) / np.linalg.norm(tau))


def rms(tau: Array, tau_hat: Array) -> Array:
    """Per joint ``sqrt(mean((tau_j - tau_hat_j)^2))``."""
    return np.sqrt(np.mean((tau - tau_hat) ** 2, axis=0))


def relative(tau: Array, tau_hat: Array) -> Array:
    """Per joint ``||tau_j - tau_hat_j|| / ||tau_j||``."""
    return np.linalg.norm(tau - tau_hat, axis=0) / np.linalg.norm(tau, axis=0)


def summary(tau: Array, tau_hat: Array) -> dict[str, Any]:
    """The three metrics as the JSON outputs carry them."""
    return {
        "relative_error": relative_error(tau, tau_hat),
        "rms": [float(x) for x in rms(tau, tau_hat)],
        "relative": [float(x) for x in relative(tau, tau_hat)],
    }


def masked_summary(tau: Array, tau_hat: Array, used: Array) -> dict[str, Any]:
    """:func:`summary` over the equations ``used`` (n, N) only (the others count as absent)."""
    used = np.asarray(used, bool)
    e = np.where(used, tau - tau_hat, 0.0)
    y = np.where(used, tau, 0.0)
    count = np.maximum(used.sum(axis=0), 1)
    return {
        "relative_error": float(np.linalg.norm(e)) / max(float(np.linalg.norm(y)), 1e-300),
        "rms": [float(x) for x in np.sqrt((e**2).sum(axis=0) / count)],
        "relative": [float(x) for x in np.linalg.norm(e, axis=0) / np.maximum(np.linalg.norm(y, axis=0), 1e-300)],
        "equations": int(used.sum()),
    }

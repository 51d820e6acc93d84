"""Effects beyond the rigid body, as extra regressor columns acting on one joint.

The catalogue names are fixed by INTERFACES.md. Effects linear in their parameters are
columns here; the ones nonlinear in a parameter (Stribeck velocity, cogging period, delay,
tilt) are searched by the diagnosis, which builds on the same interface.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .spatial import Array

ColumnFunction = Callable[[Array, Array, Array], Array]


@dataclass(frozen=True)
class LinearEffect:
    """An effect on joint ``joint`` (0-based) with ``tau_j += columns(q, qd, qdd) @ params``."""

    effect: str
    joint: int
    parameter_names: tuple[str, ...]
    column_function: ColumnFunction

    def columns(self, q: Array, qd: Array, qdd: Array) -> Array:
        """(n, k) columns for the joint's torque row."""
        return self.column_function(q[:, self.joint], qd[:, self.joint], qdd[:, self.joint])

    def labels(self) -> list[str]:
        """Column names in the parameter list: parameter name plus the 1-based joint."""
        return [f"{p}{self.joint + 1}" for p in self.parameter_names]


def _viscous(q: Array, qd: Array, qdd: Array) -> Array:
    return qd[:, None]


def _coulomb(q: Array, qd: Array, qdd: Array) -> Array:
    return np.sign(qd)[:, None]


def _offset(q: Array, qd: Array, qdd: Array) -> Array:
    return np.ones((q.shape[0], 1))


def _rotor(q: Array, qd: Array, qdd: Array) -> Array:
    return qdd[:, None]


LINEAR_EFFECTS: dict[str, tuple[tuple[str, ...], ColumnFunction]] = {
    "viscous_friction": (("fv",), _viscous),
    "coulomb_friction": (("fc",), _coulomb),
    "torque_offset": (("offset",), _offset),
    "rotor_inertia": (("ia",), _rotor),
}
"""Effects that are linear in their parameters: name -> (parameter names, columns)."""

CATALOGUE = (
    "viscous_friction",
    "coulomb_friction",
    "stribeck_friction",
    "torque_offset",
    "rotor_inertia",
    "torque_gain",
    "time_delay",
    "cogging",
    "spring",
    "gravity_tilt",
)
"""Every effect name INTERFACES.md fixes."""


def linear_effect(name: str, joint: int) -> LinearEffect:
    """The effect ``name`` on 0-based ``joint``; ``KeyError`` if it is not linear."""
    params, fn = LINEAR_EFFECTS[name]
    return LinearEffect(name, joint, params, fn)


def effect_columns(effects: list[LinearEffect], q: Array, qd: Array, qdd: Array) -> Array:
    """(n, N, k_total) extra regressor columns: each effect's columns in its joint's row."""
    n, nj = q.shape
    widths = [len(e.parameter_names) for e in effects]
    out = np.zeros((n, nj, sum(widths)))
    k = 0
    for e, wdt in zip(effects, widths):
        out[:, e.joint, k : k + wdt] = e.columns(q, qd, qdd)
        k += wdt
    return out

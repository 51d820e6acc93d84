"""Effects beyond the rigid body, as extra regressor columns acting on one joint.

The catalogue names are fixed by INTERFACES.md. Effects linear in their parameters are
columns here; the ones nonlinear in a parameter (Stribeck velocity, cogging period, delay,
tilt) are searched by the diagnosis, which builds on the same interface. Load-dependent
Coulomb friction is bilinear (its load is the model's own torque): a column once the load is
fixed, which the identification does by fixed-point passes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from .dynamics import regressor
from .robot import Robot
from .spatial import Array

ColumnFunction = Callable[[Array, Array, Array], Array]


@dataclass(frozen=True)
class LinearEffect:
    """An effect on joint ``joint`` (0-based) with ``tau_j += columns(q, qd, qdd) @ params``.

    ``setting`` holds the effect's fixed nonlinear parameters (a Coulomb model's smoothing
    velocity, a Stribeck velocity), chosen on a grid by the identification.
    """

    effect: str
    joint: int
    parameter_names: tuple[str, ...]
    column_function: ColumnFunction
    setting: tuple[tuple[str, float], ...] = ()

    def columns(self, q: Array, qd: Array, qdd: Array) -> Array:
        """(n, k) columns for the joint's torque row."""
        return self.column_function(q[:, self.joint], qd[:, self.joint], qdd[:, self.joint])

    def labels(self) -> list[str]:
        """Column names in the parameter list: parameter name plus the 1-based joint."""
        return [f"{p}{self.joint + 1}" for p in self.parameter_names]

    def with_setting(self, **setting: float) -> LinearEffect:
        """The same effect with other fixed nonlinear parameters."""
        return linear_effect(self.effect, self.joint, **{**dict(self.setting), **setting})


@dataclass(frozen=True)
class LoadFriction(LinearEffect):
    """Coulomb friction that grows with the torque the joint transmits,
    ``fl |tau_load_j| smooth_sign(qd_j)``: a gear's (a harmonic drive's) friction under load,
    its efficiency lower the more it carries. ``tau_load`` is the rigid-body torque of the
    parameters ``load_parameters`` (Khosla's phi, 10 per link) along the whole motion, so the
    column needs every joint's motion: :meth:`columns` takes the whole arrays (and, where the
    caller has it, the load itself). Linear in ``fl`` once the load is fixed; the
    identification fixes it from its own estimate (identify.identification).
    ``follows_coulomb``: its sign's smoothing moves with the same joint's searched Coulomb
    smoothing (False: the robot file fixed it)."""

    robot: Robot = field(kw_only=True)
    load_parameters: tuple[float, ...] = field(kw_only=True)
    follows_coulomb: bool = field(default=True, kw_only=True)

    def load(self, q: Array, qd: Array, qdd: Array) -> Array:
        """(n, N) the rigid-body torque of ``load_parameters`` (eq. 18 with that phi)."""
        return np.asarray(regressor(self.robot, q, qd, qdd) @ np.asarray(self.load_parameters))

    def columns(self, q: Array, qd: Array, qdd: Array, load: Array | None = None) -> Array:
        tau = self.load(q, qd, qdd) if load is None else load
        return (np.abs(tau[:, self.joint]) * self.direction(qd))[:, None]

    def direction(self, qd: Array) -> Array:
        """``smooth_sign(qd_j)`` with the effect's smoothing."""
        return smooth_sign(qd[:, self.joint], dict(self.setting).get("smoothing", 0.0))

    def with_setting(self, **setting: float) -> LinearEffect:
        return replace(self, setting=tuple({**dict(self.setting), **setting}.items()))


def load_friction(robot: Robot, joint: int, load_parameters: Array, smoothing: float = 0.0, follows_coulomb: bool = True) -> LoadFriction:
    """``load_dependent_coulomb`` on 0-based ``joint``, its load the rigid-body torque of
    ``load_parameters`` (10 N,)."""
    phi = tuple(float(x) for x in np.asarray(load_parameters, float)[: robot.n_parameters])
    return LoadFriction("load_dependent_coulomb", joint, ("fl",), _whole_motion, (("smoothing", float(smoothing)),),
                        robot=robot, load_parameters=phi, follows_coulomb=follows_coulomb)


def _whole_motion(q: Array, qd: Array, qdd: Array) -> Array:
    raise TypeError("load_dependent_coulomb needs every joint's motion: call LoadFriction.columns")


def _viscous(q: Array, qd: Array, qdd: Array) -> Array:
    return qd[:, None]


def smooth_sign(qd: Array, velocity: float) -> Array:
    """``sign(qd)`` (velocity 0) or ``tanh(qd / velocity)``: Coulomb friction that builds up
    over a velocity band instead of jumping (pre-sliding; the published Panda model's form)."""
    return np.sign(qd) if velocity <= 0.0 else np.tanh(qd / velocity)


def _coulomb(q: Array, qd: Array, qdd: Array, velocity: float) -> Array:
    return smooth_sign(qd, velocity)[:, None]


def _stribeck(q: Array, qd: Array, qdd: Array, velocity: float, smoothing: float) -> Array:
    return (smooth_sign(qd, smoothing) * np.exp(-((qd / velocity) ** 2)))[:, None]


def _offset(q: Array, qd: Array, qdd: Array) -> Array:
    return np.ones((q.shape[0], 1))


def _rotor(q: Array, qd: Array, qdd: Array) -> Array:
    return qdd[:, None]


def _spring(q: Array, qd: Array, qdd: Array) -> Array:
    return q[:, None]


def _cogging(q: Array, qd: Array, qdd: Array, period: float) -> Array:
    """A torque periodic in the joint's own position (cogging, a gear's or a cable's ripple):
    ``a sin(2 pi q / period) + b cos(2 pi q / period)``."""
    x = 2.0 * np.pi * q / period
    return np.column_stack([np.sin(x), np.cos(x)])


LINEAR_EFFECTS: dict[str, tuple[tuple[str, ...], ColumnFunction]] = {
    "viscous_friction": (("fv",), _viscous),
    "torque_offset": (("offset",), _offset),
    "rotor_inertia": (("ia",), _rotor),
    "spring": (("ks",), _spring),
}
"""Effects that are linear in their parameters: name -> (parameter names, columns)."""

SETTINGS: dict[str, tuple[str, tuple[float, ...]]] = {
    "coulomb_friction": ("velocity", (0.0, 0.003, 0.01, 0.03, 0.1)),
    "stribeck_friction": ("velocity", (0.01, 0.02, 0.05, 0.1, 0.2, 0.5)),
}
"""Effects linear given one fixed parameter, with the grid the identification searches
(rad/s or m/s): Coulomb friction's smoothing velocity (0: a sharp sign), the Stribeck velocity."""

CATALOGUE = (
    "viscous_friction",
    "coulomb_friction",
    "stribeck_friction",
    "torque_offset",
    "rotor_inertia",
    "torque_gain",
    "load_dependent_coulomb",
    "time_delay",
    "cogging",
    "spring",
    "gravity_tilt",
)
"""Every effect name INTERFACES.md fixes."""


PROFILED = ("torque_gain",)
"""Effects a robot file may declare whose parameter is not linear: a joint's torque gain (the
joint measures ``gain`` times the model's torque: a torque constant off, where the recording
gives currents), fitted by profiling the least-squares fit over it (identify.identification)."""

LOAD_DEPENDENT = ("load_dependent_coulomb",)
"""Effects whose column needs the model's own rigid-body torque (:class:`LoadFriction`): its
sign's smoothing follows the same joint's Coulomb friction unless ``velocity`` is declared."""

FIXED: dict[str, str] = {"cogging": "period_rad"}
"""Effects linear given one fixed parameter that a robot file (or the diagnosis) must give:
cogging's period in the joint's position (rad, or m for a prismatic joint)."""


def linear_effect(name: str, joint: int, **setting: float) -> LinearEffect:
    """The effect ``name`` on 0-based ``joint``; ``KeyError`` if it is not linear.

    ``coulomb_friction`` takes ``velocity`` (0: ``sign(qd)``); ``stribeck_friction`` takes
    ``velocity`` (the Stribeck velocity ``v_s``: ``fs sign(qd) exp(-(qd/v_s)^2)``, the
    friction above Coulomb's at low speed) and ``smoothing`` (the sign's smoothing velocity,
    as Coulomb's: the identification sets it to the same joint's Coulomb smoothing); ``cogging`` needs ``period_rad``.
    """
    if name == "coulomb_friction":
        v = float(setting.get("velocity", 0.0))
        return LinearEffect(name, joint, ("fc",), partial(_coulomb, velocity=v), (("velocity", v),))
    if name == "stribeck_friction":
        vs, smoothing = float(setting.get("velocity", 0.1)), float(setting.get("smoothing", 0.0))
        return LinearEffect(name, joint, ("fs",), partial(_stribeck, velocity=vs, smoothing=smoothing), (("velocity", vs), ("smoothing", smoothing)))
    if name == "cogging":
        period = float(setting["period_rad"])
        return LinearEffect(name, joint, ("cog_a", "cog_b"), partial(_cogging, period=period), (("period_rad", period),))
    params, fn = LINEAR_EFFECTS[name]
    return LinearEffect(name, joint, params, fn)


def effect_columns(effects: list[LinearEffect], q: Array, qd: Array, qdd: Array, rigid: Array | None = None,
                   load: Array | None = None) -> Array:
    """(n, N, k_total) extra regressor columns: each effect's columns in its joint's row.
    Where the caller has them, ``rigid`` is the motion's rigid-body regressor (n, N, 10 N) of
    the effects' robot, and ``load`` the load-dependent friction's load (n, N) itself (the
    model's own rigid-body torque): then its load costs no second regressor."""
    n, nj = q.shape
    widths = [len(e.parameter_names) for e in effects]
    out = np.zeros((n, nj, sum(widths)))
    loads: dict[tuple[Robot, tuple[float, ...]], Array] = {}  # one load per parameter set, not per joint
    k = 0
    for e, wdt in zip(effects, widths):
        if isinstance(e, LoadFriction):
            key = (e.robot, e.load_parameters)
            if key not in loads:
                loads[key] = load if load is not None else (e.load(q, qd, qdd) if rigid is None else rigid @ np.asarray(e.load_parameters))
            out[:, e.joint, k : k + wdt] = e.columns(q, qd, qdd, load=loads[key])
        else:
            out[:, e.joint, k : k + wdt] = e.columns(q, qd, qdd)
        k += wdt
    return out

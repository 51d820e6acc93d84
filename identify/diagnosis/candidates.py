"""The catalogue of effects a model may lack, as candidate regressor columns.

Each effect of the catalogue (the module docstring of :mod:`identify.diagnosis` lists them)
on each joint, or on the whole arm, is a :class:`Candidate`: a function of the data
(:class:`~identify.diagnosis_data.StackedData`) giving its columns, linear in its parameters. An
effect with one nonlinear parameter is one candidate per value of it on a grid (a Stribeck
velocity, a cogging period). What each effect can be mistaken for (:data:`LOOKALIKES`) and
the experiment that tells the two apart (:data:`SEPARATE`) go with the catalogue, as do the
parameters a fitted candidate reports (:func:`candidate_parameters`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from ..dynamics import regressor
from ..robot import Robot
from ..spatial import Array
from .data import StackedData, torque_rate

LOOKALIKES = {
    "coulomb_friction": "stribeck_friction",
    "stribeck_friction": "coulomb_friction",
    "torque_gain": "rotor_inertia",
    "rotor_inertia": "torque_gain",
    "time_delay": "viscous_friction",
    "viscous_friction": "time_delay",
    "torque_offset": "spring",
    "spring": "torque_offset",
    "load_dependent_coulomb": "coulomb_friction",
}


NESTING = {"torque_offset": "spring"}
"""A one-joint effect and the one that holds it (its columns and one more): an offset is a
spring's torque at its rest position (``spring``: ``q`` and an offset). The diagnosis names
the larger where its extra term is a finding beside the smaller (``DiagnosisSearch._nesting``)."""


SEPARATE = {
    frozenset(("coulomb_friction", "stribeck_friction")): "slow constant-velocity moves of joint {j} at several speeds "
    "between 0.01 and 0.5 rad/s: Stribeck friction falls with speed, Coulomb friction does not",
    frozenset(("torque_gain", "rotor_inertia")): "hold joint {j} still at poses with different gravity load, or move it "
    "with and without a known payload: a torque-constant error scales the static torque, rotor inertia adds none at rest",
    frozenset(("time_delay", "viscous_friction")): "excite joint {j} at two frequencies with the same velocity amplitude: "
    "a delay's error grows with frequency, viscous friction depends on velocity alone",
    frozenset(("load_dependent_coulomb", "coulomb_friction")): "move joint {j} at the same speeds under different loads (poses "
    "with different gravity torque on it, or with and without a known payload): load-dependent friction grows with the load, "
    "Coulomb friction does not",
    frozenset(("torque_offset", "spring")): "hold joint {j} still at several positions across its whole range (with the "
    "others fixed): a spring's torque changes with position, an offset does not; over a short range gravity absorbs a spring",
}


DISSIPATIVE_PARAMETER = {"viscous_friction": "fv", "coulomb_friction": "fc", "stribeck_friction": "fs", "rotor_inertia": "ia",
                         "load_dependent_coulomb": "fl", "spring": "stiffness"}
"""The parameter that defines each bounded effect, by its name in a finding: friction is
dissipative, an inertia positive, and the spring a passive one (a gravity-compensation
spring pulls the joint back to its rest position: ``stiffness >= 0``). A candidate whose best
admissible fit holds it at 0 explains nothing the model without it does not."""

DISSIPATIVE = tuple(DISSIPATIVE_PARAMETER)

NONNEGATIVE = ("fv", "fc", "fs", "fl", "ia", "stiffness")
"""Every candidate parameter physics bounds below by 0 (a Stribeck or load-dependent term's
Coulomb level ``fc`` too; the arm-wide friction's ``fc<j>``, ``fv<j>`` on each joint)."""


def lower_bounds(c: Candidate) -> Array:
    """(k,) each of ``c``'s parameters' lower bound: 0 for :data:`NONNEGATIVE`, else ``-inf``."""
    return np.array([0.0 if label.rstrip("0123456789") in NONNEGATIVE else -np.inf for label in c.labels])


def defining(c: Candidate) -> list[int]:
    """The indices of ``c``'s defining parameters: the one :data:`DISSIPATIVE_PARAMETER` names
    on a joint; every ``fc<j>``, ``fv<j>`` of the arm-wide friction (empty: an unbounded effect)."""
    if c.joint is None:
        return [k for k, label in enumerate(c.labels) if label.rstrip("0123456789") in ("fc", "fv")] if c.effect == "coulomb_friction" else []
    name = DISSIPATIVE_PARAMETER.get(c.effect)
    return [c.labels.index(name)] if name in c.labels else []


# the Stribeck velocity on a log grid 0.01-1 rad/s, a factor 1.33 apart (a coarser grid left
# a third of a blind case's Stribeck term in the residual)
STRIBECK_VELOCITIES = tuple(float(v) for v in np.round(np.geomspace(0.01, 1.0, 17), 4))


# ... of which a joint is offered those its motion outruns: at least a fifth of its samples
# faster than 1.73 vs, where exp(-(qd/vs)^2) is under 5 % of fs. A slower "peak" never decays
# in the data: Coulomb and viscous friction bent into another shape, not a low-speed effect
# (clean logs of the second independent generator got Stribeck at 0.75-1 rad/s on joints
# moving at up to 1 rad/s, and every such finding on its lab cases was on a joint without one)
STRIBECK_DECAYED = (80.0, np.sqrt(-np.log(0.05)))


def _cogging_columns(j: int, periods: tuple[float, ...], q: Array, qd: Array, qdd: Array) -> Array:
    """(n, 2 K) ``sin, cos(2 pi q_j / P)`` for each of the K periods, side by side: computed and
    filtered at the full rate as one array (one filter call per data set instead of one per
    period: the calls' own overhead was most of a round). Periods of consecutive whole
    numbers a turn (the catalogue's) step from one harmonic to the next by the angle-addition
    formulas, a few products a sample instead of a sine and a cosine (a diagnosis's cogging
    columns are tens of harmonics over every sample of every file; they agree with ``np.sin``
    to about 1e-14)."""
    per_turn = 2 * np.pi / np.asarray(periods, dtype=float)
    whole = np.rint(per_turn)
    if len(periods) > 1 and np.allclose(per_turn, whole, rtol=1e-12, atol=0.0) and np.all(np.diff(whole) == 1.0):
        angle = q[:, j]
        s1, c1 = np.sin(angle), np.cos(angle)
        s, c = np.sin(whole[0] * angle), np.cos(whole[0] * angle)
        by_column = np.empty((2 * len(periods), q.shape[0]))  # a column a row: contiguous writes
        for i in range(len(periods)):
            by_column[2 * i], by_column[2 * i + 1] = s, c
            s, c = s * c1 + c * s1, c * c1 - s * s1
        return by_column.T
    x = q[:, j][:, None] * per_turn[None, :]
    out = np.empty((q.shape[0], 2 * len(periods)))
    out[:, 0::2], out[:, 1::2] = np.sin(x), np.cos(x)
    return out


Columns = Callable[[StackedData], Array]
"""A candidate kind's columns of the data: a function above (a partial of it) per kind."""


@dataclass(frozen=True)
class Candidate:
    """Columns of one effect. ``block`` gives (n, k) columns living in joint ``joint``'s rows
    only (the cheap, common case); otherwise ``full`` gives (rows, k) for every row."""

    effect: str
    joint: int | None  # 0-based, None for the arm
    setting: tuple[tuple[str, float], ...]
    labels: tuple[str, ...]
    block: Columns | None = None
    full: Columns | None = None

    def columns(self, d: StackedData) -> Array:
        """(rows, k), unweighted."""
        if self.block is not None:
            assert self.joint is not None
            return d.on_joint(self.joint, self.block(d))
        assert self.full is not None
        return self.full(d)


def _coulomb_column(j: int, q: Array, qd: Array, qdd: Array) -> Array:
    """(n, 1) joint j's ``sign(qd)``, computed where the torque was measured, before the
    parallel filter: the filtered torque smooths friction's step at a reversal over the
    filter's span, and so must the column that fits it."""
    return np.sign(qd[:, j : j + 1])


def _stribeck_columns(j: int, vs: float, q: Array, qd: Array, qdd: Array) -> Array:
    """(n, 2) joint j's ``sign(qd)`` and Stribeck peak ``sign(qd) exp(-(qd/vs)^2)``, computed
    where the torque was measured, before the parallel filter: the peak is as narrow as the
    joint's time below ``vs``, which the low-pass smooths in the torque alike (computed on the
    filtered velocity, the peak of blind seed 11 fitted at -10 N*m for a true 18.6)."""
    s = np.sign(qd[:, j])
    return np.column_stack([s, s * np.exp(-((qd[:, j] / vs) ** 2))])


def coulomb(d: StackedData, j: int) -> Array:
    """(n, 1) joint j's Coulomb column as ``d``'s equations see it (:func:`_coulomb_column`)."""
    return d.filtered(functools.partial(_coulomb_column, j))


def _load_friction_columns(robot: Robot, phi: tuple[float, ...], q: Array, qd: Array, qdd: Array) -> Array:
    """(n, N) every joint's ``|tau_load_j| sign(qd_j)``, the load the rigid-body torque of
    ``phi``: computed where the torque was measured, before the parallel filter (the filtered
    torque smooths the step at a reversal; the sign of the filtered velocity does not)."""
    return np.abs(regressor(robot, q, qd, qdd) @ np.asarray(phi)) * np.sign(qd)


class CurrentModel(Protocol):
    """What a candidate's columns read of the model they are scored against, when they are
    computed: its prediction (and the same without friction's steps, for a delay's
    derivative), its standard parameters ``phi`` (a tilt's columns) and a load-dependent
    friction's load (``load``, standard rigid-body parameters)."""

    @property
    def phi(self) -> Array: ...

    @property
    def load(self) -> tuple[float, ...]: ...

    def predict(self, d: StackedData) -> Array: ...

    def predict_smooth(self, d: StackedData) -> Array: ...


def _viscous(j: int, d: StackedData) -> Array:
    return d.qd[:, j : j + 1]


def _coulomb_block(j: int, d: StackedData) -> Array:
    return coulomb(d, j)


def _offset(d: StackedData) -> Array:
    return np.ones((d.q.shape[0], 1))


def _rotor_inertia(j: int, d: StackedData) -> Array:
    return d.qdd[:, j : j + 1]


def _spring(j: int, with_offset: bool, d: StackedData) -> Array:
    """``q`` and an offset (the spring's rest), or ``q`` alone where the offset is in the model."""
    return np.column_stack([d.q[:, j], np.ones(d.q.shape[0])]) if with_offset else d.q[:, j : j + 1]


def _stribeck(j: int, vs: float, with_coulomb: bool, on_motion: bool, d: StackedData) -> Array:
    """A Stribeck peak at ``vs`` (with its Coulomb level where that is not in the model):
    filtered as the torque was, unless the level is the robot file's (the declared model's
    columns are on the filtered motion)."""
    if on_motion:
        return _stribeck_columns(j, vs, d.q, d.qd, d.qdd)[:, 1:]
    return d.filtered(functools.partial(_stribeck_columns, j, vs))[:, 0 if with_coulomb else 1 :]


def _load_friction(robot: Robot, model: CurrentModel, j: int, with_coulomb: bool, d: StackedData) -> Array:
    """``|tau_load_j| sign(qd_j)`` with the load the model's as it is when computed (with its Coulomb level where that is not in the model)."""
    cols = d.filtered(functools.partial(_load_friction_columns, robot, model.load))
    return np.column_stack(([coulomb(d, j)[:, 0]] if with_coulomb else []) + [cols[:, j]])


def _cogging(periods_of_joint: functools.partial[Array], i: int, d: StackedData) -> Array:
    """The ``i``-th period's sine and cosine of the joint's cogging columns (one array a joint)."""
    return d.filtered(periods_of_joint)[:, 2 * i : 2 * i + 2]


def _torque_gain(model: CurrentModel, j: int, d: StackedData) -> Array:
    return model.predict(d)[:, j : j + 1]


def _joint_delay(model: CurrentModel, j: int, d: StackedData) -> Array:
    """Joint j's drive reports its position late: every joint's torque leads it (the
    prediction's derivative along joint j's motion, without friction's steps)."""
    return ((model.predict_smooth(d.shifted(j, 1)) - model.predict_smooth(d.shifted(j, -1))) / (2 * d.period)).reshape(-1, 1)


def _arm_friction(nj: int, joints: tuple[int, ...], d: StackedData) -> Array:
    """Coulomb, viscous friction and an offset on each of ``joints``, each in its own rows."""
    cols = np.zeros((d.q.shape[0] * nj, 3 * len(joints)))
    for k, j in enumerate(joints):
        cols[j::nj, 3 * k : 3 * k + 3] = np.column_stack([coulomb(d, j)[:, 0], d.qd[:, j], np.ones(d.q.shape[0])])
    return cols


def _arm_delay(model: CurrentModel, d: StackedData) -> Array:
    """The whole torque channel lags the positions: minus the rate of the smooth prediction."""
    return -torque_rate(d, model.predict_smooth(d)).reshape(-1, 1)


def _tilt(robot: Robot, model: CurrentModel, d: StackedData) -> Array:
    """The prediction's change when gravity turns about base x and y (linearised)."""
    g = np.asarray(robot.gravity, float)
    cols = []
    for axis in np.eye(3)[:2]:
        tilted = replace(robot, gravity=np.cross(axis, g))
        z = np.zeros_like(d.q)
        cols.append((regressor(tilted, d.q, z, z) @ model.phi).reshape(-1))
    return np.column_stack(cols)


def candidate_catalogue(robot: Robot, data: StackedData, present: set[tuple[str, int | None]], model: CurrentModel,
                        max_cogging_per_turn: int) -> list[Candidate]:
    """Every candidate of the catalogue not ``present`` (declared, found or set aside) on
    ``data``: per joint the linear effects, a Stribeck term per velocity its motion outruns,
    cogging per whole number of periods per turn its motion spans (up to
    ``max_cogging_per_turn``), a drive gain and a late position; for the arm friction on every
    bare joint, a delay of the torque channel and a tilt of gravity. Each kind's columns are
    one function above, of the data (and what it needs); those that read ``model``
    (:class:`CurrentModel`) read it when they are computed."""
    out: list[Candidate] = []
    nj = robot.n_joints
    declared_coulomb = {k for e in robot.effects if e.effect == "coulomb_friction" for k in (range(nj) if e.joint is None else [e.joint - 1])}
    for j in range(nj):

        def lin(name: str, fn: Columns, labels: tuple[str, ...], setting: tuple[tuple[str, float], ...] = (), j: int = j) -> None:
            if (name, j) not in present:
                out.append(Candidate(name, j, setting, labels, block=fn))

        lin("viscous_friction", functools.partial(_viscous, j), ("fv",))
        lin("coulomb_friction", functools.partial(_coulomb_block, j), ("fc",))
        lin("torque_offset", _offset, ("offset",))
        lin("rotor_inertia", functools.partial(_rotor_inertia, j), ("ia",))
        with_offset = ("torque_offset", j) not in present
        lin("spring", functools.partial(_spring, j, with_offset), ("stiffness", "offset") if with_offset else ("stiffness",))
        with_coulomb = ("coulomb_friction", j) not in present
        outrun = float(np.percentile(np.abs(data.qd[:, j]), STRIBECK_DECAYED[0])) / STRIBECK_DECAYED[1]
        on_motion = j in declared_coulomb
        for vs in [v for v in STRIBECK_VELOCITIES if v <= outrun]:
            lin("stribeck_friction", functools.partial(_stribeck, j, vs, with_coulomb, on_motion), (("fc",) if with_coulomb else ()) + ("fs",),
                setting=(("velocity", vs),))
        lin("load_dependent_coulomb", functools.partial(_load_friction, robot, model, j, with_coulomb), (("fc",) if with_coulomb else ()) + ("fl",))
        if robot.joints[j].revolute:
            span = float(np.ptp(data.q[:, j]))
            # at least one whole period over the motion
            periods = tuple(p for p in (2.0 * np.pi / k for k in range(2, max_cogging_per_turn + 1)) if span >= p)
            cog = functools.partial(_cogging_columns, j, periods)
            for i, period in enumerate(periods):
                lin("cogging", functools.partial(_cogging, cog, i), ("a", "b"), setting=(("period_rad", period),))
        if ("torque_gain", j) not in present:
            out.append(Candidate("torque_gain", j, (), ("c",), block=functools.partial(_torque_gain, model, j)))
        if ("time_delay", j) not in present:
            out.append(Candidate("time_delay", j, (), ("delay_s",), full=functools.partial(_joint_delay, model, j)))
    # friction on every joint (what a real arm's residual mostly is) as one arm-wide candidate:
    # judged against the whole arm, not N separate one-joint gains
    bare = tuple(j for j in range(nj) if not {("coulomb_friction", j), ("viscous_friction", j), ("torque_offset", j)} & present)
    if len(bare) >= 2 and ("coulomb_friction", None) not in present:
        labels = tuple(f"{name}{j + 1}" for j in bare for name in ("fc", "fv", "offset"))
        out.append(Candidate("coulomb_friction", None, (), labels, full=functools.partial(_arm_friction, nj, bare)))
    if ("time_delay", None) not in present and not any(e == "time_delay" for e, _ in present):
        # the whole torque channel lags the positions (a current loop, a bus, a filter): one delay
        out.append(Candidate("time_delay", None, (), ("delay_s",), full=functools.partial(_arm_delay, model)))
    if ("gravity_tilt", None) not in present:
        out.append(Candidate("gravity_tilt", None, (), ("tilt_x_rad", "tilt_y_rad"), full=functools.partial(_tilt, robot, model)))
    return out


def candidate_parameters(c: Candidate, gamma: Array) -> dict[str, float]:
    g = [float(x) for x in gamma]
    setting = dict(c.setting)
    if c.effect == "torque_gain":
        return {"gain": 1.0 / (1.0 + g[0])}
    if c.effect == "cogging":
        return {"amplitude": float(np.hypot(g[0], g[1])), "period_rad": setting["period_rad"], "phase_rad": float(np.arctan2(g[1], g[0]))}
    if c.effect == "spring":
        out = {"stiffness": g[0]}
        if len(g) > 1 and g[0] != 0:
            out["rest_position"] = -g[1] / g[0]
        return out
    return {**dict(zip(c.labels, g)), **setting}

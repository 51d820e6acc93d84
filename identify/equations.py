"""Eq. (18) as least squares sees it: the equations of each segment, through its parallel filter.

Each sample gives one equation per joint, ``tau_j = W_j(q, qd, qdd) phi``, with the declared
effects' columns after the 10 N rigid-body ones (:func:`column_count`). Whatever filters the
motion filters the torque: each segment's regressor rows and torque go through the same
zero-phase low-pass and decimation (its ``ParallelFilter``), joint by joint, into one system
``(N, p + 1, n)`` that LAPACK factors without a transpose (:func:`regression_system`). A found drive
gain or torque delay is undone on the measured torque, a late position report on the motion,
before anything is filtered.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any

import numpy as np

from .dynamics import regressor
from .effects import LinearEffect, LoadFriction, effect_columns
from .filtering import ParallelFilter
from .preprocess import Segment
from .robot import Robot
from .spatial import Array


def column_count(robot: Robot, effects: list[LinearEffect]) -> int:
    """Columns of eq. (18) with the effects': 10 per link, then each effect's parameters."""
    return robot.n_parameters + sum(len(e.parameter_names) for e in effects)


def _model_torque(tau: Array, t: Array, scale: Array | None, delay: Array | None) -> Array:
    """The measured torque brought back to the model's: undo each joint's gain, and read each
    joint's torque ``delay`` later (it reports the model's torque of that long ago)."""
    out = np.array(tau, dtype=float, copy=True)
    if delay is not None:
        for j in np.flatnonzero(delay):
            out[:, j] = np.interp(t + delay[j], t, out[:, j])
    if scale is not None:
        out /= scale
    return out


def measured_torque(tau_model: Array, t: Array, scale: Array | None, delay: Array | None) -> Array:
    """The inverse of :func:`_model_torque`: what joint j's sensor shows of the model's torque."""
    out = np.array(tau_model, dtype=float, copy=True)
    if scale is not None:
        out *= scale
    if delay is not None:
        for j in np.flatnonzero(delay):
            out[:, j] = np.interp(t - delay[j], t, out[:, j])
    return out


def advanced(x: Array, t: Array, delay: Array | None) -> Array:
    """Each joint's column read ``delay[j]`` later: the motion a late position report hides."""
    if delay is None or not np.any(delay):
        return x
    out = np.array(x, dtype=float, copy=True)
    for j in np.flatnonzero(delay):
        out[:, j] = np.interp(t + delay[j], t, x[:, j])
    return out


def equations(robot: Robot, effects: list[LinearEffect], seg: Segment, scale: Array | None = None, delay: Array | None = None,
              motion_delay: Array | None = None, rigid: bool = True, kept: slice | None = None, out: Array | None = None) -> Array:
    """(n, N, p+1): the regressor's columns and the torque of one segment, at its samples (at
    the kept ones only when it has no low-pass); :func:`_into_system` puts them through the
    segment's parallel filter (low-pass, edges, decimation): eq. (18) as least squares sees it.
    ``scale``/``delay`` (per joint) undo a found drive gain and sensor delay on the torque.
    ``rigid=False`` leaves the rigid-body columns unset (their equations are reused). Without
    a low-pass, ``kept`` takes a part of the kept samples (each sample's equations are its own)
    and ``out`` is where they go."""
    nj = robot.n_joints
    n_cols = column_count(robot, effects)
    filt = seg.parallel
    tau_all = seg.tau if scale is None and delay is None else _model_torque(seg.tau, seg.t, scale, delay)
    q, qd, qdd = (advanced(x, seg.t, motion_delay) for x in (seg.q, seg.qd, seg.qdd))
    if filt.cutoff_hz is None:  # no low-pass: the kept samples only, straight into place
        idx = filt.kept(seg.n_samples)[kept or slice(None)]
        q, qd, qdd, tau = q[idx], qd[idx], qdd[idx], tau_all[idx]
    else:
        tau = tau_all
    m = np.empty((q.shape[0], nj, n_cols + 1)) if out is None else out[: q.shape[0]]
    if rigid:
        regressor(robot, q, qd, qdd, out=m[:, :, : 10 * nj])
    if effects:
        m[:, :, 10 * nj : n_cols] = effect_columns(effects, q, qd, qdd, rigid=m[:, :, : 10 * nj] if rigid else None)
    m[:, :, n_cols] = tau
    return m


def _through(filt: ParallelFilter, x: Array, keep: bool = True) -> Array:
    """Columns ``x`` (n, k) through the parallel filter (``keep=False``: the low-pass alone,
    every sample); a column of zeros (eq. 18 is block upper triangular: joint j's row has none
    of links i < j, nor other joints' effects) stays zero without being filtered, which is
    half the filtering of a 6-joint arm."""
    if filt.cutoff_hz is None:
        return x
    run = filt.apply if keep else filt.smooth
    live = np.flatnonzero(np.any(x != 0.0, axis=0))
    if live.size == x.shape[1]:
        return run(x)
    out = np.zeros((filt.kept(x.shape[0]).size if keep else x.shape[0], x.shape[1]))
    if live.size:
        out[:, live] = run(x[:, live])
    return out


def _into_system(system: Array, start: int, m: Array, seg: Segment, n_rigid: int, rigid: list[Array] | None = None) -> tuple[int, list[Array]]:
    """Joint by joint, the segment's equations ``m`` (n, N, p+1) through its parallel filter
    into ``system[j, :, start:]`` (no intermediate copy of all joints). The first ``n_rigid``
    columns (the rigid body's) are filtered apart from the others, or taken from ``rigid``
    (each joint's, filtered before).
    Returns the equations written and each joint's filtered rigid-body rows."""
    filt = seg.parallel
    n = 0
    done = []
    for j in range(m.shape[1]):
        rows_rigid = _through(filt, m[:, j, :n_rigid]) if rigid is None else rigid[j]
        rows_rest = _through(filt, m[:, j, n_rigid:])
        done.append(rows_rigid)
        n = rows_rest.shape[0]
        _write_rows(system, j, start, 0, rows_rigid)
        _write_rows(system, j, start, n_rigid, rows_rest)
    return n, done


def _write_rows(system: Array, j: int, start: int, first: int, rows: Array) -> None:
    """Joint j's equations ``rows`` (n, k) into ``system[j, first : first + k, start:]``,
    transposed in blocks of 512 samples that stay in cache."""
    n = rows.shape[0]
    for b in range(0, n, 512):
        system[j, first : first + rows.shape[1], start + b : start + min(b + 512, n)] = rows[b : b + 512].T


@dataclass
class _Reused:
    """What :func:`reused_equations` keeps: each segment's filtered rigid-body rows per joint
    and filtered effect columns, by segment (held here, so that its ``id`` stays its own) and
    by what they depend on (the robot's kinematics, the effect); none with a late position report."""

    rigid: dict[tuple[Any, ...], list[Array]] = field(default_factory=dict)
    columns: dict[tuple[Any, ...], Array] = field(default_factory=dict)
    joint_rest: dict[tuple[Any, ...], Array] = field(default_factory=dict)  # a joint's filtered effect columns and torque
    segments: dict[int, Segment] = field(default_factory=dict)
    bytes: int = 0

    def key(self, seg: Segment, *parts: Any) -> tuple[Any, ...]:
        self.segments[id(seg)] = seg
        return (id(seg), *parts)

    def keep(self, store: dict[tuple[Any, ...], Any], key: tuple[Any, ...], value: Any, size: int) -> None:
        if self.bytes + size <= REUSED_BYTES:
            store[key] = value
            self.bytes += size


REUSED_BYTES = 512 * 2**20
"""At most this much of filtered equations is kept by :func:`reused_equations` (a 6-joint
arm's 40,000 equations take 110 MB); beyond, equations are computed as without it."""

_REUSED: ContextVar[_Reused | None] = ContextVar("armid_reused_equations", default=None)


@contextmanager
def reused_equations() -> Iterator[None]:
    """Within it, every fit on the same segments filters their rigid-body equations and each
    effect's column once: the diagnosis fits the same recordings with a dozen models that
    differ only in their effects, and filtering the regressor again for each took half its
    time. The equations are the same as without it."""
    token = _REUSED.set(_Reused())
    try:
        yield
    finally:
        _REUSED.reset(token)


def _kinematics_key(robot: Robot) -> tuple[Any, ...]:
    """What a segment's rigid-body equations depend on besides the segment: the robot's
    joints and gravity (not its inertial values: a tilted gravity is another key)."""
    key = tuple(np.asarray(x, float).tobytes() for j in robot.joints for x in (j.pre, j.axis, j.post))
    return (*key, bytes(j.revolute for j in robot.joints), np.asarray(robot.gravity, float).tobytes())


EQUATION_BYTES = 256 * 2**20
"""Full-rate equations (regressor and torque, all joints) a segment's parallel filter takes
at once. A longer segment goes through in blocks, each with ``ParallelFilter.settling``
samples more on either side, where the zero-phase filter's response to the block's cut
dies out to rounding: the same equations as the whole segment's, without the whole
segment's regressor (a 5-minute log at 1 kHz, 7 joints: 1.2 GB)."""


def _segment_into_system(system: Array, start: int, robot: Robot, effects: list[LinearEffect], seg: Segment, scale: Array | None,
                         delay: Array | None, motion_delay: Array | None) -> int:
    """A segment's equations through its parallel filter into ``system[j, :, start:]``, in
    blocks of samples when its full-rate equations exceed ``EQUATION_BYTES``. Returns the
    equations written."""
    filt = seg.parallel
    n = seg.n_samples
    n_cols = column_count(robot, effects)
    block = max(1, EQUATION_BYTES // (8 * robot.n_joints * (n_cols + 1)))
    if filt.cutoff_hz is None and _REUSED.get() is None and scale is None and delay is None and motion_delay is None:
        return _unfiltered_into_system(system, start, robot, effects, seg)
    if filt.cutoff_hz is None or n <= block + 2 * filt.settling:
        reused = _REUSED.get() if motion_delay is None else None  # a late report's equations: one delay's try each
        key = None if reused is None else reused.key(seg, _kinematics_key(robot))
        rigid = None if reused is None else reused.rigid.get(key)  # type: ignore[arg-type]
        if reused is not None and rigid is not None:
            return _reused_into_system(system, start, robot, effects, seg, scale, delay, reused, rigid)
        m = equations(robot, effects, seg, scale, delay, motion_delay, rigid=rigid is None)
        written, rows = _into_system(system, start, m, seg, robot.n_parameters, rigid)
        if reused is not None and rigid is None:
            rows = [r if r.base is None else r.copy() for r in rows]  # unfiltered rows are views of all of ``m``: keep only them
            reused.keep(reused.rigid, key, rows, sum(r.nbytes for r in rows))  # type: ignore[arg-type]
        return written
    kept = filt.kept(n)
    written = 0
    for a in range(0, n, block):
        b = min(a + block, n)
        lo, hi = max(0, a - filt.settling), min(n, b + filt.settling)
        part = replace(seg, t=seg.t[lo:hi], q=seg.q[lo:hi], qd=seg.qd[lo:hi], qdd=seg.qdd[lo:hi], tau=seg.tau[lo:hi], stamps=None)
        m = equations(robot, effects, part, scale, delay, motion_delay)
        mine = kept[(kept >= a) & (kept < b)] - lo
        for j in range(robot.n_joints):
            system[j, :, start + written : start + written + mine.size] = _through(filt, m[:, j, :], keep=False)[mine].T
        written += mine.size
    return written


UNFILTERED_BYTES = 16 * 2**20
"""Equations without a low-pass go into the system through one buffer of this size, block by
block of samples (each sample's equations are its own: the same numbers as all at once): a
second copy of a long recording's equations (100,000 samples of a 6-joint arm: 350 MB) cost
more in the memory's first touch than computing them."""


def _unfiltered_into_system(system: Array, start: int, robot: Robot, effects: list[LinearEffect], seg: Segment) -> int:
    """A segment without a low-pass: its kept samples' equations into ``system[j, :, start:]``
    through one reused buffer of ``UNFILTERED_BYTES``. Returns the equations written."""
    n_cols = column_count(robot, effects)
    n = seg.parallel.kept(seg.n_samples).size
    step = max(1, UNFILTERED_BYTES // (8 * robot.n_joints * (n_cols + 1)))
    buffer = np.empty((min(step, n), robot.n_joints, n_cols + 1))
    for a in range(0, n, step):
        m = equations(robot, effects, seg, kept=slice(a, a + step), out=buffer)
        for j in range(robot.n_joints):
            _write_rows(system, j, start + a, 0, m[:, j, :])
    return n


def _reused_into_system(system: Array, start: int, robot: Robot, effects: list[LinearEffect], seg: Segment, scale: Array | None,
                        delay: Array | None, reused: _Reused, rigid: list[Array]) -> int:
    """The segment's equations as :func:`_into_system` writes them, from what earlier fits
    filtered: each joint's rigid-body rows, and its effect columns and torque, kept by the
    effects on that joint and its torque's scale and delay. A diagnosis's fits differ by a
    finding on one joint, so the other joints' columns are neither computed nor filtered
    again. A joint's columns go through the filter together, as in :func:`_through` (the same
    numbers to the bit). Returns the equations written."""
    nj, n_rigid = robot.n_joints, robot.n_parameters
    first = n_rigid + np.cumsum([0] + [len(e.parameter_names) for e in effects])  # each effect's first column
    n_cols = int(first[-1])
    tau: Array | None = None
    n = rigid[0].shape[0]
    for j in range(nj):
        mine = [k for k, e in enumerate(effects) if e.joint == j]
        key = reused.key(seg, "joint", j, tuple(_column_key(effects[k]) for k in mine),
                         None if scale is None else float(scale[j]), None if delay is None else float(delay[j]))
        rows = reused.joint_rest.get(key)
        if rows is None:
            if tau is None:
                tau = seg.tau if scale is None and delay is None else _model_torque(seg.tau, seg.t, scale, delay)
            rows = _joint_rest(robot, [effects[k] for k in mine], seg, tau, j)
            reused.keep(reused.joint_rest, key, rows, rows.nbytes)
        rest = np.zeros((n, n_cols - n_rigid + 1))
        k0 = 0
        for k in mine:
            width = len(effects[k].parameter_names)
            rest[:, first[k] - n_rigid : first[k] - n_rigid + width] = rows[:, k0 : k0 + width]
            k0 += width
        rest[:, -1] = rows[:, -1]
        _write_rows(system, j, start, 0, rigid[j])
        _write_rows(system, j, start, n_rigid, rest)
    return n


def _joint_rest(robot: Robot, mine: list[LinearEffect], seg: Segment, tau: Array, j: int) -> Array:
    """(n, k + 1): joint j's effect columns (``mine``, all on joint j) and its torque, through
    the segment's parallel filter as :func:`equations` and :func:`_through` put them."""
    filt = seg.parallel
    q, qd, qdd = seg.q, seg.qd, seg.qdd
    if filt.cutoff_hz is None:
        idx = filt.kept(seg.n_samples)
        q, qd, qdd, tau = q[idx], qd[idx], qdd[idx], tau[idx]
    cols = effect_columns(mine, q, qd, qdd)[:, j, :] if mine else np.zeros((q.shape[0], 0))
    return _through(filt, np.column_stack([cols, tau[:, j]]))


def _column_key(effect: LinearEffect) -> tuple[Any, ...]:
    """What an effect's columns are a function of (:func:`_effect_key`), a load-dependent
    friction's load included (its parameters and the robot whose torque it is)."""
    if isinstance(effect, LoadFriction):
        return (*_effect_key(effect), effect.setting, effect.load_parameters, effect.follows_coulomb, _kinematics_key(effect.robot))
    return (*_effect_key(effect), effect.setting)


def regression_system(robot: Robot, effects: list[LinearEffect], segments: list[Segment], scale: Array | None = None, delay: Array | None = None,
            motion_delay: Array | None = None) -> Array:
    """The equations of all segments, joint by joint: (N, p+1, n); row ``k`` of ``[j]`` is
    column ``k`` of ``[W_j | tau_j]``, the layout LAPACK factors without a transpose."""
    nj = robot.n_joints
    n_cols = column_count(robot, effects)
    system = np.empty((nj, n_cols + 1, sum(s.n_equations for s in segments)))
    start = 0
    for seg in segments:
        start += _segment_into_system(system, start, robot, effects, seg, scale, delay, motion_delay)
    return system


def equation_motion(segments: list[Segment], name: str) -> Array:
    """A kinematic array at the equations' samples (after the parallel filter)."""
    return np.concatenate([s.parallel.apply(getattr(s, name)) for s in segments])


def equation_column(segments: list[Segment], effect: LinearEffect, motion_delay: Array | None = None,
                     loads: list[Array] | None = None) -> Array:
    """An effect's one column through each segment's parallel filter, concatenated
    (``loads``: each segment's load torque for a load-dependent friction, computed once)."""
    out = []
    reused = _REUSED.get()
    for k, seg in enumerate(segments):
        key = None if reused is None or motion_delay is not None or isinstance(effect, LoadFriction) else reused.key(seg, _effect_key(effect))
        if key is not None and key in reused.columns:  # type: ignore[union-attr]
            out.append(reused.columns[key])  # type: ignore[union-attr]
            continue
        filt = seg.parallel
        q, qd, qdd = (advanced(x, seg.t, motion_delay) for x in (seg.q, seg.qd, seg.qdd))
        # a column is one joint's function of the samples: taken at every sample, then the
        # kept ones (not a copy of the whole motion per try of a setting's search)
        if isinstance(effect, LoadFriction):
            col = effect.columns(q, qd, qdd, load=effect.load(q, qd, qdd) if loads is None else loads[k])[:, 0]
        else:
            col = effect.columns(q, qd, qdd)[:, 0]
        out.append(col[filt.kept(seg.n_samples)] if filt.cutoff_hz is None else filt.apply(col))
        if key is not None:
            reused.keep(reused.columns, key, out[-1], out[-1].nbytes)  # type: ignore[union-attr]
    return np.concatenate(out)


def _effect_key(effect: LinearEffect) -> tuple[Any, ...]:
    """What an effect's column is a function of: its joint and its column function (a
    partial by its function and arguments, as :func:`~identify.effects.linear_effect` makes it anew each time)."""
    fn = effect.column_function
    what = (fn.func, fn.args, tuple(sorted(fn.keywords.items()))) if isinstance(fn, partial) else fn
    return (type(effect), effect.joint, effect.parameter_names, what)


def segment_loads(segments: list[Segment], effect: LoadFriction, motion_delay: Array | None = None) -> list[Array]:
    """Each segment's load torque (n, N) for a load-dependent friction, at its samples."""
    return [effect.load(*(advanced(x, seg.t, motion_delay) for x in (seg.q, seg.qd, seg.qdd))) for seg in segments]

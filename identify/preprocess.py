"""From a raw recording to clean, uniformly sampled segments with velocity and acceleration.

Controllers log imperfectly: time steps jitter, logs have gaps, a few rows are garbage,
velocity may be missing. :func:`prepare` deals with each explicitly and says what it did:

1. rows with a non-finite value, a time that does not increase, a position no joint could
   reach from its neighbours within its velocity limit, or a torque beyond 5x its limit are
   dropped (garbage);
2. the record is split where a time step exceeds ``max_gap_factor`` times the median step;
3. a segment whose steps jitter more than ``jitter_tolerance`` is resampled onto a uniform
   grid at its median step (cubic for positions and velocities, linear for torques);
4. missing velocity comes from positions and acceleration from velocity by Khosla's 5-point
   filter (5.1), optionally after a zero-phase low-pass; the filter's edge samples go.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .differentiation import five_point_derivative, lowpass
from .errors import RecordingError
from .recordings import Recording
from .robot import Robot
from .spatial import Array


@dataclass(frozen=True)
class PrepareOptions:
    max_gap_factor: float = 20.0
    jitter_tolerance: float = 0.05
    lowpass_hz: float | None = None
    min_segment_samples: int = 20
    # the torque (current) of a sample was held over the period before its time stamp, as a
    # drive's current between two SYNCs is: it then belongs half a period earlier than the
    # positions, and is re-timed onto the sample instants by averaging neighbours
    torque_hold: bool = False


@dataclass
class Segment:
    """Uniformly sampled data ready for the regressor; arrays (n, N), ``t`` (n,)."""

    source: str
    t: Array
    q: Array
    qd: Array
    qdd: Array
    tau: Array

    @property
    def n_samples(self) -> int:
        return int(self.t.shape[0])


@dataclass
class Prepared:
    segments: list[Segment]
    notes: list[str] = field(default_factory=list)
    dropped_rows: int = 0

    @property
    def n_samples(self) -> int:
        return sum(s.n_samples for s in self.segments)


def garbage_rows(rec: Recording, robot: Robot) -> tuple[Array, list[str]]:
    """Boolean mask of rows to drop, and a sentence per reason."""
    n = rec.n_samples
    bad = np.zeros(n, dtype=bool)
    notes: list[str] = []
    lines = rec.lines if rec.lines is not None else np.arange(n)
    arrays = [rec.t[:, None], rec.q, rec.tau] + [a for a in (rec.qd, rec.qdd) if a is not None]
    nonfinite = ~np.all(np.concatenate([np.isfinite(a) for a in arrays], axis=1), axis=1)
    _flag(bad, nonfinite, "non-numeric or non-finite value", lines, notes)
    # time must increase: drop a row whose time is not after every earlier kept row's
    t = rec.t
    kept_t = np.where(bad, -np.inf, t)
    earlier_max = np.concatenate([[-np.inf], np.maximum.accumulate(kept_t)[:-1]])
    backwards = (t <= earlier_max) & ~bad
    _flag(bad, backwards, "time not increasing", lines, notes)
    # positions no joint could have reached: compare with the median of 4 neighbours
    keep = np.flatnonzero(~bad)
    if keep.size >= 5:
        q, tk = rec.q[keep], t[keep]
        vmax = np.array([j.limits.velocity if j.limits.velocity else 2.0 * np.pi for j in robot.joints])
        neighbours = np.stack([q[:-4], q[1:-3], q[3:-1], q[4:]])
        med = np.median(neighbours, axis=0)
        span = (tk[4:] - tk[:-4])[:, None]
        jump = np.abs(q[2:-2] - med) > 2.0 * vmax * span + 1e-3
        impossible = np.zeros(n, dtype=bool)
        impossible[keep[2:-2]] = np.any(jump, axis=1)
        _flag(bad, impossible, "position jump beyond the joint's velocity limit", lines, notes)
    tmax = np.array([j.limits.torque if j.limits.torque else np.inf for j in robot.joints])
    over = np.any(np.abs(rec.tau) > 5.0 * tmax, axis=1) & ~bad
    _flag(bad, over, "torque beyond 5x the joint's torque limit", lines, notes)
    return bad, notes


def _flag(bad: Array, mask: Array, reason: str, lines: Array, notes: list[str]) -> None:
    new = mask & ~bad
    if new.any():
        where = lines[new]
        shown = ", ".join(str(int(x)) for x in where[:5]) + (f" and {where.size - 5} more" if where.size > 5 else "")
        notes.append(f"dropped {int(new.sum())} row(s): {reason} (line {shown})")
        bad |= new


def prepare(rec: Recording, robot: Robot, options: PrepareOptions | None = None) -> Prepared:
    """Clean ``rec`` into uniform segments with ``qd`` and ``qdd`` (see module docstring)."""
    options = options or PrepareOptions()
    notes = list(rec.notes)
    bad, garbage_notes = garbage_rows(rec, robot)
    notes += garbage_notes
    keep = ~bad
    if keep.sum() < options.min_segment_samples:
        raise RecordingError(rec.source, f"only {int(keep.sum())} usable rows of {rec.n_samples}")
    t = rec.t[keep]
    q = rec.q[keep]
    tau = rec.tau[keep]
    qd = rec.qd[keep] if rec.qd is not None else None
    qdd = rec.qdd[keep] if rec.qdd is not None else None
    dt = np.diff(t)
    median_dt = float(np.median(dt))
    gaps = np.flatnonzero(dt > options.max_gap_factor * median_dt)
    if gaps.size:
        notes.append(
            f"split at {gaps.size} gap(s) longer than {options.max_gap_factor:g}x the median step "
            f"{median_dt * 1e3:.3g} ms (longest {dt[gaps].max():.3g} s at t={t[gaps[np.argmax(dt[gaps])]]:.6g} s)"
        )
    bounds = np.concatenate([[0], gaps + 1, [t.size]])
    segments = []
    short = 0
    for a, b in zip(bounds[:-1], bounds[1:]):
        if b - a < options.min_segment_samples:
            short += 1
            continue
        seg = _uniform(rec.source, t[a:b], q[a:b], tau[a:b], None if qd is None else qd[a:b], None if qdd is None else qdd[a:b],
                       replace(options, torque_hold=options.torque_hold or rec.torque_held), notes)
        if seg is not None and seg.n_samples >= 1:
            segments.append(seg)
    if short:
        notes.append(f"left out {short} segment(s) shorter than {options.min_segment_samples} samples")
    derived = []
    if qd is None:
        derived.append("velocity from positions")
    if qdd is None:
        derived.append("acceleration from velocity")
    if derived:
        filt = f" after a zero-phase {options.lowpass_hz:g} Hz low-pass" if options.lowpass_hz else ""
        notes.append(f"{' and '.join(derived)} by the 5-point least-squares filter (Khosla 5.1){filt}")
    if not segments:
        raise RecordingError(rec.source, "no segment long enough to use after cleaning: " + "; ".join(notes))
    return Prepared(segments, notes, int(bad.sum()))


def _uniform(source: str, t: Array, q: Array, tau: Array, qd: Array | None, qdd: Array | None, options: PrepareOptions, notes: list[str]) -> Segment | None:
    dt = np.diff(t)
    period = float(np.median(dt))
    jitter = float(np.max(np.abs(dt - period)) / period)
    if jitter > options.jitter_tolerance:
        from scipy.interpolate import CubicSpline

        grid = t[0] + period * np.arange(int(np.floor((t[-1] - t[0]) / period + 1e-9)) + 1)
        notes.append(
            f"resampled {t.size} samples onto a uniform {period * 1e3:.4g} ms grid ({grid.size} samples; "
            f"steps ranged {dt.min() * 1e3:.3g}-{dt.max() * 1e3:.3g} ms)"
        )
        q = CubicSpline(t, q, axis=0)(grid)
        qd = None if qd is None else CubicSpline(t, qd, axis=0)(grid)
        qdd = None if qdd is None else np.column_stack([np.interp(grid, t, c) for c in qdd.T])
        tau = np.column_stack([np.interp(grid, t, c) for c in tau.T])
        t = grid
    if options.torque_hold and tau.shape[0] > 1:
        tau = np.vstack([0.5 * (tau[:-1] + tau[1:]), tau[-1:]])
    if options.lowpass_hz:
        q = lowpass(q, period, options.lowpass_hz)
        tau = lowpass(tau, period, options.lowpass_hz)
        if qd is not None:
            qd = lowpass(qd, period, options.lowpass_hz)
    if qd is None:
        qd = five_point_derivative(q, period)
    if qdd is None:
        qdd = five_point_derivative(qd, period)
    valid = np.all(np.isfinite(qd), axis=1) & np.all(np.isfinite(qdd), axis=1)
    if options.lowpass_hz:
        # a forward-backward filter starts and ends with a transient that differentiation
        # turns into large accelerations: leave out three time constants at both ends
        edge = int(np.ceil(3.0 / (options.lowpass_hz * period)))
        valid[:edge] = False
        valid[max(valid.size - edge, 0) :] = False
    if not valid.any():
        return None
    return Segment(source, t[valid], q[valid], qd[valid], qdd[valid], tau[valid])

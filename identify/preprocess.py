"""From a raw recording to clean, uniformly sampled segments with velocity and acceleration.

Controllers log imperfectly: time steps jitter, logs have gaps, a few rows are garbage,
velocity may be missing. :func:`prepare` deals with each explicitly and says what it did:

1. rows with a non-finite value, a time that does not increase, a position no joint could
   reach from its neighbours within its velocity limit, or a torque beyond 5x its limit are
   dropped (garbage);
2. the record is split where a time step exceeds ``max_gap_factor`` times the median step;
3. a segment whose steps jitter more than ``jitter_tolerance`` is resampled onto a uniform
   grid at its median step (cubic for positions and velocities, linear for torques) for
   filtering and differentiating, while :class:`Stamps` keeps the input's own samples;
4. the low-pass (``lowpass_hz``: "auto" chooses it from the spectrum of ``q``, see
   :mod:`identify.filtering`) smooths the kinematics, missing velocity comes from positions
   (also when the recorded one is much noisier) and acceleration from velocity by Khosla's
   5-point filter (5.1); the torque is left raw, for identification filters the regressor
   and the torque in parallel (:class:`~identify.filtering.ParallelFilter`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .differentiation import five_point_derivative, uniform_derivative
from .errors import RecordingError
from .filtering import SAMPLES_PER_CUTOFF, Band, ParallelFilter, choose_filter, noise_level
from .recordings import Recording
from .robot import Robot
from .spatial import Array


@dataclass(frozen=True)
class PrepareOptions:
    max_gap_factor: float = 20.0
    jitter_tolerance: float = 0.05
    # "auto" (the default, as `armid identify` and `diagnose` have it): chosen from the
    # recording's spectrum (identify.filtering.choose_filter); a number: that cut-off in Hz;
    # None or "off": no low-pass, no decimation (the demo's 2 ms drive data, whose torque
    # noise does not bias least squares and whose velocity comes from the drives). The
    # commands take a named recipe (armid.pipeline: USER_LOG for a user's log, DRIVE_RUN
    # for a drive run), never this default alone
    lowpass_hz: float | str | None = "auto"
    min_segment_samples: int = 20
    # the torque (current) of a sample was held over the period before its time stamp, as a
    # drive's current between two SYNCs is: it then belongs half a period earlier than the
    # positions, and is re-timed onto the sample instants by averaging neighbours
    torque_hold: bool = False


@dataclass
class Stamps:
    """The input's own samples inside a segment: their time stamps (n,), the kinematics the
    model needs evaluated at each of them, and the raw torque measured there."""

    t: Array
    q: Array
    qd: Array
    qdd: Array
    tau: Array
    held: bool = False  # the torque of a sample was held over the period before its stamp

    def as_measured(self, tau_model: Array) -> Array:
        """The model's torque (n, N) as the sensor reports it: a torque held over the period
        before each stamp (a drive's current between SYNCs) is the mean of the model at the
        two ends of that period."""
        if not self.held or tau_model.shape[0] < 2:
            return tau_model
        out = tau_model.copy()
        out[1:] = 0.5 * (tau_model[1:] + tau_model[:-1])
        return out


@dataclass
class Segment:
    """Uniformly sampled data ready for the regressor; arrays (n, N), ``t`` (n,).

    ``q, qd, qdd`` are the (low-passed) kinematics on a uniform grid, ``tau`` the torque on
    it, unfiltered: the equations least squares sees are ``filter.apply`` of the regressor
    columns and of ``tau`` alike (parallel filtering). ``stamps`` holds the same motion at
    the input's own time stamps, for predictions and held-out errors against the raw torque.
    """

    source: str
    t: Array
    q: Array
    qd: Array
    qdd: Array
    tau: Array
    filter: ParallelFilter | None = None
    stamps: Stamps | None = None

    @property
    def n_samples(self) -> int:
        return int(self.t.shape[0])

    @property
    def parallel(self) -> ParallelFilter:
        """The parallel filter (identity, with the differentiators' edges trimmed, when none was chosen)."""
        if self.filter is not None:
            return self.filter
        period = float(np.median(np.diff(self.t))) if self.t.size > 1 else 1.0
        return ParallelFilter(period)

    @property
    def at_stamps(self) -> Stamps:
        """The motion and raw torque at the input's stamps (the grid itself when it was not resampled)."""
        return self.stamps if self.stamps is not None else Stamps(self.t, self.q, self.qd, self.qdd, self.tau)

    @property
    def n_equations(self) -> int:
        return int(self.parallel.kept(self.n_samples).size)


@dataclass
class Prepared:
    segments: list[Segment]
    notes: list[str] = field(default_factory=list)
    dropped_rows: int = 0
    rows: int = 0  # rows in the recording
    band: Band | None = None
    torque_from_current: bool | None = None  # the recording's (Recording.torque_from_current)

    @property
    def n_samples(self) -> int:
        return sum(s.n_samples for s in self.segments)

    @property
    def n_stamps(self) -> int:
        """Input samples the segments cover (predicted, and scored on held-out data)."""
        return sum(s.at_stamps.t.size for s in self.segments)

    def filtering(self) -> dict[str, Any]:
        """What was chosen and why, for the JSON outputs."""
        b = self.band
        seg = self.segments[0] if self.segments else None
        out: dict[str, Any] = {"cutoff_hz": None, "decimation": 1}
        if seg is not None and seg.filter is not None:
            out = {"cutoff_hz": seg.filter.cutoff_hz, "decimation": seg.filter.decimation}
        if b is not None:
            out.update({"excitation_band_hz": b.band_hz, "sample_rate_hz": 1.0 / b.period_s, "why": b.reason})
        return out


def unwrap_continuous(rec: Recording, robot: Robot) -> Recording:
    """Undo the 2 pi wraps a logger puts in a continuous joint's angle (a revolute joint with no
    position limits, or limits more than a turn apart, logged in (-pi, pi]): a step over pi
    between samples is a wrap, not motion, and left in it would be dropped as a jump and split
    the record. The rigid body is periodic in the angle, so unwrapping changes no torque; a
    recording without wraps is returned as is."""
    free = [k for k, j in enumerate(robot.joints)
            if j.revolute and (j.limits.position is None or j.limits.position[1] - j.limits.position[0] > 2 * np.pi)]
    if not free or rec.n_samples < 2:
        return rec
    q = rec.q.copy()
    wrapped = []
    for k in free:
        ok = np.flatnonzero(np.isfinite(q[:, k]))
        if ok.size < 2 or not np.any(np.abs(np.diff(q[ok, k])) > np.pi):
            continue
        q[ok, k] = np.unwrap(q[ok, k])
        wrapped.append(robot.joints[k].name)
    if not wrapped:
        return rec
    note = f"unwrapped the 2 pi wraps of joint(s) {', '.join(wrapped)}"
    return replace(rec, q=q, notes=[*rec.notes, note])


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
    beyond = np.abs(rec.tau) > 5.0 * tmax
    over = np.any(beyond, axis=1) & ~bad
    reason = "torque beyond 5x the joint's torque limit"
    if over.sum() > 0.5 * max(int((~bad).sum()), 1):  # not spikes: the torque's unit or scale
        worst = int(np.argmax(beyond[~bad].mean(axis=0)))
        reason += (f" (joint {worst + 1}'s median |torque| {float(np.median(np.abs(rec.tau[~bad, worst]))):.4g} against its limit "
                   f"{tmax[worst]:g}: is the torque in N*m, or the current scaled by the right torque_constant?)")
    _flag(bad, over, reason, lines, notes)
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
    rec = unwrap_continuous(rec, robot)
    notes = list(rec.notes)
    bad, garbage_notes = garbage_rows(rec, robot)
    notes += garbage_notes
    keep = ~bad
    if keep.sum() < options.min_segment_samples:
        why = "; ".join(garbage_notes) if garbage_notes else "too few rows"
        raise RecordingError(rec.source, f"only {int(keep.sum())} usable rows of {rec.n_samples}: {why}")
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
    pieces = [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b - a >= options.min_segment_samples]
    short = len(bounds) - 1 - len(pieces)
    if not pieces:
        raise RecordingError(rec.source, "no segment long enough to use after cleaning: " + "; ".join(notes))
    band = _choose_band(rec.source, t, q, qd, pieces, median_dt, options.lowpass_hz)
    if band is not None:
        notes.append(f"filtering: {band.reason}")
    held = options.torque_hold or rec.torque_held
    segments = []
    for a, b in pieces:
        seg = _uniform(rec.source, t[a:b], q[a:b], tau[a:b], None if qd is None else qd[a:b], None if qdd is None else qdd[a:b],
                       band, replace(options, torque_hold=held), notes)
        segments.append(seg)
    left_out = int(bad.sum()) + sum(b - a for a, b in zip(bounds[:-1], bounds[1:]) if b - a < options.min_segment_samples)
    if short:
        notes.append(f"left out {short} segment(s) shorter than {options.min_segment_samples} samples")
    derived = []
    if qd is None:
        derived.append("velocity from positions")
    if qdd is None:
        derived.append("acceleration from velocity")
    if derived:
        notes.append(f"{' and '.join(derived)} by the 5-point least-squares filter (Khosla 5.1), sharpened")
    prepared = Prepared(segments, notes, int(bad.sum()), rec.n_samples, band, rec.torque_from_current)
    if left_out:
        notes.append(f"{left_out} of {rec.n_samples} input samples are not predicted (garbage rows, segments too short)")
    return prepared


CLEAN_KINEMATICS = 1e-3
"""Below this ratio of acceleration noise (what a low-pass would remove) to acceleration,
the kinematics need no low-pass (simulated or already filtered data)."""


GAP_STEPS = 2.5
"""A step of more than this many periods is a gap (samples missing), not a logger's jitter."""


def _acceleration_noise(t: Array, q: Array, qd: Array | None, grid: Array, filt: ParallelFilter) -> float:
    """Largest ratio over the moving joints of the acceleration's content above the cut-off
    to its content below, the acceleration by the 5-point filter applied twice. The grid's
    samples within the filter's settling of a gap are left out where enough remain: the
    straight line interpolated across a gap has a kink at each end, which is not noise (ten
    NaN rows in a clean 5,000-sample recording read as noise 1e-1 and chose a low-pass)."""
    period = filt.period_s
    v = np.column_stack([np.interp(grid, t, c) for c in (q if qd is None else qd).T])
    if qd is None:
        v = five_point_derivative(v, period)
    a = five_point_derivative(v, period)[6:-6]
    if a.shape[0] < 32:
        return np.inf
    smooth = filt.smooth(a)
    keep = _away_from_gaps(t, grid[6:-6], filt.settling * period, period)
    if keep.sum() >= 32:
        a, smooth = a[keep], smooth[keep]
    signal = np.std(smooth, axis=0)
    moving = signal > 1e-9 * max(float(signal.max()), 1e-300)
    return float(np.max(np.std(a - smooth, axis=0)[moving] / signal[moving])) if moving.any() else np.inf


def _away_from_gaps(t: Array, grid: Array, margin_s: float, period: float) -> Array:
    """Grid samples farther than ``margin_s`` from every gap of ``t`` (a step over GAP_STEPS periods)."""
    keep = np.ones(grid.size, bool)
    for k in np.flatnonzero(np.diff(t) > GAP_STEPS * period):
        keep &= (grid < t[k] - margin_s) | (grid > t[k + 1] + margin_s)
    return keep


def _choose_band(source: str, t: Array, q: Array, qd: Array | None, pieces: list[tuple[int, int]], period: float,
                 lowpass_hz: float | str | None) -> Band | None:
    """The recording's parallel filter: from the spectrum of its longest piece (``"auto"``),
    at a given cut-off, or none."""
    if lowpass_hz is None or lowpass_hz == "off":
        return None
    a, b = max(pieces, key=lambda p: p[1] - p[0])
    t = t - t[a]  # relative: epoch stamps lose digits
    grid = period * np.arange(int(np.floor(t[b - 1] / period + 1e-9)) + 1)
    q_grid = np.column_stack([np.interp(grid, t[a:b], c) for c in q[a:b].T])
    if lowpass_hz == "auto":
        band = choose_filter(q_grid, period)
        if band.cutoff_hz is not None:
            noise = _acceleration_noise(t[a:b], q[a:b], None if qd is None else qd[a:b], grid, ParallelFilter(period, band.cutoff_hz))
            if noise < CLEAN_KINEMATICS:
                return Band(band.band_hz, None, 1, period,
                            f"excitation up to {band.band_hz:.3g} Hz, but the kinematics are clean (acceleration noise "
                            f"{noise:.2g} of its signal above a {band.cutoff_hz:.3g} Hz cut-off): no low-pass")
        return band
    if isinstance(lowpass_hz, str):
        raise RecordingError(source, f"low-pass '{lowpass_hz}': give a cut-off in Hz, 'auto' or 'off'")
    nyquist = 0.5 / period
    cutoff = float(lowpass_hz)
    if not 0.0 < cutoff < nyquist:
        raise RecordingError(source, f"low-pass cut-off {cutoff:g} Hz must lie in (0, {nyquist:g}) Hz, the Nyquist frequency of this recording")
    auto = choose_filter(q_grid, period)
    decimation = max(1, int(np.floor(1.0 / (period * SAMPLES_PER_CUTOFF * cutoff))))
    return Band(auto.band_hz, cutoff, decimation, period,
                f"zero-phase {cutoff:g} Hz low-pass as asked (the excitation reaches {auto.band_hz:.3g} Hz) on the kinematics, "
                f"the regressor and the torque alike; decimated {decimation}:1")


NOISE_FLOOR = 1e-9
"""A noise level (relative to the signal) below this is no noise: a ratio over it says nothing
(over a denormal one it said "3.85e+298x noisier"), and a recorded velocity that clean is kept."""


def _uniform(source: str, t: Array, q: Array, tau: Array, qd: Array | None, qdd: Array | None, band: Band | None,
             options: PrepareOptions, notes: list[str]) -> Segment:
    raw_t, raw_tau = t, tau
    t0 = float(t[0])
    t = t - t0  # epoch stamps (1.5e9 s) would cost the splines their last digits
    dt = np.diff(t)
    period = float(np.median(dt))
    jitter = float(np.max(np.abs(dt - period)) / period)
    resampled = jitter > options.jitter_tolerance
    if resampled:
        from scipy.interpolate import CubicSpline  # here: its import costs more than a clean recording's preparation

        grid = t[0] + period * np.arange(int(np.floor((t[-1] - t[0]) / period + 1e-9)) + 1)
        notes.append(
            f"resampled {t.size} samples onto a uniform {period * 1e3:.4g} ms grid ({grid.size} samples; "
            f"steps ranged {dt.min() * 1e3:.3g}-{dt.max() * 1e3:.3g} ms) for filtering and differentiating; "
            f"predictions are evaluated at the input's own stamps"
        )
        q = CubicSpline(t, q, axis=0)(grid)
        qd = None if qd is None else CubicSpline(t, qd, axis=0)(grid)
        qdd = None if qdd is None else np.column_stack([np.interp(grid, t, c) for c in qdd.T])
        tau = np.column_stack([np.interp(grid, t, c) for c in tau.T])
        t = grid
    if options.torque_hold and tau.shape[0] > 1:
        tau = np.vstack([0.5 * (tau[:-1] + tau[1:]), tau[-1:]])
    filt = ParallelFilter(period, None if band is None else band.cutoff_hz, 1 if band is None else band.decimation)
    if qd is not None and filt.cutoff_hz is not None:
        # a recorded velocity is used unless differentiating the positions is less noisy
        # (fine encoders beat a noisy velocity estimate): compare what the low-pass removes
        from_q = uniform_derivative(q, period)
        noise_qd = float(np.median(noise_level(qd, filt) / np.maximum(np.std(qd, axis=0), 1e-12)))
        noise_q = float(np.median(noise_level(from_q, filt) / np.maximum(np.std(qd, axis=0), 1e-12)))
        if noise_q < 0.5 * noise_qd and noise_qd > NOISE_FLOOR:
            qd = None
            if not any(n.startswith("velocity from positions") for n in notes):
                how = (f"{noise_qd / noise_q:.3g}x noisier above the cut-off" if noise_q > NOISE_FLOOR else
                       f"noisier above the cut-off, where the positions' derivative carries no noise (below {NOISE_FLOOR:g} of the signal)")
                notes.append(f"velocity from positions: the recorded velocity is {how}")
    q = filt.smooth(q)
    from_positions = qd is None
    qd = uniform_derivative(q, period) if qd is None else filt.smooth(qd)
    qdd = uniform_derivative(qd, period, 2 if from_positions else 1, q if from_positions else None) if qdd is None else filt.smooth(qdd)
    stamps = None
    if resampled:
        from scipy.interpolate import CubicSpline

        rel = raw_t - t0
        inside = (rel >= t[0]) & (rel <= t[-1] + period)
        ts = rel[inside]
        stamps = Stamps(raw_t[inside], CubicSpline(t, q, axis=0)(ts), CubicSpline(t, qd, axis=0)(ts), CubicSpline(t, qdd, axis=0)(ts), raw_tau[inside],
                        options.torque_hold)
    elif options.torque_hold or t0 != 0.0:
        stamps = Stamps(raw_t, q, qd, qdd, raw_tau, options.torque_hold)
    return Segment(source, t + t0, q, qd, qdd, tau, filt, stamps)

"""Plausibility of a recording before it is identified: garbage that parses.

A log in the wrong units or from a dead sensor reads without a single bad row, and least
squares then returns numbers: inertias 1,000 times off when the time stamps are in
milliseconds, ``NaN`` when every torque is zero. These checks look at the raw arrays
(before any cleaning) and either raise :class:`RecordingError` naming the file and what is
implausible, or return warnings for what may still be right.

- Time units: with velocity columns, ``dq/dt`` must agree with ``qd``. Time stamps in
  milliseconds make ``dq/dt`` 1,000 times smaller than ``qd`` (microseconds 10^6,
  nanoseconds 10^9): an error that names the unit. Any other disagreement is a warning.
- Time: a log whose time never advances, or runs backwards throughout, is refused.
- Angles: ``dq/dt`` 57.3 times ``qd`` (or 1/57.3) means one of them is in degrees: an error.
- Torque: every torque zero, or constant on every joint, is refused (a dead sensor or a
  current column not wired), and so is a constant torque on a joint that moves; a joint
  that stays still with a constant torque is a warning.
- Motion: no joint moving at all is refused: the data cannot say anything about dynamics.

The functions are pure: arrays in, warnings or an error out.
"""

from __future__ import annotations

import numpy as np

from .errors import RecordingError
from .preprocess import GAP_STEPS
from .spatial import Array

UNITS = ((1e-3, "milliseconds"), (1e-6, "microseconds"), (1e-9, "nanoseconds"))
"""Time stamps in these units make dq/dt this many times the drive's velocity."""

AGREE = (0.5, 2.0)
"""dq/dt over qd within this band is agreement (noise and quantisation widen it)."""

ANGLES = ((180.0 / np.pi, "positions q look like degrees while the velocities qd are in rad/s"),
          (np.pi / 180.0, "velocities qd look like degrees/s while the positions q are in rad"))
"""dq/dt over qd at these ratios: one of the columns is in degrees (revolute joints)."""

ANGLE_BAND = 1.1
"""A ratio within this factor of 180/pi (pi/180) is that mistake."""

UNIT_BAND = 3.0
"""A ratio within this factor of 10^-3 (10^-6, 10^-9) is that unit."""

MIN_MOTION = 1e-9
"""Position range (rad or m) at or below which a joint's positions are constant (a column
not wired, a drive off): not a joint held still, which :data:`MOVING_RAD` tells."""
MOVING_RAD = 0.05
"""A joint whose positions span more than this (rad or m) over a recording moved
(:func:`moving_joints`): one held still by its servo wanders by less (its dq/dt is then the
encoder's quantisation and the servo's holding torque, not motion), an excited one by far more."""


def check_recording(t: Array, q: Array, qd: Array | None, tau: Array, source: str, need_motion: bool = True) -> list[str]:
    """Warnings about a recording, or :class:`RecordingError` when it is garbage.

    ``t`` (n,), ``q`` (n, N), ``qd`` (n, N) or None, ``tau`` (n, N), as read (NaN allowed:
    cleaning drops those rows later); ``source`` names the file in every message.
    ``need_motion``: a recording in which nothing moves is refused (identification); the
    payload estimator answers "not excited" to it itself.
    """
    t = np.asarray(t, float)
    q = np.asarray(q, float)
    tau = np.asarray(tau, float)
    warnings: list[str] = []
    check_time(t, source)
    if need_motion:
        check_motion(q, source)
    warnings += check_torque(tau, source, q)
    if qd is not None:
        warnings += check_time_units(t, q, np.asarray(qd, float), source)
    return warnings


def check_time(t: Array, source: str) -> None:
    """Time must advance: refuse a log whose stamps never change or mostly run backwards."""
    ok = np.isfinite(t)
    if ok.sum() < 2:
        return  # too short: the reader or the cleaning says so
    dt = np.diff(t[ok])
    if not (dt != 0).any():
        raise RecordingError(source, f"column t: time never advances (every stamp is {t[ok][0]:g})")
    backwards = dt < 0
    if backwards.mean() > 0.5:
        raise RecordingError(source, f"column t: time runs backwards on {int(backwards.sum())} of {dt.size} steps "
                                     "(a log written in reverse?)")


def check_motion(q: Array, source: str) -> None:
    """Refuse a recording in which no joint moves: no dynamics parameter shows in it."""
    q = np.asarray(q, float)
    if q.ndim != 2 or (np.isfinite(q).sum(axis=0) < 2).any():
        return  # columns without two readable values: the reader or the cleaning says so
    span = joint_spans(q)
    if span.size and np.all(span <= MIN_MOTION):
        raise RecordingError(source, "columns q: no joint moves (every position is constant): the data cannot say anything "
                                     "about the dynamics (not excited)")


def check_torque(tau: Array, source: str, q: Array | None = None) -> list[str]:
    """Refuse all-zero or everywhere-constant torque, and a constant torque on a joint that
    moves (``q`` given): no moving joint's drive holds one value to the last bit. Warn
    about a constant torque on a joint that stays still."""
    tau = np.asarray(tau, float)
    finite = tau[np.isfinite(tau).all(axis=1)] if tau.ndim == 2 else tau
    if finite.shape[0] < 2:
        return []
    n = finite.shape[1]
    if not np.any(finite):
        raise RecordingError(source, f"columns tau1..tau{n}: every torque is zero (a sensor or a current column "
                                     "not wired?): nothing to identify from")
    span = joint_spans(finite)
    if np.all(span == 0):
        raise RecordingError(source, f"columns tau1..tau{n}: the torque is constant on every joint "
                                     f"({', '.join(f'{v:g}' for v in finite[0])}): nothing to identify from")
    moves = joint_spans(q) > MIN_MOTION if q is not None and np.shape(q) == tau.shape else np.zeros(n, bool)
    for j in range(n):
        if span[j] == 0 and moves[j]:
            raise RecordingError(source, f"column tau{j + 1}: the torque is constant ({finite[0, j]:g}) while joint {j + 1} "
                                         "moves: a dead sensor or a current column not wired?")
    return [f"{source}: column tau{j + 1}: the torque is constant ({finite[0, j]:g}) over the whole recording"
            for j in range(n) if span[j] == 0]


def velocity_ratio(t: Array, q: Array, qd: Array) -> float | None:
    """The median over moving joints of the least-squares slope of the position increments
    on ``qd dt`` (1 when the units agree), or None when no joint moves enough to tell.

    A slope, not a ratio of rms values: the quantisation of q is uncorrelated with qd and
    averages out, where its rms would dominate a slow joint's dq/dt at a high sample rate.
    Steps across a gap (records missing) are left out: the trapezoid of the velocities at a
    gap's two ends is not the travel between them."""
    ok = np.isfinite(t) & np.isfinite(q).all(axis=1) & np.isfinite(qd).all(axis=1)
    t, q, qd = t[ok], q[ok], qd[ok]
    if t.size < 3:
        return None
    dt = np.diff(t)
    step = dt > 0
    if step.sum() >= 2:
        step &= dt <= GAP_STEPS * float(np.median(dt[step]))
    if step.sum() < 2:
        return None
    dq = np.diff(q, axis=0)[step]
    travel = (0.5 * (qd[1:] + qd[:-1]) * np.where(step, dt, 0.0)[:, None])[step]
    ratios = []
    for j in range(q.shape[1]):
        power = float(travel[:, j] @ travel[:, j])
        if power > 0 and moving_joints(q[:, j : j + 1])[0]:
            ratios.append(float(dq[:, j] @ travel[:, j]) / power)
    return float(np.median(ratios)) if ratios else None


def check_time_units(t: Array, q: Array, qd: Array, source: str) -> list[str]:
    """Compare the sample period against the velocity columns: dq/dt must agree with qd."""
    ratio = velocity_ratio(t, q, qd)
    if ratio is None or AGREE[0] <= ratio <= AGREE[1]:
        return []
    for factor, unit in UNITS:
        if factor / UNIT_BAND <= ratio <= factor * UNIT_BAND:
            raise RecordingError(source, f"column t: the time stamps look like {unit}, not seconds: dq/dt is {ratio:.3g} "
                                         f"times the velocity columns qd (convert t to seconds)")
    for factor, mistake in ANGLES:
        if factor / ANGLE_BAND <= ratio <= factor * ANGLE_BAND:
            raise RecordingError(source, f"columns q, qd: the {mistake} (dq/dt is {ratio:.3g} times qd)")
    return [f"{source}: columns qd: dq/dt is {ratio:.3g} times the velocity columns: are t in seconds and qd in "
            "rad/s (m/s)?"]


BEYOND = 0.5
"""A joint outside its position limits (widened by a tenth of their span) on more than this
fraction of the samples is not where the robot file says it can be."""


def check_positions(q: Array, limits: list[tuple[float, float] | None], revolute: list[bool], source: str) -> list[str]:
    """Positions against the robot file's position limits. Positions that leave them on most
    samples, reach five times them, and would fit them all in radians are in degrees: an error
    (without velocity columns the dq/dt test cannot see it, and a fit on degrees is silently
    wrong). Positions beyond them otherwise (a controller's other zero, the wrong robot file)
    are a warning."""
    q = np.asarray(q, float)
    ok = np.isfinite(q).all(axis=1)
    q = q[ok]
    if q.shape[0] == 0:
        return []

    def outside(x: Array, j: int) -> float:
        lo, hi = limits[j]  # type: ignore[misc]
        margin = 0.1 * (hi - lo)
        return float(np.mean((x < lo - margin) | (x > hi + margin)))

    bounded = [j for j in range(q.shape[1]) if limits[j] is not None]
    beyond = {j: outside(q[:, j], j) for j in bounded}
    far = [j for j in bounded if beyond[j] > BEYOND]
    if not far:
        return []
    # degrees: far beyond (5x the larger limit, more than another zero could put them) and
    # every joint within its limits as radians
    if (all(revolute[j] and np.abs(q[:, j]).max() > 5 * max(abs(limits[j][0]), abs(limits[j][1])) for j in far)  # type: ignore[index]
            and all(outside(np.radians(q[:, j]), j) == 0.0 for j in bounded if revolute[j])):
        j = far[0]
        raise RecordingError(source, f"column q{j + 1}: the positions look like degrees: joint {j + 1} reaches "
                                     f"{np.abs(q[:, j]).max():.4g} against its limits {limits[j][0]:g}..{limits[j][1]:g} rad, "  # type: ignore[index]
                                     "and every joint's positions fit their limits as radians (convert q to rad)")
    return [f"{source}: column q{j + 1}: joint {j + 1} is beyond its limits {limits[j][0]:g}..{limits[j][1]:g} "  # type: ignore[index]
            f"on {100 * beyond[j]:.0f} % of the samples: the controller's zero, the units or the robot file?" for j in far]


SIGN_CORRELATION = -0.9
"""A joint whose torque correlates below this with the modeled rigid body's runs opposite to it
(the KUKA LWR4+'s light wrist joints 5 and 7 correlate -0.7 with their CAD model: a poor model
of a torque that friction and cables dominate, not a flipped sign)."""

SCALE_BAND = (0.2, 5.0)
"""Measured over modeled torque outside this band (with correlation above SCALE_CORRELATION)
is a unit, a gear ratio or a torque constant, not a CAD value off by tens of percent."""

SCALE_CORRELATION = 0.9

MODELED_MIN_SHARE = 0.05
"""A joint's modeled torque must vary by this share of the largest joint's for the sign and
scale checks: a held wrist's modeled torque is near zero, and what its sensor measures beside
it (friction, a CAD mass off by half) is no unit; a light wrist whose modeled torque is 0.2 %
of the base's (a blind case's joint 5: 0.02 N*m) correlated -0.99 with it through a CAD first
moment of the other sign, which is no sensor's sign."""

POOLED_SIGN_CORRELATION = -0.4
"""The torques of all joints together against the modeled ones: below this, every sign is
flipped (a convention of the logger or of the torque constants). Pooled, the large joints
carry it: the KUKA's recordings pool at 0.99; the PUMA example, whose model lacks the large
rotor inertias (joint 1 correlates 0.19), pools at 0.48, and at -0.48 with every torque negated."""


def check_against_model(tau: Array, modeled: Array, source: str, moving: Array | None = None) -> list[str]:
    """Warnings for joints whose measured torque runs opposite to the robot file's modeled
    rigid-body torque at the same samples, or is many times it: a sensor's sign convention,
    mN*m, a missing torque constant or gear ratio. Friction and offsets are not modeled, so
    only the varying part is compared, and only where the modeled torque varies at all.
    With ``moving`` (per joint), only the joints that move: a held joint's varying torque is
    its servo holding it against the others' pull, through the rotor inertia and friction the
    rigid body lacks (the simulated PUMA's joint 3, held while joint 4 moves, measured 12 times
    its modeled torque at correlation 0.90: a reflected rotor inertia 12 times the link's)."""
    ok = np.isfinite(tau).all(axis=1) & np.isfinite(modeled).all(axis=1)
    tau, modeled = tau[ok] - tau[ok].mean(axis=0), modeled[ok] - modeled[ok].mean(axis=0)
    if tau.shape[0] < 10:
        return []
    spread_m, spread_t = np.sqrt(np.mean(modeled**2, axis=0)), np.sqrt(np.mean(tau**2, axis=0))
    out = []
    pooled = float(np.sum(tau * modeled) / max(np.sqrt(np.sum(tau**2) * np.sum(modeled**2)), 1e-300))
    if pooled < POOLED_SIGN_CORRELATION:
        out.append(f"{source}: the torques of all joints together run opposite to the robot file's modeled torque "
                   f"(correlation {pooled:.2f}): is every torque's sign (the logger's convention, the torque constants) the model's?")
    for j in range(tau.shape[1]):
        if spread_m[j] < MODELED_MIN_SHARE * spread_m.max() or spread_t[j] == 0 or (moving is not None and not moving[j]):
            continue
        r = float(np.mean(tau[:, j] * modeled[:, j]) / (spread_m[j] * spread_t[j]))
        scale = float(np.mean(tau[:, j] * modeled[:, j]) / spread_m[j] ** 2)
        if r < SIGN_CORRELATION:
            out.append(f"{source}: column tau{j + 1}: joint {j + 1}'s torque runs opposite to the robot file's modeled torque "
                       f"(correlation {r:.2f}): is the sensor's or the torque constant's sign the model's?")
        elif r > SCALE_CORRELATION and not SCALE_BAND[0] <= scale <= SCALE_BAND[1]:
            out.append(f"{source}: column tau{j + 1}: joint {j + 1} measures {scale:.3g} times the robot file's modeled torque "
                       f"(correlation {r:.2f}): is it in N*m (not mN*m), and its torque_constant (gear ratio included) right?")
    return out


def joint_spans(q: Array) -> Array:
    """Each joint's (column's) range of position over its finite samples (a few NaN fields
    must not make a moving joint look still); 0 for a joint without one."""
    q = np.asarray(q, float)
    if q.ndim == 1:
        q = q[:, None]
    finite = np.isfinite(q)
    hi, lo = np.where(finite, q, -np.inf).max(axis=0), np.where(finite, q, np.inf).min(axis=0)
    return np.where(finite.any(axis=0), hi - lo, 0.0)


def moving_joints(q: Array) -> Array:
    """Per joint, whether it moved over the recording ``q`` (n, N): a span over
    :data:`MOVING_RAD` (:func:`joint_spans`). The one test of which joints moved."""
    return joint_spans(q) > MOVING_RAD

"""A recording as arrays (:class:`Recording`): what the preprocessing takes, and the one function
that makes it of a drive's records (:func:`recording_of`).

Reading files (CSV, NPZ, MCAP) into a :class:`Recording` is the I/O layer's job
(:mod:`armid.io.recordings`); this package never opens a file.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from armid.schema.errors import RecordingError
from armid.schema.joint_states import JointStates

from .spatial import Array

if TYPE_CHECKING:
    from .robot import Robot


@dataclass
class Recording:
    """Raw samples as read: time (n,), joint arrays (n, N); ``qd``/``qdd`` may be absent.

    ``lines`` gives each sample's line in the source file (for messages); ``notes`` says
    what reading did (units converted, columns missing).
    """

    source: str
    t: Array
    q: Array
    tau: Array
    qd: Array | None = None
    qdd: Array | None = None
    lines: Array | None = None
    notes: list[str] = field(default_factory=list)
    torque_held: bool = False  # torque held over the period before each stamp (drive currents)
    cycle: Array | None = None  # each sample's cycle counter (a drive recording), else None
    period_s: float | None = None  # the cycle's nominal period, where the recording says it (its metadata), else None
    # where the torque comes from: True, a measured current times a torque constant (a drive's
    # gain is in question); False, joint torque given directly (a torque sensor: no drive gain
    # between it and the model); None, not said (arrays made in memory, a simulated drive's)
    torque_from_current: bool | None = None
    # the line that stopped the run the recording holds (a drive fault, lost frames, a safety
    # stop: what its metadata says), None for a run that completed or a file that does not say
    stopped: str | None = None

    @property
    def n_samples(self) -> int:
        return int(self.t.shape[0])


def with_torque(states: JointStates, robot: Robot) -> tuple[JointStates, str]:
    """``states`` with their joint torque, and how it was had: as the driver recorded it, or,
    where the source carried currents only (its torque NaN throughout), the measured current
    times each joint's ``torque_constant`` of ``robot``: the one place a recording of currents
    gets its torque."""
    if len(states) and np.isnan(states.torque).all():
        kt = np.array([j.torque_constant for j in robot.joints])
        return replace(states, torque=states.measured_current * kt), "torque = measured current x torque_constant"
    return states, "torque as recorded (the driver's measured current x torque constant)"


def recording_of(states: JointStates, robot: Robot, source: str, notes: list[str] | None = None, period_s: float | None = None,
                 stopped: str | None = None) -> Recording:
    """A drive recording's records as identification takes them: in sequence order, those stamped
    no later than an earlier one and the unusable ones (:meth:`JointStates.unusable`) left out (said in
    the notes), the drives' velocity (:func:`drive_velocity`), the torque by :func:`with_torque`.
    ``notes`` (what reading said so far, extended here), ``period_s`` and ``stopped`` are the
    recording's (its metadata's)."""
    notes = [] if notes is None else notes
    if states.n_joints != robot.n_joints:
        raise RecordingError(source, f"{states.n_joints} joints recorded, robot {robot.name} has {robot.n_joints}")
    order = np.argsort(states.sequence, kind="stable")
    if np.any(order != np.arange(order.size)):
        states = states[order]
        notes.append("records stored out of sequence order: put back in order by their sequence numbers")
    states, how = with_torque(states, robot)
    unusable = states.unusable()
    bad = np.logical_or.reduce(list(unusable.values()))
    if bad.any():
        why = ", ".join(f"{int(m.sum())} {reason}" for reason, m in unusable.items() if m.any())
        notes.append(f"left out {int(bad.sum())} unusable records ({why})")
    t_all = np.where(bad, -np.inf, states.time)  # an unusable record neither leads nor lags
    ahead = np.concatenate([[True], t_all[1:] > np.maximum.accumulate(t_all)[:-1]]) | bad
    if not ahead.all():
        first = int(np.flatnonzero(~ahead)[0])
        before = float(np.max(t_all[:first]))
        notes.append(f"time goes backwards at sequence {int(states.sequence[first])} (t {before:.6f} -> "
                     f"{t_all[first]:.6f} s): left out {int((~ahead).sum())} records stamped no later than an earlier one")
    keep = ~bad & ahead
    if keep.sum() < 2:
        raise RecordingError(source, f"only {int(keep.sum())} usable records of {keep.size} (" + "; ".join(notes) + ")")
    kept = states[keep]
    velocity = drive_velocity(kept.time, kept.velocity, kept.velocity_fresh, notes)
    return Recording(source, kept.time, kept.position, kept.torque, velocity, None, None, notes + [how], torque_held=True,
                     cycle=kept.cycle, period_s=period_s, torque_from_current=True, stopped=stopped)


def drive_velocity(t: Array, velocity: Array, fresh: NDArray[np.bool_], notes: list[str]) -> Array | None:
    """The drives' velocity at every sample. A PDO plan may carry it every k-th cycle only;
    it is then interpolated (cubic) through the cycles that carried it: the drives' own
    velocity beats differentiating quantised positions, which needs a low-pass that smears
    the Coulomb step at every reversal (measured: viscous friction 14 % low at 20 Hz)."""
    if fresh.all():
        return velocity
    share = fresh.mean(axis=0)
    if t.size < 8 or share.min() < 0.2:
        notes.append("drive velocity too sparse to use: velocity from the positions")
        return None
    from scipy.interpolate import CubicSpline

    out = velocity.copy()
    for j in range(velocity.shape[1]):
        f = fresh[:, j]
        if not f.all():
            out[:, j] = CubicSpline(t[f], velocity[f, j])(t)
    notes.append(f"drive velocity reported on {100 * share.min():.0f} % of the cycles: interpolated (cubic) onto the others")
    return out

"""One pipeline from a recording to parameters: read -> check -> prepare -> identify / diagnose.

``armid identify``, ``armid diagnose``, ``armid serve``, ``armid demo`` and ``armid estimate
--replay`` all go through these functions, so that one recording gives one answer whichever
command reads it (issue 32: the copies at each entry point had drifted apart). What differs
between them is said by a named :class:`Recipe`, never by options written at the call site:

- :data:`USER_LOG`: a log the user brings; the command line's defaults (``--lowpass auto``,
  ``--max-gap-factor 20``, weighted least squares, the modeled prior). ``armid identify``,
  ``armid diagnose`` and ``armid serve --whole-arm identify``.
- :data:`DRIVE_RUN`: a run of ``armid excite`` on the drives, cut to its plan's excitation
  window; the drives' velocity, no low-pass, currents re-timed as held, the samples next to
  a velocity reversal left out. ``armid demo`` and ``armid serve --whole-arm drives``.

Warnings come back as strings (the caller decides where they are printed); a recording that
cannot be identified raises :class:`~armid.schema.errors.RecordingError`. A recording of a run
that ended on a stop (its MCAP metadata says so, :attr:`Recording.stopped
<armid.identify.recordings.Recording.stopped>`) is read and identified like any other, and
:func:`read` (every command's way in) warns with :func:`stop_warning`, naming the file.
"""

from __future__ import annotations

import warnings as _warnings
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from armid.identify.identification import IdentificationResult, IdentifyOptions, modeled_torque
from armid.identify.identification import identify as _identify
from armid.identify.plausibility import check_against_model, check_positions, check_recording, moving_joints
from armid.identify.preprocess import Prepared, PrepareOptions, prepare
from armid.identify.recordings import Recording, recording_of, with_torque
from armid.identify.robot import Robot
from armid.io.recordings import read_mcap_arrays, read_recording, recording_kind, stop_line
from armid.schema.errors import OptionError, PoorExcitationWarning, RecordingError
from armid.schema.joint_states import JointStates

if TYPE_CHECKING:
    from armid.identify.diagnosis.search import DiagnoseOptions, Diagnosis


@dataclass(frozen=True)
class Recipe:
    """How a recording becomes parameters: its preparation and its least squares, named."""

    name: str
    prepare: PrepareOptions
    identify: IdentifyOptions

    def with_options(self, **changes: object) -> Recipe:
        """The recipe with some fields of either options replaced (the command line's flags)."""
        prep = {k: v for k, v in changes.items() if k in PrepareOptions.__dataclass_fields__}
        ident = {k: v for k, v in changes.items() if k in IdentifyOptions.__dataclass_fields__}
        unknown = set(changes) - set(prep) - set(ident)
        if unknown:
            raise TypeError(f"no option {', '.join(sorted(unknown))} in a recipe")
        return replace(self, prepare=replace(self.prepare, **prep), identify=replace(self.identify, **ident))  # type: ignore[arg-type]


USER_LOG = Recipe("user_log", PrepareOptions(max_gap_factor=20.0, lowpass_hz="auto", torque_hold=False),
                  IdentifyOptions(weighting="wls", prior="modeled"))
"""A log the user brings: the command line's defaults (``armid identify --help``). The low-pass
is chosen from each recording's spectrum: a controller's log rarely says how it was filtered."""

DRIVE_RUN = Recipe("drive_run", PrepareOptions(lowpass_hz=None, torque_hold=True), IdentifyOptions(exclude_reversals=True))
"""A drive recording of ``armid excite``: the drives' velocity through the 5-point filter for
acceleration, currents re-timed as held over a period, no low-pass, and the samples next to
a velocity reversal left out. A zero-phase low-pass smears the Coulomb step at every
reversal over tens of milliseconds, which ``sign(qd)`` does not: at 20 Hz viscous friction
came out 7-22 % low and Coulomb friction 2-4 % high, 4-6 sigma, on the simulated PUMA.
Noise in the torque does not bias least squares."""

RECIPES = {"identify": USER_LOG, "drives": DRIVE_RUN}
"""The recipes by the name ``armid serve --whole-arm`` gives them."""


@dataclass(frozen=True)
class Window:
    """A plan's excitation window in a drive recording, as ``armid excite``'s run report gives it:
    the plan started at ``first_cycle``; ``window_s`` is in the plan's time."""

    first_cycle: int
    window_s: tuple[float, float]
    period_s: float


@dataclass
class Inputs:
    """Prepared recordings with what their checks warned about (in the order read)."""

    experiments: list[Prepared]
    validation: list[Prepared] = field(default_factory=list)
    sources: list[str] = field(default_factory=list)  # experiments', then validation's
    warnings: list[str] = field(default_factory=list)
    stopped: dict[str, str] = field(default_factory=dict)  # source -> the line that stopped its run (Recording.stopped)

    def recordings(self) -> list[dict[str, str | None]]:
        """Each recording read, its role and how its run ended (the JSON outputs' ``recordings``)."""
        n = len(self.experiments)
        return [{"path": s, "role": "identification" if k < n else "validation", "stopped": self.stopped.get(s)}
                for k, s in enumerate(self.sources)]


def stop_warning(source: str, line: str) -> str:
    """What every command says of a recording whose run ended on a stop."""
    return f"{source}: the run ended on a stop: {line}"


def plausibility(source: str, robot: Robot, t: np.ndarray, q: np.ndarray, qd: np.ndarray | None, tau: np.ndarray,
                 need_motion: bool = True) -> list[str]:
    """The checks every recording passes before it is used (time units, degrees, dead sensors,
    positions beyond the limits): warnings, or :class:`RecordingError` for garbage."""
    limits = [j.limits.position for j in robot.joints]
    return check_recording(t, q, qd, tau, source, need_motion) + check_positions(q, limits, [j.revolute for j in robot.joints], source)


def read(path: str | Path, robot: Robot, need_motion: bool = True, window: Window | None = None,
         topic: str | None = None) -> tuple[Recording, list[str]]:
    """Read and check one recording (cut to ``window`` when given; ``topic``: a rosbag2 bag's
    JointState topic, ``--topic``); its warnings."""
    return checked(read_recording(path, robot, topic), robot, need_motion, window)


def checked(rec: Recording, robot: Robot, need_motion: bool = True, window: Window | None = None) -> tuple[Recording, list[str]]:
    """Check one recording, read or held in memory (cut to ``window`` when given); its warnings."""
    found = [stop_warning(rec.source, rec.stopped)] if rec.stopped else []
    found += plausibility(rec.source, robot, rec.t, rec.q, rec.qd, rec.tau, need_motion)
    return (rec if window is None else cut_to_window(rec, window)), found


def cut_to_window(rec: Recording, window: Window) -> Recording:
    """A drive recording's samples inside a plan's excitation window (whole periods of the design)."""
    if rec.cycle is None:
        raise RecordingError(rec.source, "no cycle counter: an excitation window is cut from a drive recording (MCAP) only")
    t_plan = (rec.cycle - window.first_cycle) * window.period_s
    w0, w1 = window.window_s
    keep = (t_plan >= w0) & (t_plan <= w1)
    return replace(rec, t=rec.t[keep], q=rec.q[keep], tau=rec.tau[keep], qd=None if rec.qd is None else rec.qd[keep], cycle=rec.cycle[keep],
                   notes=rec.notes + [f"cut to the excitation window {w0:.2f}-{w1:.2f} s of the plan"])


def check_lowpass(value: float | str | None, recordings: Sequence[Recording]) -> None:
    """A numeric cut-off must lie below every recording's Nyquist frequency (``--lowpass``)."""
    if value is None or isinstance(value, str):
        return
    for rec in recordings:
        dt = np.diff(rec.t)
        dt = dt[np.isfinite(dt) & (dt > 0)]
        if dt.size == 0:
            continue
        nyquist = 0.5 / float(np.median(dt))
        if value >= nyquist:
            raise OptionError("--lowpass", f"{value:g} Hz is not below the Nyquist frequency of {rec.source} "
                                           f"({nyquist:g} Hz at its {float(np.median(dt)):g} s sample period)")


def model_warnings(robot: Robot, prepared: Prepared, source: str) -> list[str]:
    """A prepared recording's torque against the robot file's modeled torque (sign, scale)."""
    pair = modeled_torque(robot, prepared)
    if pair is None:
        return []
    moving = moving_joints(np.concatenate([s.q for s in prepared.segments]))
    return check_against_model(*pair, source, moving)


def prepare_checked(recordings: Sequence[tuple[Recording, list[str]]], robot: Robot, recipe: Recipe,
                    sources: Sequence[str] | None = None) -> Inputs:
    """Prepare what :func:`read` gave, by ``recipe``; every warning (the reads', then the model's)."""
    recs = [r for r, _ in recordings]
    names = list(sources) if sources is not None else [r.source for r in recs]
    check_lowpass(recipe.prepare.lowpass_hz, recs)
    prepared = [prepare(r, robot, recipe.prepare) for r in recs]
    found = [w for _, ws in recordings for w in ws]
    for name, prep in zip(names, prepared):
        found += model_warnings(robot, prep, name)
    return Inputs(prepared, [], names, found, {name: r.stopped for name, r in zip(names, recs) if r.stopped})


def load(robot: Robot, recipe: Recipe, data: Sequence[str | Path], validate: Sequence[str | Path] = (),
         topic: str | None = None) -> Inputs:
    """Read, check and prepare the identification and validation recordings of a command
    (``topic``: the JointState topic of those that are rosbag2 bags)."""
    paths = [str(p) for p in [*data, *validate]]
    inputs = prepare_checked([read(p, robot, topic=topic) for p in paths], robot, recipe, paths)
    return Inputs(inputs.experiments[: len(data)], inputs.experiments[len(data) :], paths, inputs.warnings, inputs.stopped)


def load_run(path: str | Path, robot: Robot, recipe: Recipe, window: Window | None = None, need_motion: bool = True) -> tuple[Prepared, list[str]]:
    """One run read, checked, cut to its window and prepared (the demo's)."""
    return prepare_run(read_recording(path, robot), robot, recipe, window, need_motion)


def prepare_run(rec: Recording, robot: Robot, recipe: Recipe, window: Window | None = None, need_motion: bool = True) -> tuple[Prepared, list[str]]:
    """One run checked, cut to its window and prepared (the service's, from memory: the same
    numbers as :func:`load_run` on the run's recording)."""
    inputs = prepare_checked([checked(rec, robot, need_motion, window)], robot, recipe, [rec.source])
    return inputs.experiments[0], inputs.warnings


def identify(robot: Robot, experiments: Sequence[Prepared], validation: Sequence[Prepared], recipe: Recipe) -> tuple[IdentificationResult, list[str]]:
    """The recipe's least squares on prepared recordings; what it warned about (poor excitation)."""
    with _warnings.catch_warnings(record=True) as caught:
        _warnings.simplefilter("always", PoorExcitationWarning)
        result = _identify(robot, list(experiments), list(validation) or None, recipe.identify)
    return result, [str(w.message) for w in caught]


def diagnose(robot: Robot, inputs: Inputs, options: DiagnoseOptions | None = None) -> Diagnosis:
    """The residual's diagnosis on prepared recordings (its 'before' is :func:`identify`'s fit
    with the library's defaults, which are :data:`USER_LOG`'s)."""
    from armid.identify.diagnosis.search import diagnose as _diagnose

    return _diagnose(robot, inputs.experiments, inputs.validation, options)


def replay_records(path: str | Path, robot: Robot, topic: str | None = None) -> tuple[JointStates, list[str], list[str]]:
    """A recording's records in order, on its own stamps, for the payload estimator (``armid
    estimate --replay``); its notes and its checks' warnings.

    An MCAP's records keep their sequence numbers and validity flags (the estimator counts
    what was lost), their torque by :func:`~armid.identify.recordings.with_torque`; the rows of
    any other recording (a CSV, an NPZ, a rosbag2 bag's messages on ``topic``) are numbered.
    Both pass :func:`plausibility`."""
    path = Path(path)
    if not path.exists():
        raise RecordingError(str(path), "no such file")
    if recording_kind(path) != "mcap":
        rec, found = read(path, robot, need_motion=False, topic=topic)
        return _numbered(rec, robot), list(rec.notes), found
    a, metadata, notes = read_mcap_arrays(path)
    if not a:
        raise RecordingError(str(path), "no joint_state record could be read" + (f": {notes[0]}" if notes else ""))
    if a["position"].shape[1] != robot.n_joints:
        raise RecordingError(str(path), f"{a['position'].shape[1]} joints recorded, robot {robot.name} has {robot.n_joints}")
    states, _ = with_torque(JointStates.from_columns(a), robot)
    # identify's checks on identify's reading of it (its usable records, the drives' velocity:
    # what names stamps in milliseconds), the estimator's records as they are
    _, found = checked(recording_of(states, robot, str(path), [], None, stop_line(metadata)), robot, need_motion=False)
    return states, notes, found


def _numbered(rec: Recording, robot: Robot) -> JointStates:
    """A CSV's rows as replay records: those without a time left out (as identify does), time
    required to increase (the line named)."""
    t = np.asarray(rec.t, float)
    line = np.arange(t.size) + 2
    stamped = np.isfinite(t)
    if not stamped.all():
        rec.notes.append(f"left out {int((~stamped).sum())} row(s) without a time stamp (line {', '.join(map(str, line[~stamped][:5]))})")
    t, q, tau = t[stamped], np.asarray(rec.q, float)[stamped], np.asarray(rec.tau, float)[stamped]
    back = np.flatnonzero(~(np.diff(t) > 0))
    if back.size:
        k = int(back[0]) + 1
        raise RecordingError(rec.source, f"line {line[stamped][k]}: time {t[k]:.6g} s is not after the line before ({t[k - 1]:.6g} s): "
                                         "time must increase (a reversed or shuffled log?)")
    return JointStates.of_log(np.arange(t.size), t, np.ones((t.size, robot.n_joints), bool), q, tau)

"""One recording of one arm identified: the work of one Ray task (or of the local loop).

The same pipeline as ``armid identify RECORDING --robot ARM/robot.yaml`` (:mod:`armid.pipeline`:
read and check, prepare and identify by :data:`~armid.pipeline.USER_LOG`, the robot file's
declared effects), then a 2-fold cross-validation over the recording's two halves in time,
and the quantities a fleet tracks (:mod:`armid.identify.tracked`). Whatever goes wrong with a
recording ends as its result's one-line ``error``, never as an exception: a bad file costs
its own row, not the night. A recording whose run ended on a stop (its MCAP metadata says so)
is such a row: ``error`` gives the stop's line, and its quantities are not tracked.
"""

from __future__ import annotations

import os
import socket
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from armid.identify.payload.load_change import last_link_rows
from armid.identify.recordings import Recording
from armid.identify.robot import Robot
from armid.identify.tracked import Tracked, tracked_quantities
from armid.schema.errors import ArmidError

RECORDING_SUFFIXES = (".csv", ".mcap", ".npz", ".db3")
"""The files that are recordings; a rosbag2 bag's folder is one too (:func:`armid.io.ros2_bag.is_bag_folder`)."""


@dataclass(frozen=True)
class Job:
    """A recording to identify: its arm (the folder's name), the fleet's root, its path relative
    to the root, the arm's robot file, and the JointState topic if it is a rosbag2 bag."""

    arm: str
    root: str
    recording: str
    robot_file: str
    topic: str | None = None


@dataclass
class Result:
    """What a recording gave: its first time stamp (s), the tracked quantities, the relative
    errors of the fit and of the cross-validation, or ``error`` (one line) when it failed.
    ``load_rows``: per base parameter (its expression), its coefficients on the last link's ten
    standard parameters (a row of ``P_N``, :func:`armid.identify.payload.load_change.last_link_rows`),
    to read a load on the last link out of the base parameters' steps."""

    arm: str
    recording: str
    start_time: float | None = None
    quantities: list[Tracked] = field(default_factory=list)
    fit_error: float | None = None
    cv_error: float | None = None
    samples: int = 0
    error: str | None = None
    warnings: list[str] = field(default_factory=list)
    seconds: float = 0.0
    cpu_seconds: float = 0.0  # of the process that ran it: the work, whatever the machine's load
    worker: str = ""
    load_rows: dict[str, list[float]] = field(default_factory=dict)
    n_joints: int = 0

    @property
    def ok(self) -> bool:
        return self.error is None


def one_line(text: str, most: int = 400) -> str:
    line = " ".join(str(text).split())
    return line if len(line) <= most else line[: most - 3] + "..."


def halves(rec: Recording) -> tuple[Recording, Recording]:
    """The recording's first and second half in time (every per-sample array cut alike)."""
    cut = rec.n_samples // 2

    def part(s: slice) -> Recording:
        arrays = {k: getattr(rec, k)[s] for k in ("t", "q", "tau", "qd", "qdd", "lines", "cycle") if getattr(rec, k) is not None}
        return replace(rec, **arrays, source=f"{rec.source} ({'first' if s.start is None else 'second'} half)", notes=list(rec.notes))

    return part(slice(None, cut)), part(slice(cut, None))


def cross_validation(rec: Recording, robot: Robot, warnings: list[str]) -> float | None:
    """Mean held-out relative error of a 2-fold cross-validation over the halves in time: each
    half identified by the recipe, the other predicted at its own stamps. None (and a warning)
    when a half cannot be identified on its own."""
    from armid import pipeline

    errors = []
    first, second = halves(rec)
    try:
        a, b = (pipeline.prepare_checked([(h, [])], robot, pipeline.USER_LOG).experiments[0] for h in (first, second))
        recipe = pipeline.USER_LOG.with_options(held_out_error=False)  # the halves' validation errors are what is wanted
        for train, test in ((a, b), (b, a)):
            result, _ = pipeline.identify(robot, [train], [test], recipe)
            if result.validation is not None:
                errors.append(float(result.validation["relative_error"]))
    except ArmidError as err:
        warnings.append(f"cross-validation left out: {one_line(str(err), 200)}")
        return None
    return float(np.mean(errors)) if errors else None


def identify_recording(job: Job) -> Result:
    """Identify one recording as ``armid identify`` does and cross-validate it; never raises.
    BLAS keeps to one thread: the engine runs one task per core."""
    from threadpoolctl import threadpool_limits

    start, cpu = time.perf_counter(), time.process_time()
    out = Result(job.arm, job.recording, worker=f"{socket.gethostname()}:{os.getpid()}")
    try:
        with threadpool_limits(1, "blas"):
            _identify_into(job, out)
    except ArmidError as err:
        out.error = one_line(str(err))
    except Exception as err:  # a bug must cost its recording, not the night: said as such
        out.error = one_line(f"internal error ({type(err).__name__}: {err})")
    out.seconds, out.cpu_seconds = time.perf_counter() - start, time.process_time() - cpu
    return out


def _identify_into(job: Job, out: Result) -> None:
    from armid import pipeline
    from armid.io.robot_file import load_robot

    robot = load_robot(job.robot_file)
    path = Path(job.root) / job.recording
    rec, found = pipeline.read(path, robot, topic=job.topic)
    stamps = rec.t[np.isfinite(rec.t)]
    out.start_time = float(stamps[0]) if stamps.size else None
    if rec.stopped:  # a run cut short is not the arm's usual experiment: tracked, it would pass for a change
        out.error = one_line(f"the run ended on a stop: {rec.stopped}; not tracked")
        return
    inputs = pipeline.prepare_checked([(rec, found)], robot, pipeline.USER_LOG, [str(path)])
    result, excitation = pipeline.identify(robot, inputs.experiments, [], pipeline.USER_LOG)
    out.warnings = [one_line(w, 300) for w in [*inputs.warnings, *excitation]]
    out.quantities = tracked_quantities(result)
    out.n_joints = robot.n_joints
    rows = last_link_rows(result.base, robot.n_joints)
    out.load_rows = {x: [float(v) for v in row] for x, row in zip(result.base.expressions(), rows)}
    out.fit_error = float(result.fit["relative_error"])
    out.samples = int(result.samples)
    out.cv_error = cross_validation(rec, robot, out.warnings)

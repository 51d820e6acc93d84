"""The operator's experiments: designs chained pose to pose, run on the drives, analysed.

``armid excite`` and ``armid demo`` share this: every trajectory is designed, planned from
where the previous one ends and checked against every limit at the control period before it
can move anything (a plan that fails is refused with its first violation), then run back to
back. ``armid excite`` checks them all before any drive is enabled; the demo designs its
later ones beside the first runs, and checks each before its run.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from armid.daq.excite import ExcitationSession, RunReport
from armid.identify import excitation as ex
from armid.identify.identification import IdentificationResult
from armid.identify.preprocess import Prepared
from armid.identify.robot import Robot
from armid.schema.errors import ArmidError, UsageError

from . import pipeline
from .pipeline import DRIVE_RUN, Recipe, Window


@dataclass(frozen=True)
class Experiment:
    name: str
    design: ex.Design
    plan: ex.Plan

    @property
    def link(self) -> int | None:
        """0-based link of a single-link experiment, None for a whole-arm run."""
        return self.design.moving[0] if len(self.design.moving) == 1 else None


LINK_MARGIN = 0.8
"""The share of each velocity and acceleration limit a single-link design may use
(:func:`~identify.excitation.design`'s default)."""

WHOLE_MARGIN = 0.6
"""The share a whole-arm design may use: coupled joints at speed track less well."""


@dataclass(frozen=True)
class Designed:
    """A design as it comes from the optimiser, before it is planned from a pose."""

    name: str
    design: ex.Design
    periods: int
    margin: float  # the share of each limit its plan's lead-in uses
    seconds: float  # the design's own time

    def line(self) -> str:
        """What it identifies, as the operator reads it."""
        d = self.design
        what = f"identifies {', '.join(d.base)}; condition number {d.condition_number:.3g}" if len(d.moving) == 1 else \
            f"rank {d.rank}, condition number {d.condition_number:.3g}, {len(d.unidentifiable)} parameters unidentifiable"
        return f"designed {self.name.replace('link', 'link ')} in {self.seconds:.1f} s: {what}"


def designs(robot: Robot, start: np.ndarray, links: list[int], whole: list[tuple[str, int]], link_frequency_hz: float = 0.5,
            link_periods: int = 2, whole_frequency_hz: float = 0.2, seed: int = 0, whole_margin: float = WHOLE_MARGIN) -> Iterator[Designed]:
    """Single-link designs for ``links`` (0-based, in the order given; each holds the others where
    the previous one ends, Khosla's property 4), then the whole-arm designs ``whole`` (name,
    periods), which start from no pose: one after the other, as each is made. Each takes the
    seed of its link or of its place among the whole-arm runs, so that a chain continued
    elsewhere (:class:`ExperimentsBeside`) gives the same designs."""
    pose = np.asarray(start, float)
    for k in links:
        began = time.monotonic()
        hold = ex.choose_hold(robot, k, pose, seed=seed + k)
        d = ex.design(robot, moving=(k,), q_hold=hold, base_frequency_hz=link_frequency_hz, seed=seed + k, margin=LINK_MARGIN)
        yield Designed(f"link{k + 1}", d, link_periods, LINK_MARGIN, time.monotonic() - began)
        pose = end_pose(d)
    for i, (name, periods) in enumerate(whole):
        began = time.monotonic()
        d = ex.design(robot, base_frequency_hz=whole_frequency_hz, seed=seed + 100 + i, margin=whole_margin)
        yield Designed(name, d, periods, whole_margin, time.monotonic() - began)


def end_pose(d: ex.Design) -> np.ndarray:
    """Where a plan of ``d`` ends (its trajectory's pose at time 0: whole periods)."""
    return np.asarray(d.trajectory.evaluate(np.zeros(1))[0][0], float)


class Chain:
    """Plans designs one after the other, each from where the previous one ends, and checks
    each at the control period against every limit (the first violation raises
    :class:`~identify.excitation.TrajectoryLimitError`, before that plan can move anything)."""

    def __init__(self, robot: Robot, start: np.ndarray, period_s: float) -> None:
        self.robot, self.period_s, self.limits = robot, period_s, ex.Limits.of(robot)
        self.pose = np.asarray(start, float)

    def add(self, d: Designed) -> Experiment:
        p = ex.plan(d.design, self.pose, self.limits, periods=d.periods, lead_fraction=d.margin)
        ex.check_plan(self.robot, p, self.period_s, self.limits)
        self.pose = end_pose(d.design)
        return Experiment(d.name, d.design, p)


def design_experiments(robot: Robot, start: np.ndarray, links: list[int], whole: list[tuple[str, int]], period_s: float,
                       link_frequency_hz: float = 0.5, link_periods: int = 2, whole_frequency_hz: float = 0.2,
                       seed: int = 0, log: Any = None, whole_margin: float = WHOLE_MARGIN) -> list[Experiment]:
    """Every experiment designed (:func:`designs`), planned from its pose and checked
    (:class:`Chain`) before any drive is enabled. Whole-arm runs use ``whole_margin`` of
    each limit: coupled joints at speed track less well, and the supervision stops the arm
    at the limit itself. A lead-in uses the share of the limits its experiment uses (it was
    half of them: 16 of the demo's 59 s of motion were lead-ins). ``log``: each design's line."""
    chain = Chain(robot, start, period_s)
    out = []
    for d in designs(robot, start, links, whole, link_frequency_hz, link_periods, whole_frequency_hz, seed, whole_margin):
        out.append(chain.add(d))
        if log:
            log(d.line())
    return out


class ExperimentsBeside:
    """The experiments of :func:`design_experiments`, the first designed here and the others in
    a process of their own while the drives run the ones before (issue 65: the demo's 5 s of
    designs came before any motion). Each is planned from its pose and checked against every
    limit here, in the process that commands the drives, before it is handed over to run; a
    plan that fails stops the sequence there. ``links``: one at least (the first is designed
    here); ``log``: each design's line as it is handed over."""

    def __init__(self, robot: Robot, start: np.ndarray, links: list[int], whole: list[tuple[str, int]], period_s: float,
                 link_frequency_hz: float = 0.5, link_periods: int = 2, whole_frequency_hz: float = 0.2, seed: int = 0,
                 log: Any = None, whole_margin: float = WHOLE_MARGIN) -> None:
        import multiprocessing

        if not links:
            raise UsageError("experiments designed beside the runs start with a single-link experiment: none given")
        settings: dict[str, Any] = {"link_frequency_hz": link_frequency_hz, "link_periods": link_periods, "whole_frequency_hz": whole_frequency_hz,
                    "seed": seed, "whole_margin": whole_margin}
        self.names = [f"link{k + 1}" for k in links] + [name for name, _ in whole]
        self._cycle_s = [link_periods / link_frequency_hz] * len(links) + [periods / whole_frequency_hz for _, periods in whole]
        self._log, self._chain = log, Chain(robot, start, period_s)
        self.experiments: list[Experiment] = []  # handed over so far, in order
        self.waited_s = 0.0  # for designs not yet made when their run was due
        spawn = multiprocessing.get_context("spawn")  # a fork would copy this process's threads' locks
        self._poses, self._designed = spawn.Queue(), spawn.Queue()
        self._process = spawn.Process(target=_design_beside, args=(self._poses, self._designed, robot, links[1:], whole, settings),
                                      name="armid-designs", daemon=True)
        self._process.start()  # its imports are made while the first design is made here
        try:
            self._hand_over(next(designs(robot, start, links[:1], [], **settings)))
        except BaseException:
            self.close()
            raise
        self._poses.put(self._chain.pose)

    def __len__(self) -> int:
        return len(self.names)

    @property
    def motion_s(self) -> float:
        """The plans' seconds of motion: those handed over, and the others as their periods and the
        mean lead-in and settling of those make them (a lead-in takes 1-2.5 s, as far as it goes)."""
        known = [e.plan.duration_s for e in self.experiments]
        leads = (sum(known) - sum(self._cycle_s[: len(known)])) / len(known)
        return sum(known) + sum(s + leads for s in self._cycle_s[len(known):])

    def __iter__(self) -> Iterator[Experiment]:
        yield self.experiments[0]
        while len(self.experiments) < len(self.names):
            yield self._hand_over(self._next())

    def _next(self) -> Designed:
        import queue

        name, began = self.names[len(self.experiments)], time.monotonic()
        while True:
            try:
                got = self._designed.get(timeout=0.5)
            except queue.Empty:
                if not self._process.is_alive():
                    raise ArmidError(f"the design process ended (exit code {self._process.exitcode}) before {name} was designed") from None
                continue
            self.waited_s += time.monotonic() - began
            if isinstance(got, str):
                raise ArmidError(f"designing {name}: {got}")
            return got

    def _hand_over(self, d: Designed) -> Experiment:
        self.experiments.append(self._chain.add(d))
        if self._log:
            self._log(d.line())
        return self.experiments[-1]

    def close(self) -> None:
        if self._process.is_alive():
            self._process.terminate()
        self._process.join(5.0)
        for q in (self._poses, self._designed):
            q.close()
            q.join_thread()


def _design_beside(poses: Any, designed: Any, robot: Robot, links: list[int], whole: list[tuple[str, int]], settings: dict[str, Any]) -> None:
    """:class:`ExperimentsBeside`'s process: the designs after the first, from the pose it is
    sent, each put on ``designed`` as it is made (a failure as its message). One BLAS thread, as
    the demo's (the products are small; a second thread stalls on a loaded 2-core machine), so
    that its designs are those one process makes."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(1, "blas")
    pose = poses.get()
    try:
        for d in designs(robot, pose, links, whole, **settings):
            designed.put(d)
    except Exception as err:  # said by the process that runs the drives, where the design is needed
        designed.put(f"{type(err).__name__}: {err}")


def run_experiments(session: ExcitationSession, experiments: Sequence[Experiment] | ExperimentsBeside, out: Path, console: Any = None,
                    status: Callable[[], str] | None = None, tick: Callable[[], None] | None = None) -> list[RunReport]:
    """Run each experiment on the drives with a progress bar; stop at the first that fails.
    ``experiments`` designed beside the runs come as they are designed (the bars' total of
    motion is the plans' so far and the others' periods). ``status``: a live line (records,
    rate, lost cycles, faults) shown under the bars; ``tick``: called with each update of the
    bars (every 0.2 s, in this thread, not the bus's)."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    reports = []
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.fields[summary]}"), TimeRemainingColumn(),
                  console=console, transient=False) as progress:
        total_s = _motion_s(experiments)
        overall = progress.add_task(f"{'all runs':>8}", total=total_s, summary=f"{len(experiments)} plans, {total_s:.0f} s of motion")
        done_s = 0.0
        live = progress.add_task(f"{'live':>8}", total=None, summary=status()) if status is not None else None
        for e in experiments:
            progress.update(overall, total=_motion_s(experiments))
            task = progress.add_task(f"{e.name:>8}", total=e.plan.duration_s, summary="")

            def update(t: float, control: Any, task: Any = task, e: Experiment = e, done_s: float = done_s) -> None:
                err = np.max(control.max_error) * 1000.0
                tq = np.max(control.peak_torque) * 100.0
                progress.update(task, completed=min(t, e.plan.duration_s),
                                summary=f"tracking error {err:5.1f} mrad, peak torque {tq:4.0f} % of limit")
                progress.update(overall, completed=done_s + min(t, e.plan.duration_s))
                if live is not None and status is not None:
                    progress.update(live, summary=status())
                if tick is not None:
                    tick()

            report = session.run(e.plan, out / e.name, e.name, {"design": e.design.to_json()}, progress=update)
            reports.append(report)
            done_s += e.plan.duration_s
            progress.update(overall, completed=done_s)
            if not report.completed:
                break
    return reports


def _motion_s(experiments: Sequence[Experiment] | ExperimentsBeside) -> float:
    """The experiments' seconds of motion (of those designed beside the runs: as known so far)."""
    return experiments.motion_s if isinstance(experiments, ExperimentsBeside) else sum(e.plan.duration_s for e in experiments)


def run_window(report: RunReport, period_s: float) -> Window:
    """The excitation window (whole periods of the design) of a run, from its report."""
    return Window(report.first_cycle, report.window_s, period_s)


def prepared_runs(reports: list[RunReport], robot: Robot, period_s: float, warn: Callable[[str], None] | None = None) -> dict[str, Prepared]:
    """Each run's recording through the pipeline as a drive run (:data:`~armid.pipeline.DRIVE_RUN`),
    cut to its excitation window; what the checks found goes to ``warn``."""
    out = {}
    for r in reports:
        out[r.name], found = pipeline.load_run(r.recording, robot, DRIVE_RUN, run_window(r, period_s))
        if warn is not None:
            for warning in found:
                warn(warning)
    return out


def identify_whole_arm(robot: Robot, run: Prepared, others: list[Prepared], recipe: Recipe = DRIVE_RUN) -> IdentificationResult:
    """A whole-arm run's fit, validated on the ``others``: the one recipe of the demo and the
    service (a poorly excited parameter is the design's business, said at design time)."""
    return pipeline.identify(robot, [run], others, recipe)[0]


def service_agreement(doc: dict[str, Any], whole: IdentificationResult, run: str = "whole_a") -> dict[str, Any]:
    """The estimator service's published fit of ``run`` against the one made from the complete
    recording: equal when the service received every record (largest difference in sigmas)."""
    fit = (doc.get("whole_arm") or {}).get(run) or {}
    values = np.array([b["value"] for b in fit.get("base_parameters", [])], float)
    beta, std = whole.estimate.beta, whole.estimate.std
    if values.shape != beta.shape:
        return {"run": run, "published": int(values.size), "max_difference_sigma": float("inf")}
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(std > 0, np.abs(values - beta) / std, 0.0)
    return {"run": run, "published": int(values.size), "max_difference_sigma": float(np.max(z)),
            "missing_records": int(doc["experiment"].get("missing", 0)) if doc.get("experiment") else None}

"""The operator's experiments: designs chained pose to pose, run on the drives, analysed.

``armid excite`` and ``armid demo`` share this: every trajectory is designed and checked
against every limit before any drive is enabled (a plan that fails is refused with its
first violation), then run back to back, each starting where the previous one ended.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from armid.daq.excite import ExcitationSession, RunReport
from armid.identify import excitation as ex
from armid.identify.identification import IdentificationResult
from armid.identify.preprocess import Prepared
from armid.identify.robot import Robot

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


def design_experiments(robot: Robot, start: np.ndarray, links: list[int], whole: list[tuple[str, int]], period_s: float,
                       link_frequency_hz: float = 0.5, link_periods: int = 2, whole_frequency_hz: float = 0.2,
                       seed: int = 0, log: Any = None, whole_margin: float = WHOLE_MARGIN,
                       progress: Callable[[int, int, float], None] | None = None, whole_beside: bool = False) -> list[Experiment]:
    """Single-link experiments for ``links`` (0-based, in the order given), then the whole-arm
    runs ``whole`` (name, periods); each plan starts where the previous one ends. Every
    plan is checked at the control period; the first violation raises
    :class:`~identify.excitation.TrajectoryLimitError` before anything moves. Whole-arm
    runs use ``whole_margin`` of each limit: coupled joints at speed track less well, and
    the supervision stops the arm at the limit itself. A lead-in uses the share of the limits
    its experiment uses (it was half of them: 16 of the demo's 59 s of motion were lead-ins).
    ``progress(done, total, seconds)`` follows each design with the time it took. ``whole_beside``: the first whole-arm design,
    which does not depend on the pose it starts from, is made in a process of its own while the
    single-link chain is designed here, the others here after the chain (the same designs: the
    two sides take about as long, the process's start included, on two cores); each is planned
    from its pose and checked here."""
    limits = ex.Limits.of(robot)
    out: list[Experiment] = []
    pose = np.asarray(start, float)
    total = len(links) + len(whole)
    seeds = [seed + 100 + i for i in range(len(whole))]

    def add(name: str, d: ex.Design, periods: int, took: float, what: str, margin: float) -> np.ndarray:
        p = ex.plan(d, pose, limits, periods=periods, lead_fraction=margin)
        ex.check_plan(robot, p, period_s, limits)
        out.append(Experiment(name, d, p))
        if progress:
            progress(len(out), total, took)
        if log:
            log(f"designed {what} in {took:.1f} s: " + (f"identifies {', '.join(d.base)}; condition number {d.condition_number:.3g}"
                if len(d.moving) == 1 else f"rank {d.rank}, condition number {d.condition_number:.3g}, "
                f"{len(d.unidentifiable)} parameters unidentifiable"))
        return d.trajectory.evaluate(np.zeros(1))[0][0]

    beside = _WholeDesigns(robot, whole_frequency_hz, seeds[:1], whole_margin) if whole_beside and whole and links else None
    try:
        for k in links:
            began = time.monotonic()
            hold = ex.choose_hold(robot, k, pose, seed=seed + k)
            d = ex.design(robot, moving=(k,), q_hold=hold, base_frequency_hz=link_frequency_hz, seed=seed + k, margin=LINK_MARGIN)
            pose = add(f"link{k + 1}", d, link_periods, time.monotonic() - began, f"link {k + 1}", LINK_MARGIN)
        for i, (name, periods) in enumerate(whole):
            d, took = beside.result(i) if beside is not None and i == 0 else _timed_whole_design(robot, whole_frequency_hz, seeds[i], whole_margin)
            pose = add(name, d, periods, took, name, whole_margin)
    finally:
        if beside is not None:
            beside.close()
    return out


def _timed_whole_design(robot: Robot, frequency_hz: float, seed: int, margin: float) -> tuple[ex.Design, float]:
    """A whole-arm design and the seconds it took."""
    began = time.monotonic()
    d = ex.design(robot, base_frequency_hz=frequency_hz, seed=seed, margin=margin)
    return d, time.monotonic() - began


def _one_blas_thread() -> None:
    """The worker's BLAS as the demo's (one thread: the products are small, and a second
    thread stalls on a loaded 2-core machine), so that its designs are the ones made here."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(1, "blas")


class _WholeDesigns:
    """Whole-arm designs made in one worker process (spawned: a fork would copy this process's
    threads' locks), handed over in order."""

    def __init__(self, robot: Robot, frequency_hz: float, seeds: list[int], margin: float) -> None:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        self._pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), initializer=_one_blas_thread)
        self._futures = [self._pool.submit(_timed_whole_design, robot, frequency_hz, s, margin) for s in seeds]

    def result(self, i: int) -> tuple[ex.Design, float]:
        return self._futures[i].result()

    def close(self) -> None:
        self._pool.shutdown(cancel_futures=True)


def run_experiments(session: ExcitationSession, experiments: list[Experiment], out: Path, console: Any = None,
                    status: Callable[[], str] | None = None, tick: Callable[[], None] | None = None) -> list[RunReport]:
    """Run each experiment on the drives with a progress bar; stop at the first that fails.
    ``status``: a live line (records, rate, lost cycles, faults) shown under the bars; ``tick``:
    called with each update of the bars (every 0.2 s, in this thread, not the bus's)."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    reports = []
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.fields[summary]}"), TimeRemainingColumn(),
                  console=console, transient=False) as progress:
        total_s = sum(e.plan.duration_s for e in experiments)
        overall = progress.add_task(f"{'all runs':>8}", total=total_s, summary=f"{len(experiments)} plans, {total_s:.0f} s of motion")
        done_s = 0.0
        live = progress.add_task(f"{'live':>8}", total=None, summary=status()) if status is not None else None
        for e in experiments:
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

"""What ``armid demo`` is doing and how long the rest will take: its phases, each announced with
the time left, and a timeline of each announcement beside the time that in fact followed
(``demo.json``'s ``timeline``)."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any


class Phases:
    """What the demo is doing and how long the rest will take, printed as each phase starts.

    Each phase has an estimate in seconds, replaced by what is known as the demo goes: the
    first design by the time it took, the runs by their plans' durations (the arm runs in real
    time; the plans not yet designed by their periods), the payload phase by its plan's at the
    pace the runs had. The rest
    are figures measured on the 2-core machine the demo was written on. Every line that says
    a time left is kept in :attr:`timeline` with this process's wall and CPU seconds."""

    def __init__(self, console: Any, estimates: dict[str, float]) -> None:
        self.console, self.estimates, self.started = console, dict(estimates), time.monotonic()
        self.current: str | None = None
        self.phase_started = self.started
        self.timeline: list[dict[str, Any]] = []

    def mark(self, what: str, left_s: float | None = None) -> None:
        """A step of the timeline: seconds since the start, this process's CPU seconds, the time
        left announced then (None: a step that announced none)."""
        self.timeline.append({"what": what, "at_s": round(time.monotonic() - self.started, 3), "cpu_s": round(time.process_time(), 3),
                              "announced_left_s": None if left_s is None else round(left_s, 1)})

    def honesty(self) -> list[dict[str, Any]]:
        """The timeline with, beside each announced time left, the time that followed (to now, the
        end) and the announcement's error in % of it."""
        end = time.monotonic() - self.started
        out = []
        for m in self.timeline:
            actual = round(end - m["at_s"], 1) if m["announced_left_s"] is not None else None
            error = round(100 * (m["announced_left_s"] / actual - 1), 1) if actual else None
            out.append({**m, "actual_left_s": actual, "error_percent": error})
        return out

    def left_s(self) -> float:
        """Seconds left: the rest of the current phase and every phase after it."""
        keys = list(self.estimates)
        k = keys.index(self.current) if self.current in keys else 0
        in_phase = max(0.0, self.estimates[keys[k]] - (time.monotonic() - self.phase_started)) if self.current else self.estimates[keys[0]]
        return in_phase + sum(self.estimates[key] for key in keys[k + 1 :])

    def start(self, key: str, text: str) -> None:
        self.current, self.phase_started = key, time.monotonic()
        keys = list(self.estimates)
        left = self.left_s()
        self.mark(key, left)
        self.console.print(f"[bold][{keys.index(key) + 1}/{len(keys)}][/] {text} "
                           f"[dim]({time.monotonic() - self.started:.0f} s in, about {left:.0f} s left)[/]")

    def note(self, text: str) -> None:
        left = self.left_s()
        self.mark(f"{self.current}: {text[:40]}", left)
        self.console.print(f"  {text} [dim](about {left:.0f} s left)[/]")


PHASE_ESTIMATES_S = {"design": 1.5, "runs": 58.0, "payload": 16.0}
"""First guesses for :class:`Phases` (the first design; the runs and the payload phase until the
designs give their plans), from runs on a 2-core machine with a warm numba cache."""

CORES = max(os.cpu_count() or 1, 1)


class IdleCpu:
    """The machine's CPU left idle since this was made, in cores (idle and I/O wait over every
    core, ``/proc/stat``): what tells a quiet machine from a busy one while the demo runs."""

    def __init__(self) -> None:
        self._since, self._idle = time.monotonic(), _idle_cpu_s()
        self.last: float | None = None  # the last reading

    def cores(self) -> float | None:
        """Idle cores on average so far; None where ``/proc/stat`` is not there, or too soon."""
        idle, elapsed = _idle_cpu_s(), time.monotonic() - self._since
        self.last = None if idle is None or self._idle is None or elapsed < 1.0 else (idle - self._idle) / elapsed
        return self.last


def _idle_cpu_s() -> float | None:
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return (int(fields[4]) + int(fields[5])) / os.sysconf("SC_CLK_TCK") if fields[0] == "cpu" else None
    except (OSError, ValueError, IndexError):
        return None


BUSY_BELOW_IDLE_CORES = 0.1
"""Idle cores over the runs below which the machine is busy beyond the demo: 0.40 measured quiet on
the 2-core machine (the real-time process costs 1.0-1.4 ms of CPU a 2 ms cycle as the host varies,
by that a slow hour would leave about 0.2), 0.0005 beside two busy loops."""


def analysis_share_over_the_payload_run(idle_cores: float | None) -> float:
    """The share of a core the demo's analysis gets over the payload run, beside the real-time process
    (SCHED_FIFO) and the payload estimator above it: 0.40-0.48 measured on the quiet 2-core machine,
    0.31-0.35 beside two busy loops, told apart by the CPU left idle over the runs (``idle_cores``;
    where it is not known, by the load average). Measured before the run, the share was higher than
    over it, and the phase announced 15 s where 21 s followed. The load average told them apart until
    demos ran back to back: a quiet one began at 3.25 and ended at 4.18 and took the busy share
    (+38 %: 18 s announced, 13 s followed)."""
    busy = os.getloadavg()[0] > CORES + 1.5 if idle_cores is None else idle_cores < BUSY_BELOW_IDLE_CORES
    return 0.35 if busy else 0.45


ESTIMATOR_ABOVE = 5
"""How far above the demo's priority its payload estimator runs where allowed (nice 5 less): it must keep up
with the live stream while the analysis computes beside it at the demo's own."""

RUNS_START_S = 1.4
"""The runs' phase beyond their motion: the drives' start before the first run and their stop after
the last, the estimator service's last fit (measured on the 2-core machine)."""

PER_RUN_S = 0.35
"""Each run's own seconds beyond its plan: the recording closed, the next plan started (measured)."""

PAYLOAD_OVERHEAD_S = 3.0
"""The payload phase beyond its plan's motion: its drives' start and stop, the last estimates, the
report written once the analysis beside it is in (measured on the 2-core machine)."""

ANALYSIS_CPU_S = 6.0
"""The analysis's CPU seconds once the runs have ended (every recording through the pipeline, the
identifications, truth checks, diagnosis, consistent model, reports and plots, the payload's plot
included: 4.9-6.7 s measured on the 2-core machine, its imports made while the arm moved)."""

REPORT_S = 1.0
"""The report's own seconds once the analysis is in: writing it, ending the processes (measured)."""


def cpu_seconds(pid: int) -> float | None:
    """A process's CPU seconds so far (user and system, Linux's ``/proc``), None where there is none."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


class Share:
    """The analysis's process as the clock sees it: its CPU seconds since it was given its work
    and the share of a core it has had, and how long the rest of ``need_s`` CPU seconds will take."""

    def __init__(self, pid: int, need_s: float) -> None:
        self.pid, self.need_s = pid, need_s
        self.cpu0, self.t0 = cpu_seconds(pid) or 0.0, time.monotonic()

    def since_s(self) -> float:
        return time.monotonic() - self.t0

    def used_s(self) -> float:
        return (cpu_seconds(self.pid) or self.cpu0) - self.cpu0

    def left_s(self, measure_s: float = 0.0, least: float = 0.05) -> float:
        """Wall seconds until it is done at the share it has had since it started (with ``measure_s``:
        the share it gets over the next ``measure_s`` seconds, if more: the machine may have freed up),
        taken as ``least`` of a core at least."""
        if measure_s > 0:
            used0 = self.used_s()
            time.sleep(measure_s)
            used = self.used_s()
            rate = max(used / self.since_s(), (used - used0) / measure_s)
        else:
            used = self.used_s()
            rate = used / max(self.since_s(), 1e-3)
        return max(self.need_s - used, 0.3) / max(rate, least)

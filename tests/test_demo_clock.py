"""The demo's clock (issue 65): each time left it announces is kept in ``demo.json``'s timeline
beside the time that in fact followed; the analysis's share of a core is measured from its CPU
seconds; the whole-arm designs made beside the single-link chain are those made in line."""

from __future__ import annotations

import io
import os
import subprocess
import sys
import time

import numpy as np
from rich.console import Console

from armid.demo_clock import BUSY_BELOW_IDLE_CORES, CORES, IdleCpu, Phases, Share, analysis_share_over_the_payload_run, cpu_seconds


def test_the_timeline_keeps_each_announcement_beside_the_time_that_followed() -> None:
    text = io.StringIO()
    phases = Phases(Console(file=text, width=200), {"a": 2.0, "b": 3.0})
    phases.start("a", "first")
    phases.mark("a step that announces nothing")
    phases.estimates["b"] = 1.0
    phases.start("b", "second")
    phases.note("a note")
    time.sleep(0.2)
    steps = phases.honesty()
    end = steps[-1]["at_s"] + steps[-1]["actual_left_s"]
    assert [m["what"] for m in steps] == ["a", "a step that announces nothing", "b", "b: a note"]
    assert steps[0]["announced_left_s"] == 5.0 and steps[1]["announced_left_s"] is None and steps[1]["actual_left_s"] is None
    assert steps[2]["announced_left_s"] == 1.0
    for m in (steps[0], steps[2], steps[3]):
        assert abs(m["at_s"] + m["actual_left_s"] - end) < 0.15  # each to the same end, rounded to 0.1 s
        assert m["error_percent"] == round(100 * (m["announced_left_s"] / m["actual_left_s"] - 1), 1)
    assert "[1/2] first" in text.getvalue() and "about 5 s left" in text.getvalue()


def test_a_process_share_of_a_core_and_what_is_left_of_its_work_are_measured() -> None:
    """A child that computes 0.6 CPU seconds then sleeps: its CPU seconds grow to that, then stop;
    with 1.0 s of work announced, what is left is the rest at the share of a core it has had since
    it started (its measured rate), or at ``least`` where that is more; a reaped process has no
    CPU seconds."""
    child = subprocess.Popen([sys.executable, "-c", "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.6: pass\n"
                              "time.sleep(60)"])
    try:
        share = Share(child.pid, need_s=1.0)
        deadline = time.monotonic() + 60
        while share.used_s() < 0.6 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)  # idle now: its CPU seconds stay where they are
        used = share.used_s()
        assert 0.6 <= used < 0.7
        before = share.since_s()
        left = share.left_s(measure_s=0.3)
        after = share.since_s()
        assert (1.0 - used) / (used / before) * 0.95 <= left <= (1.0 - used) / (used / after) * 1.05, (used, before, after, left)
        assert abs(share.left_s(least=100.0) - 0.4 / 100.0) < 1e-3  # the rest (0.3 s at least) at 100 cores
    finally:
        child.kill()
        child.wait()
    assert cpu_seconds(child.pid) is None
    assert (mine := cpu_seconds(os.getpid())) is not None and mine > 0


def test_the_idle_cpu_tells_a_machine_kept_busy_beside_the_demo() -> None:
    """As many busy loops as cores leave no CPU idle: the demo counts its analysis at the busy
    share then, and at the quiet one where a core is idle (0.40 of one measured over the quiet
    demo's runs, 0.0005 beside two busy loops). Too soon to say, it says nothing."""
    loops = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(CORES)]
    try:
        time.sleep(0.5)  # the loops started
        idle = IdleCpu()
        assert idle.cores() is None and idle.last is None
        time.sleep(2.0)
        cores = idle.cores()
    finally:
        for loop in loops:
            loop.kill()
            loop.wait()
    assert cores is not None and 0.0 <= cores < BUSY_BELOW_IDLE_CORES and idle.last == cores
    assert analysis_share_over_the_payload_run(cores) == 0.35 and analysis_share_over_the_payload_run(0.40) == 0.45


def test_the_experiments_designed_beside_the_runs_are_those_designed_in_line() -> None:
    """:class:`ExperimentsBeside` (the demo's: the first design here, the others in a process of
    their own while the drives run) hands over, in order, the designs and plans that one
    process gives; its estimate of the motion is the plans' once all are in, and within 15 %
    of it before (the lead-ins not yet planned take 1-2.5 s each)."""
    from threadpoolctl import threadpool_limits

    from armid.demo import DEFAULT_RIG
    from armid.experiments import ExperimentsBeside, design_experiments
    from armid.io.rig_file import load_rig

    rig = load_rig(DEFAULT_RIG)
    start = np.asarray(rig.simulation["initial_position"], float)
    whole = [("whole_a", 2), ("whole_b", 1)]
    said: list[str] = []
    with threadpool_limits(1, "blas"):
        chain = ExperimentsBeside(rig.robot, start, [5, 4], whole, rig.period_s, seed=3, log=said.append)
        try:
            assert [e.name for e in chain.experiments] == ["link6"] and len(chain) == 4
            ahead = chain.motion_s
            beside = list(chain)
        finally:
            chain.close()
        in_line = design_experiments(rig.robot, start, [5, 4], whole, rig.period_s, seed=3)
    assert [e.name for e in beside] == ["link6", "link5", "whole_a", "whole_b"] == [e.name for e in in_line]
    for e, f in zip(beside, in_line):
        assert e.design.to_json() == f.design.to_json()
        assert np.array_equal(e.plan.start, f.plan.start) and e.plan.duration_s == f.plan.duration_s
    motion = sum(e.plan.duration_s for e in in_line)
    assert chain.motion_s == motion and abs(ahead - motion) < 0.15 * motion, (ahead, motion)
    assert [line.split(" in ")[0] for line in said] == ["designed link 6", "designed link 5", "designed whole_a", "designed whole_b"]



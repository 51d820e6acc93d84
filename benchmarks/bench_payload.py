"""On-line payload RLS: cost of one update and the rate it sustains on replay.

Replay folds a 2 ms recording of the simulated PUMA 560 (with a 2 kg payload attached
half way) through the same code ``armid estimate --replay`` and the Zenoh service run
(:meth:`EstimateStream.feed`: derivatives of the whole batch at once, one 10 x 10
update per 10 ms of the arm's time). Figures are ratios to a reference run in the same
process (the arm model evaluated on every record in one batch) and the recording's duration
over the time taken; the live service is timed fed 10 records at a time. The estimator is numpy
but for the projection of each published estimate onto physically possible payloads, a
compiled kernel that ``PayloadRLS.warm`` compiles before the service says it is alive (a cold
compile of the whole estimator once took 40 s, which a fresh machine paid while the arm moved).

    python benchmarks/bench_payload.py [seconds_of_data]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from figures_json import recorded

from armid.daq.payload_service import EstimateStream
from armid.identify import excitation as ex
from armid.identify.identification import declared_effects, structural_base
from armid.identify.payload.rls import ArmModel, PayloadRLS
from armid.io.rig_file import load_rig
from armid.schema.joint_states import JointStates
from armid.sim_bus.offline import simulate
from armid.sim_bus.physics import Payload, simulation_config

RIG = Path(__file__).resolve().parent.parent / "config" / "rigs" / "sim.yaml"


def main(seconds: float = 20.0) -> None:
    from armid.demo import true_parameters

    rig = load_rig(RIG)
    robot = rig.robot
    effects = declared_effects(robot)
    base = structural_base(robot, effects)
    names = robot.parameter_names + [label for e in effects for label in e.labels()]
    arm = ArmModel(robot, tuple(effects), base.independent, base.base_values(true_parameters(rig, names)),
                   np.array([0.42, 0.87, 0.22, 0.10, 0.16, 0.15]))
    d = ex.design(robot, base_frequency_hz=0.2, seed=3, margin=0.6)
    plan = ex.plan(d, np.asarray(rig.simulation["initial_position"], float), ex.Limits.of(robot), periods=max(1, int(seconds / 5)))
    run = simulate(robot, simulation_config(rig.simulation, 6), plan.evaluate, plan.duration_s,
                   payloads=[(plan.duration_s / 2, Payload(2.0, (0.02, -0.03, 0.08)))])
    duration = float(run.t[-1] - run.t[0])

    records = JointStates.of_log(np.arange(run.t.size), run.t, np.ones((run.t.size, 6), bool), run.position, run.torque)
    EstimateStream(PayloadRLS(arm)).feed(records[:400])  # first calls
    # the reference run, in this process: the arm model and payload columns of every record in one
    # batch (the least any replay must do); the figures below are ratios to it, not wall-clock bounds
    start = time.perf_counter()
    arm.torque_and_payload_columns(run.position, np.zeros_like(run.position), np.zeros_like(run.position))
    reference_s = time.perf_counter() - start

    stream = EstimateStream(PayloadRLS(arm))
    start = time.perf_counter()
    docs = stream.feed(records)  # what armid estimate --replay runs
    replay_s = time.perf_counter() - start

    one = EstimateStream(PayloadRLS(arm))
    start = time.perf_counter()
    for k in range(0, run.t.size, 10):  # the live service keeping up: a batch per 10 records (20 ms at 2 ms)
        one.feed(records[k : k + 10])
    live_s = time.perf_counter() - start

    n = run.t.size
    print(f"{n} records ({duration:.1f} s of data at {rig.period_s * 1000:g} ms), {len(docs)} estimates; "
          f"last mass {docs[-1]['mass']:.3f} +- {docs[-1]['mass_std']:.3f} kg ({docs[-1]['status']})")
    print(f"reference (arm model of every record, one batch): {reference_s:.3f} s")
    print(f"replay (armid estimate --replay): {replay_s:.2f} s = {replay_s / reference_s:.1f}x the reference, "
          f"{1e6 * replay_s / n:.0f} us per record, {duration / replay_s:.1f}x real time")
    print(f"live, 10 records per batch: {live_s:.2f} s = {live_s / reference_s:.1f}x the reference, {duration / live_s:.1f}x real time")


if __name__ == "__main__":
    with recorded("payload"):
        main(float(sys.argv[1]) if len(sys.argv) > 1 else 20.0)

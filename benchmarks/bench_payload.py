"""On-line payload RLS: cost of one update and the rate it sustains on replay.

Replay folds a 2 ms recording of the simulated PUMA 560 (with a 2 kg payload attached
half way) through the same code ``armid estimate --replay`` and the Zenoh service run; the
figure is the recording's duration over the time it took (target: at least 20 times real
time). One update is also timed alone, fed one record at a time as the live service is
when it keeps up. The estimator is plain numpy (a cold numba compile took 40 s, which a
fresh machine paid while the arm moved); each published estimate includes the projection
onto physically possible payloads.

    python benchmarks/bench_payload.py [seconds_of_data]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from armid.daq.payload_service import EstimateStream
from armid.identify import excitation as ex
from armid.identify.identification import declared_effects, structural_base
from armid.identify.payload import ArmModel, PayloadRLS
from armid.io.rig_file import load_rig
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
    records = [(k, float(run.t[k]), np.ones(6, bool), run.position[k], run.torque[k]) for k in range(run.t.size)]
    duration = run.t[-1] - run.t[0]

    EstimateStream(PayloadRLS(arm)).feed(records[:200])  # first-call costs out of the way (nothing is compiled)
    stream = EstimateStream(PayloadRLS(arm))
    start = time.perf_counter()
    docs = stream.feed(records)
    replay_s = time.perf_counter() - start

    one = EstimateStream(PayloadRLS(arm))
    start = time.perf_counter()
    for r in records:
        one.feed([r])
    single_s = time.perf_counter() - start

    n = len(records)
    print(f"{n} records ({duration:.1f} s of data at {rig.period_s * 1000:g} ms), {len(docs)} estimates; "
          f"last mass {docs[-1]['mass']} kg ({docs[-1]['status']})")
    print(f"replay (armid estimate --replay): {replay_s:.2f} s = {1e6 * replay_s / n:.0f} us per update, "
          f"{duration / replay_s:.1f}x real time (target >= 20x)")
    print(f"one record at a time (live, keeping up): {1e6 * single_s / n:.0f} us per update, {duration / single_s:.1f}x real time")


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else 20.0)

"""``armid diagnose`` against ``armid identify`` on the same long log, in the same process
(target: diagnose at most 4x identify).

The log has the shape of a user's real arm (issue 34): 6 joints, motor currents at 100 Hz
(quantised, jittery stamps, no velocity), three identification runs and one validation run
of 125 s each (50,000 samples in all), friction on every joint declared in the robot file
and an undeclared torque-constant error on one joint under it. It is ``tests/blindgen.py``'s
(Pinocchio, no armid code). Both commands read the same prepared recordings (reading and
preprocessing, which they share, is timed apart); identify is the declared model's fit,
diagnose that fit and its search for what the model lacks. Wall-clock and CPU seconds are
both given: on a shared machine the CPU figure is the steadier one.

    python benchmarks/bench_diagnose.py [seconds_per_run] [repeats]
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

import blindgen  # noqa: E402
from figures_json import recorded  # noqa: E402

from armid import pipeline  # noqa: E402
from armid.io.robot_file import load_robot  # noqa: E402

FRICTION = [{"effect": e, "joint": None} for e in ("coulomb_friction", "viscous_friction", "torque_offset")]


def make_log(out: Path, seconds: float) -> blindgen.Case:
    """The long simulated log (module docstring)."""
    return blindgen.make_case(3, out, n_joints=6, rate_hz=100.0, noise="medium", currents=True, current_lsb=1e-3, velocity=False,
                              jitter=0.1, effect="torque_gain", effect_snr=25.0, extra_effects=[{"effect": "friction_all", "size": 0.2}],
                              n_ident=3, duration_s=seconds, valid_duration_s=seconds, declare=FRICTION)


def timed(fn):  # type: ignore[no-untyped-def]
    """(result, wall seconds, CPU seconds) of ``fn()``."""
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - wall, time.process_time() - cpu


def main(seconds: float = 125.0, repeats: int = 1) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        case = make_log(Path(tmp) / "log", seconds)
        robot = load_robot(case.robot_yaml)
        inputs, t_read, _ = timed(lambda: pipeline.load(robot, pipeline.USER_LOG, case.ident_csvs, [case.valid_csv]))
    samples = sum(s.n_samples for p in inputs.experiments + inputs.validation for s in p.segments)
    runs = []
    for _ in range(repeats):  # alternating, so that a load that comes and goes falls on both
        _, wall_i, cpu_i = timed(lambda: pipeline.identify(robot, inputs.experiments, inputs.validation, pipeline.USER_LOG))
        diag, wall_d, cpu_d = timed(lambda: pipeline.diagnose(robot, inputs))
        runs.append((wall_i, cpu_i, wall_d, cpu_d))
    wall_i, cpu_i, wall_d, cpu_d = (statistics.median(r[k] for r in runs) for k in range(4))
    found = ", ".join(f"{f.effect}@{'arm' if f.joint is None else f.joint + 1}" for f in diag.found) or "nothing"
    print(f"diagnose, {robot.n_joints} joints, 4 files, {samples} samples at 100 Hz (reading and preprocessing {t_read:.1f} s): "
          f"identify {wall_i:.2f} s ({cpu_i:.2f} s CPU), diagnose {wall_d:.2f} s ({cpu_d:.2f} s CPU), "
          f"ratio {wall_d / wall_i:.2f}x (CPU {cpu_d / cpu_i:.2f}x); found {found}; validation error "
          f"{100 * diag.before['relative_error']:.3g} % -> {100 * diag.after['relative_error']:.3g} %")


if __name__ == "__main__":
    with recorded("diagnose"):
        main(float(sys.argv[1]) if len(sys.argv) > 1 else 125.0, int(sys.argv[2]) if len(sys.argv) > 2 else 1)

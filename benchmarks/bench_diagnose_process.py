"""``armid diagnose`` on four 6-joint 100 Hz current logs (about 5,000 samples each), validated on a
fifth, against the plain pipeline (``../shared/tools/baseline.py``, rigid body and friction) on
the same files, as whole processes, what a user waits for (target: at most 4x).

    python benchmarks/bench_diagnose_process.py [repeats] [seconds_per_log]

The logs are ``tests/blindgen.py``'s (Pinocchio, no armid code), with the shape of a user's real
arm as in ``bench_diagnose.py``: motor currents quantised to 1 mA, jittery stamps, no velocity,
friction on every joint declared in the robot file and an undeclared torque-constant error on
one joint under it. The two processes run interleaved (diagnose, plain, diagnose, ...); each is
given as its best and its median, wall-clock and CPU seconds, with the load average at the start
and the end.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

import blindgen  # noqa: E402
from bench_identify_process import interleaved, print_against  # noqa: E402
from figures_json import load_average, recorded  # noqa: E402

BASELINE = ROOT.parent / "shared" / "tools" / "baseline.py"
FRICTION = [{"effect": e, "joint": None} for e in ("coulomb_friction", "viscous_friction", "torque_offset")]


def main(repeats: int = 5, seconds: float = 50.0) -> None:
    armid = str(Path(sys.executable).parent / "armid")
    with tempfile.TemporaryDirectory() as tmp:
        case = blindgen.make_case(3, Path(tmp) / "logs", n_joints=6, rate_hz=100.0, noise="medium", currents=True, current_lsb=1e-3,
                                  velocity=False, jitter=0.1, effect="torque_gain", effect_snr=25.0,
                                  extra_effects=[{"effect": "friction_all", "size": 0.2}], n_ident=4, duration_s=seconds,
                                  valid_duration_s=seconds, declare=FRICTION)
        logs = [str(p) for p in case.ident_csvs]
        commands = {
            "armid diagnose": [armid, "diagnose", *logs, "--robot", str(case.robot_yaml), "--validate", str(case.valid_csv),
                               "--json", str(Path(tmp) / "diagnose.json")],
            "plain pipeline": [sys.executable, str(BASELINE), *logs, "--robot", str(case.robot_yaml), "--validate", str(case.valid_csv)],
        }
        times, cpus, last, load_start = interleaved(commands, repeats)
    print(f"4 logs of {int(seconds * 100)} samples x 6 joints (currents, 100 Hz) and a fifth to validate, {repeats} interleaved runs each, "
          f"{os.cpu_count()} cores, load average {load_start} at the start, {load_average()} at the end")
    print_against(times, cpus, last, "armid diagnose", "plain pipeline")


if __name__ == "__main__":
    args = sys.argv[1:]
    with recorded("diagnose_process"):
        main(int(args[0]) if args else 5, float(args[1]) if len(args) > 1 else 50.0)

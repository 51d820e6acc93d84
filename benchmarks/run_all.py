"""Every benchmark, one after another, each writing ``benchmarks/results/<name>.json``; then
``python scripts/gen_figures.py`` renders ``docs/figures.md`` from them.

    python benchmarks/run_all.py [--list] [NAME ...]    # NAME: a result's name (default: all)

Run it on a quiet machine: the figures are the machine's, and the load average is recorded
beside each. On the project's 2-core machine, with other test runs beside it (load average
6-12), the whole run took about 40 minutes, of which the five demos 16 and the timing-sensitive
tests beside two busy processes 5; quiet, expect about half.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

# result name -> the command's arguments after ``python benchmarks/``
RUNS = {
    "startup": ["bench_startup.py"],
    "identify_process": ["bench_identify_process.py"],
    "diagnose_process": ["bench_diagnose_process.py"],
    "regressor": ["bench_regressor.py"],
    "identify": ["bench_identify.py"],
    "feasible": ["bench_feasible.py"],
    "diagnose": ["bench_diagnose.py"],
    "design": ["bench_design.py"],
    "puma_identify": ["bench_command.py", "puma_identify"],
    "kuka_identify": ["bench_command.py", "kuka_identify"],
    "kuka_diagnose": ["bench_command.py", "kuka_diagnose"],
    "check_cases": ["bench_command.py", "check_cases"],
    "payload": ["bench_payload.py"],
    "recording": ["bench_recording.py"],
    "bags": ["bench_bags.py"],
    "daq": ["bench_daq.py"],
    "canopen": ["bench_canopen.py", "10", "virtual", "udp_multicast"],
    "canopen_busy2": ["bench_canopen.py", "10", "virtual", "udp_multicast", "--busy", "2"],
    "dynamixel": ["bench_dynamixel.py"],
    "serial_load": ["bench_serial_load.py", "30", "2"],
    "dynamixel_excite": ["bench_command.py", "dynamixel_excite"],
    "dynamixel_excite_busy2": ["bench_command.py", "dynamixel_excite", "--busy", "2"],
    "fleet": ["bench_fleet.py"],
    "demo": ["bench_demo.py", "2"],
    "demo_busy2": ["bench_demo.py", "3", "--busy", "2"],
    "realtime_busy2": ["bench_realtime.py", "--busy", "2"],
}


def main(names: list[str]) -> int:
    unknown = [n for n in names if n not in RUNS]
    if unknown:
        print(f"unknown: {', '.join(unknown)}; the names: {', '.join(RUNS)}", file=sys.stderr)
        return 2
    failed = []
    start = time.monotonic()
    for name in names or list(RUNS):
        argv = [sys.executable, str(HERE / RUNS[name][0]), *RUNS[name][1:]]
        print(f"== {name}: python benchmarks/{' '.join(RUNS[name])}", flush=True)
        t0 = time.monotonic()
        if subprocess.run(argv, cwd=ROOT).returncode != 0:
            failed.append(name)
        print(f"== {name}: {time.monotonic() - t0:.0f} s", flush=True)
    print(f"all in {(time.monotonic() - start) / 60:.1f} min" + (f"; failed: {', '.join(failed)}" if failed else ""))
    return 1 if failed else 0


if __name__ == "__main__":
    if "--list" in sys.argv[1:]:
        print("\n".join(f"{n}: python benchmarks/{' '.join(a)}" for n, a in RUNS.items()))
        raise SystemExit(0)
    raise SystemExit(main(sys.argv[1:]))

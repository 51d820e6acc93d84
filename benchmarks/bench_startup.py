"""How long ``armid --version`` and ``armid identify --help`` take, as whole processes, against
``python -c "import numpy"`` in the same run (target: each at most 2x, best of N).

    python benchmarks/bench_startup.py [repeats]

The three commands run interleaved (reference, version, help, reference, ...) so that a change
in the machine's load falls on all of them alike; each is reported as its best and its median
over the repeats, with the load average at the start and the end of the run.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from figures_json import load_average, recorded

ROOT = Path(__file__).resolve().parent.parent
ARMID = str(Path(sys.executable).parent / "armid")
COMMANDS = {
    'python -c "import numpy"': [sys.executable, "-c", "import numpy"],
    "armid --version": [ARMID, "--version"],
    "armid identify --help": [ARMID, "identify", "--help"],
}
REFERENCE = 'python -c "import numpy"'


def wall_seconds(argv: list[str]) -> float:
    """One whole process, start to exit; a failed run is the benchmark's fault, not a figure."""
    start = time.perf_counter()
    done = subprocess.run(argv, cwd=ROOT, capture_output=True)
    took = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} exited {done.returncode}: {done.stderr.decode()[-500:]}")
    return took


def main(repeats: int = 7) -> None:
    for argv in COMMANDS.values():  # one warm-up each: the files in the page cache, as a user's second run
        wall_seconds(argv)
    load_start = load_average()
    times: dict[str, list[float]] = {name: [] for name in COMMANDS}
    for _ in range(repeats):
        for name, argv in COMMANDS.items():
            times[name].append(wall_seconds(argv))
    best_ref, median_ref = min(times[REFERENCE]), statistics.median(times[REFERENCE])
    print(f"{repeats} interleaved runs each, {os.cpu_count()} cores, load average {load_start} at the start, {load_average()} at the end")
    for name, secs in times.items():
        best, median = min(secs), statistics.median(secs)
        ratio = "" if name == REFERENCE else f"; {best / best_ref:.2f}x the reference (best), {median / median_ref:.2f}x (median)"
        print(f"`{name}`: best {1000 * best:.0f} ms, median {1000 * median:.0f} ms{ratio}")


if __name__ == "__main__":
    with recorded("startup"):
        main(int(sys.argv[1]) if len(sys.argv) > 1 else 7)

"""The timing-sensitive tests (``-m "realtime and not slow"``, the service's end-to-end runs
left out as CI leaves them) as one whole pytest process beside busy processes (a lab PC's load):
how many pass, and how long the pass takes.

    python benchmarks/bench_realtime.py [--busy N]     # default: 2 busy processes

Writes ``benchmarks/results/realtime_busyN.json`` (``realtime.json`` with ``--busy 0``).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

from busy import busy_loops
from figures_json import recorded

ROOT = Path(__file__).resolve().parent.parent
PYTEST = ["-m", "pytest", "tests", "-m", "realtime and not slow", "--ignore=tests/test_serve.py", "-p", "no:cacheprovider"]


def main(busy: int) -> int:
    with busy_loops(busy):
        start = time.monotonic()
        done = subprocess.run([sys.executable, *PYTEST], cwd=ROOT, env=dict(os.environ), capture_output=True, text=True)
        took = time.monotonic() - start
    lines = done.stdout.strip().splitlines()
    tally = next((ln.strip("= ") for ln in reversed(lines) if re.search(r"\d+ (passed|failed)", ln)), "no tally")
    failed = [ln.split(" - ")[0] for ln in lines if ln.startswith("FAILED ")]
    print(f"`python {' '.join(PYTEST[:4])} \"{PYTEST[4]}\" {' '.join(PYTEST[5:6])}`"
          + (f" beside {busy} busy processes" if busy else ", no busy process of its own") + f": {tally} ({took:.0f} s wall)")
    for line in failed:
        print(line)
    return 0


if __name__ == "__main__":
    args = sys.argv[1:]
    busy = int(args[args.index("--busy") + 1]) if "--busy" in args else 2
    with recorded("realtime" + (f"_busy{busy}" if busy else "")):
        main(busy)

"""A documented ``armid`` command (or example) run as a whole process, as a user runs it: its
wall-clock time and the lines of its output that state its figures.

    python benchmarks/bench_command.py NAME       # NAME: one of CASES below

``puma_identify``: the shipped PUMA 560 example identified and validated; ``kuka_identify`` and
``kuka_diagnose``: the shared KUKA LWR4+ recordings (``../shared/data/kuka_lwr4/``, beside the
repository), the declared model's fit and its diagnosis; ``check_cases``: ``armid check`` on
simulated arms with and without a tool (``examples/check_cases.py``, seeds 0-2 of its ten). Each writes
``benchmarks/results/<NAME>.json``.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from figures_json import recorded

ROOT = Path(__file__).resolve().parent.parent
KUKA = "../shared/data/kuka_lwr4"


@dataclass(frozen=True)
class Case:
    argv: list[str]  # OUT stands for a fresh temporary folder
    keep: str  # a regular expression: the output lines that state the figures


CASES = {
    "puma_identify": Case(["armid", "identify", "examples/puma560_excitation.csv", "--robot", "config/robots/puma560.yaml",
                           "--validate", "examples/puma560_validation.csv", "--json", "OUT/identify.json"],
                          r"base parameters|error"),
    "kuka_identify": Case(["armid", "identify", f"{KUKA}/measurements_1.npz", "--robot", "config/robots/kuka_lwr4.yaml",
                           "--validate", f"{KUKA}/measurements_2.npz", "--json", "OUT/identify.json"],
                          r"base parameters|error"),
    "kuka_diagnose": Case(["armid", "diagnose", f"{KUKA}/measurements_1.npz", "--robot", "config/robots/kuka_lwr4.yaml",
                           "--validate", f"{KUKA}/measurements_2.npz", "--out", "OUT/diagnosis"],
                          r"found|error|set aside|negligible|finding"),
    "check_cases": Case([sys.executable, "examples/check_cases.py", "OUT", "--seeds", "0", "1", "2"], r"^tools found"),
}


def main(name: str) -> int:
    case = CASES[name]
    env = {**os.environ, "PATH": str(Path(sys.executable).parent) + os.pathsep + os.environ.get("PATH", ""), "COLUMNS": "200"}
    with tempfile.TemporaryDirectory() as out:
        argv = [a.replace("OUT", out) for a in case.argv]
        start = time.monotonic()
        done = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True)
        took = time.monotonic() - start
    shown = " ".join("python" if a == sys.executable else a.replace("OUT", "OUT") for a in case.argv)
    if done.returncode != 0:
        print(f"`{shown}` exited {done.returncode}:\n{done.stdout[-2000:]}{done.stderr[-2000:]}", file=sys.stderr)
        return done.returncode
    print(f"`{shown}`: {took:.1f} s")
    for line in done.stdout.splitlines():
        if line.strip() and re.search(case.keep, line):
            print(line.replace(out, "OUT").rstrip())
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 2 or sys.argv[1] not in CASES:
        raise SystemExit(f"usage: python benchmarks/bench_command.py {{{','.join(CASES)}}}")
    with recorded(sys.argv[1]):
        code = main(sys.argv[1])
        if code:
            raise SystemExit(code)

"""A documented ``armid`` command (or example) run as a whole process, as a user runs it: its
wall-clock time and the lines of its output that state its figures.

    python benchmarks/bench_command.py NAME [--busy N]    # NAME: one of CASES below

``puma_identify``: the shipped PUMA 560 example identified and validated; ``kuka_identify`` and
``kuka_diagnose``: the shared KUKA LWR4+ recordings (``../shared/data/kuka_lwr4/``, beside the
repository), the declared model's fit and its diagnosis; ``check_cases``: ``armid check`` on
simulated arms with and without a tool (``examples/check_cases.py``, seeds 0-2 of its ten);
``dynamixel_excite``: the simulated Dynamixel arm's whole-arm excitation, then its recording
identified. Each writes ``benchmarks/results/<NAME>.json`` (``<NAME>_busyN.json`` beside N busy
processes).
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

from busy import busy_loops
from figures_json import recorded

ROOT = Path(__file__).resolve().parent.parent
KUKA = "../shared/data/kuka_lwr4"


@dataclass(frozen=True)
class Case:
    steps: list[list[str]]  # the commands, in order; OUT stands for one fresh temporary folder
    keep: str  # a regular expression: the output lines that state the figures


CASES = {
    "puma_identify": Case([["armid", "identify", "examples/puma560_excitation.csv", "--robot", "config/robots/puma560.yaml",
                            "--validate", "examples/puma560_validation.csv", "--json", "OUT/identify.json"]],
                          r"base parameters|error"),
    "kuka_identify": Case([["armid", "identify", f"{KUKA}/measurements_1.npz", "--robot", "config/robots/kuka_lwr4.yaml",
                            "--validate", f"{KUKA}/measurements_2.npz", "--json", "OUT/identify.json"]],
                          r"base parameters|error"),
    "kuka_diagnose": Case([["armid", "diagnose", f"{KUKA}/measurements_1.npz", "--robot", "config/robots/kuka_lwr4.yaml",
                            "--validate", f"{KUKA}/measurements_2.npz", "--json", "OUT/diagnose.json"]],
                          r"found|error|set aside|negligible|finding"),
    "check_cases": Case([[sys.executable, "examples/check_cases.py", "OUT", "--seeds", "0", "1", "2"]], r"^tools found"),
    "dynamixel_excite": Case([["armid", "excite", "--rig", "config/rigs/sim_dynamixel.yaml", "--whole", "--no-zenoh", "--out", "OUT"],
                              ["armid", "identify", "OUT/whole/run.mcap", "--robot", "config/robots/dxl_arm6.yaml"]],
                             r"tracking error|completed|base parameters|fit error|lost"),
}


def main(name: str) -> int:
    case = CASES[name]
    env = {**os.environ, "PATH": str(Path(sys.executable).parent) + os.pathsep + os.environ.get("PATH", ""), "COLUMNS": "200"}
    with tempfile.TemporaryDirectory() as out:
        for step in case.steps:
            shown = " ".join("python" if a == sys.executable else a for a in step)
            start = time.monotonic()
            done = subprocess.run([a.replace("OUT", out) for a in step], cwd=ROOT, env=env, capture_output=True, text=True)
            took = time.monotonic() - start
            if done.returncode == 2:  # bad usage or input: the benchmark's own fault, no figure
                print(f"`{shown}` exited 2:\n{done.stdout[-2000:]}{done.stderr[-2000:]}", file=sys.stderr)
                return 2
            lines = [ln.replace(out, "OUT").rstrip() for ln in (done.stdout + done.stderr).splitlines() if ln.strip()]
            if done.returncode != 0:  # a run that stopped (a fault, a lost drive): that is the figure
                print(f"`{shown}`: exited {done.returncode} after {took:.1f} s: {lines[-1] if lines else ''}")
                return 0
            print(f"`{shown}`: {took:.1f} s")
            for line in lines:
                if re.search(case.keep, line) and "━" not in line:
                    print(line)
    return 0


if __name__ == "__main__":
    args = sys.argv[1:]
    busy = int(args[args.index("--busy") + 1]) if "--busy" in args else 0
    if "--busy" in args:
        del args[args.index("--busy"): args.index("--busy") + 2]
    if len(args) != 1 or args[0] not in CASES:
        raise SystemExit(f"usage: python benchmarks/bench_command.py {{{','.join(CASES)}}} [--busy N]")
    with recorded(args[0] + (f"_busy{busy}" if busy else "")), busy_loops(busy):
        code = main(args[0])
        if code:
            raise SystemExit(code)

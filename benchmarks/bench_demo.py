"""``armid demo`` as a user runs it, a whole process each time: how long it takes and what it
finds (the truth check of the single-link sequence and of the whole arm, the payload), quiet or
beside busy processes (a lab PC's load).

    python benchmarks/bench_demo.py [runs] [--busy N]

Each run is ``armid demo --out DIR`` in a fresh folder, its figures read from ``DIR/demo.json``;
a run that does not finish is counted and its last lines shown. Writes
``benchmarks/results/demo.json`` (``demo_busyN.json`` with ``--busy N``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from busy import busy_loops
from figures_json import recorded

ROOT = Path(__file__).resolve().parent.parent


def one_demo() -> tuple[float, dict | None, str]:  # type: ignore[type-arg]
    """(wall seconds, demo.json or None when it failed, the output's tail)."""
    env = {**os.environ, "PATH": str(Path(sys.executable).parent) + os.pathsep + os.environ.get("PATH", ""), "COLUMNS": "200"}
    with tempfile.TemporaryDirectory() as out:
        start = time.monotonic()
        done = subprocess.run(["armid", "demo", "--out", out], cwd=ROOT, env=env, capture_output=True, text=True)
        took = time.monotonic() - start
        doc = json.loads((Path(out) / "demo.json").read_text()) if done.returncode == 0 else None
    return took, doc, (done.stdout + done.stderr)[-400:]


def summary(took: float, doc: dict) -> str:  # type: ignore[type-arg]
    s, w, p, service = doc["truth_check"]["single_link"], doc["truth_check"]["whole_arm"], doc["payload"], doc["service"]
    attach = p["after_attach_2s"]
    com = attach["com_error_m"]
    payload = (f"payload 2 s after the attach {attach['mass']:.3f} kg (true {p['true_mass']} kg), centre of mass off by {1000 * com:.1f} mm"
               if com is not None and attach["mass"] is not None else "payload: no estimate 2 s after the attach")
    return (f"{took:.0f} s; single-link {s['within_3_sigma']} of {s['combinations']} within 3 sigma (max |z| {s['max_abs_z']:.2f}), "
            f"whole arm {w['within_3_sigma']} of {w['combinations']} ({w['max_abs_z']:.2f}); the service's whole-arm fit against "
            f"the recording's: {service['max_difference_sigma']:.2g} sigma at most, {service.get('missing_records')} records missed; {payload}")


def main(runs: int, busy: int) -> None:
    finished = 0
    with busy_loops(busy):
        for k in range(runs):
            took, doc, tail = one_demo()
            if doc is None:
                print(f"run {k + 1}: did not finish after {took:.0f} s: {tail.strip().splitlines()[-1] if tail.strip() else ''}", flush=True)
                continue
            finished += 1
            print(f"run {k + 1}: {summary(took, doc)}", flush=True)
    print(f"{finished} of {runs} demos finished" + (f" beside {busy} busy processes" if busy else ", no busy process of its own"))


if __name__ == "__main__":
    args = sys.argv[1:]
    busy = int(args[args.index("--busy") + 1]) if "--busy" in args else 0
    if "--busy" in args:
        del args[args.index("--busy"): args.index("--busy") + 2]
    with recorded("demo" + (f"_busy{busy}" if busy else "")):
        main(int(args[0]) if args else 1, busy)

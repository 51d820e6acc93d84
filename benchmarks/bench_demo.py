"""``armid demo`` as a user runs it, a whole process each time: how long it takes, how true the
time left it announces is, and what it finds (the truth check of the single-link sequence and of
the whole arm, the payload), quiet or beside busy processes (a lab PC's load).

    python benchmarks/bench_demo.py [runs] [--busy N] [--against CHECKOUT]

Each run is ``armid demo --out DIR`` in a fresh folder, its figures read from ``DIR/demo.json``;
a run that does not finish is counted and its last lines shown. Each run's line gives its wall
time, the load average (1 min) as it started and as it ended, the worst error of the time left
the demo announced against the time that in fact followed (``demo.json``'s ``timeline``; issue
65 asks for at most 25 % at each step), the truth checks passed and the payload. The summary:
min, median and max wall time, the worst time-left error, the runs whose every combination is
within 3 sigma. ``--against CHECKOUT`` alternates each run with one of another checkout's demo
(its ``.venv``), in the same period: old against new under the same load. ``--busy N``: N
processes each keeping a core busy beside every run, killed by id after. Writes
``benchmarks/results/demo.json`` (``demo_busyN.json`` with ``--busy N``).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from busy import busy_loops
from figures_json import recorded

ROOT = Path(__file__).resolve().parent.parent


def stolen_s() -> float:
    """CPU seconds the host has taken from this virtual machine so far (``/proc/stat``'s steal, all
    CPUs; 0 where there is none): a demo is real time, and a host that does not run the machine's
    CPUs when they are due stretches it (8-11 s of a 95 s demo measured on a busy host)."""
    try:
        fields = Path("/proc/stat").read_text().splitlines()[0].split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return 0.0


def one_demo(checkout: Path = ROOT) -> tuple[float, dict[str, Any] | None, str, tuple[float, float, float]]:
    """(wall seconds, demo.json or None when it failed, the output's tail, the load average at its
    start and end and the CPU seconds the host stole meanwhile); ``checkout``'s demo (with its
    ``.venv``; this interpreter's for this checkout)."""
    bin_dir = Path(sys.executable).parent if checkout == ROOT else checkout / ".venv" / "bin"
    env = {**os.environ, "PATH": str(bin_dir) + os.pathsep + os.environ.get("PATH", ""), "COLUMNS": "200"}
    with tempfile.TemporaryDirectory() as out:
        load0, stolen0 = os.getloadavg()[0], stolen_s()
        start = time.monotonic()
        done = subprocess.run([str(bin_dir / "armid"), "demo", "--out", out], cwd=checkout, env=env, capture_output=True, text=True)
        took = time.monotonic() - start
        load1 = os.getloadavg()[0]
        doc = json.loads((Path(out) / "demo.json").read_text()) if done.returncode == 0 else None
    return took, doc, (done.stdout + done.stderr)[-400:], (load0, load1, stolen_s() - stolen0)


def worst_time_left(doc: dict[str, Any]) -> tuple[float | None, str]:
    """The worst announced time left against the time that followed, in %, and where it was said."""
    steps = [m for m in doc.get("timeline", []) if m.get("announced_left_s") is not None and m.get("actual_left_s")]
    if not steps:
        return None, "no timeline (a demo before issue 65's)"
    worst = max(steps, key=lambda m: abs(m["announced_left_s"] / m["actual_left_s"] - 1))
    off = 100 * (worst["announced_left_s"] / worst["actual_left_s"] - 1)
    return off, (f"time left within {abs(off):.0f} % at all {len(steps)} steps (worst {off:+.0f} % at {worst['what'][:32]!r}: "
                 f"announced {worst['announced_left_s']:.0f} s, {worst['actual_left_s']:.0f} s followed)")


def truth_passed(doc: dict[str, Any]) -> bool:
    s, w = doc["truth_check"]["single_link"], doc["truth_check"]["whole_arm"]
    return bool(s["within_3_sigma"] == s["combinations"] and w["within_3_sigma"] == w["combinations"])


def summary(took: float, doc: dict[str, Any], load: tuple[float, float, float]) -> str:
    s, w, p, service = doc["truth_check"]["single_link"], doc["truth_check"]["whole_arm"], doc["payload"], doc["service"]
    attach = p["after_attach_2s"]
    com = attach["com_error_m"]
    payload = (f"payload 2 s after the attach {attach['mass']:.3f} kg (true {p['true_mass']} kg), centre of mass off by {1000 * com:.1f} mm, "
               f"{p['estimates']} estimates, {p['skipped']} records skipped"
               if com is not None and attach["mass"] is not None else "payload: no estimate 2 s after the attach")
    return (f"{took:.1f} s (load average {load[0]:.2f} -> {load[1]:.2f}, {load[2]:.1f} CPU s stolen by the host); {worst_time_left(doc)[1]}; "
            f"single-link {s['within_3_sigma']} of {s['combinations']} within 3 sigma (max |z| {s['max_abs_z']:.2f}, p {s['chi2_p']:.2f}), "
            f"whole arm {w['within_3_sigma']} of {w['combinations']} ({w['max_abs_z']:.2f}, p {w['chi2_p']:.2f}); the service's whole-arm "
            f"fit against the recording's: {service['max_difference_sigma']:.2g} sigma at most, {service.get('missing_records')} records "
            f"missed; {payload}")


def main(runs: int, busy: int, against: Path | None = None) -> None:
    checkouts = [("", ROOT)] + ([(f" ({against})", against)] if against is not None else [])
    walls: dict[str, list[float]] = {name: [] for name, _ in checkouts}
    worst: dict[str, list[float]] = {name: [] for name, _ in checkouts}
    truths: dict[str, int] = {name: 0 for name, _ in checkouts}
    with busy_loops(busy):
        for k in range(runs):
            for name, checkout in checkouts:
                took, doc, tail, load = one_demo(checkout)
                if doc is None:
                    print(f"run {k + 1}{name}: did not finish after {took:.0f} s (load average {load[1]:.2f}): "
                          f"{tail.strip().splitlines()[-1] if tail.strip() else ''}", flush=True)
                    continue
                walls[name].append(took)
                off, _ = worst_time_left(doc)
                if off is not None:
                    worst[name].append(abs(off))
                truths[name] += truth_passed(doc)
                print(f"run {k + 1}{name}: {summary(took, doc, load)}", flush=True)
    for name, _ in checkouts:
        t = sorted(walls[name])
        where = f" beside {busy} busy processes" if busy else ", no busy process of its own"
        print(f"{len(t)} of {runs} demos{name} finished{where}"
              + (f": wall min {t[0]:.1f} s, median {statistics.median(t):.1f} s, max {t[-1]:.1f} s" if t else "")
              + (f"; the worst time-left error {max(worst[name]):.0f} %" if worst[name] else "")
              + f"; every combination within 3 sigma in {truths[name]} of {len(t)}")


if __name__ == "__main__":
    args = sys.argv[1:]
    busy = int(args[args.index("--busy") + 1]) if "--busy" in args else 0
    if "--busy" in args:
        del args[args.index("--busy") : args.index("--busy") + 2]
    against = Path(args[args.index("--against") + 1]).resolve() if "--against" in args else None
    if "--against" in args:
        del args[args.index("--against") : args.index("--against") + 2]
    with recorded("demo" + (f"_busy{busy}" if busy else "")):
        main(int(args[0]) if args else 1, busy, against)

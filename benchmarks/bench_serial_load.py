"""`armid record` on the simulated Dynamixel rig beside a busy loop pinned to CPU 0: replies lost.

    python benchmarks/bench_serial_load.py [seconds] [rounds]

Each round records the serial rig for ``seconds`` twice, interleaved: as shipped, and with
the chain's counters of the line ignored (``LineProgress.behind`` always False: the driver
as it was before them, the reference). Beside each run, one real-time process pinned to
each CPU sleeps 0.5 ms at a time and notes every wake more than 2 ms after the last: the
machine's own stalls (a host that stops a virtual CPU: nothing inside the machine preempts
it), which no priority of the chain or the driver can get through. Printed per run: lost
cycles per joint, the reply windows given again for the chain, the stalls each CPU saw,
the load average before and after. The reference, in the same run and beside the same busy
loop: a bare pty between two real-time processes, one asking 52 bytes and the other answering
92 (a cycle's bytes) every 2 ms: what the pty alone delays past 8 ms (its kernel worker, of
ordinary priority, carries every byte between its ends). Why this is a benchmark and not a test: the stalls
come from the host and the other tenants of the machine, not from the run.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from figures_json import recorded  # noqa: E402

RIG = ROOT / "config" / "rigs" / "sim_dynamixel.yaml"
CANARY = """
import json, os, sys, time
cpu, seconds, out = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
os.sched_setaffinity(0, {cpu})
try:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(70))
except OSError:
    pass
gaps, last = [], time.monotonic()
end = last + seconds
while last < end:
    time.sleep(0.0005)
    now = time.monotonic()
    if now - last > 0.002:
        gaps.append(now - last)
    last = now
json.dump(gaps, open(out, "w"))
"""
PTY_ECHO = """
import os, select, sys, time, tty
import numpy as np
master, slave = os.openpty()
tty.setraw(slave)
if os.fork() == 0:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(60))
    except OSError:
        pass
    while select.select([master], [], [], 2.0)[0]:
        os.read(master, 4096)
        os.write(master, bytes(92))
    os._exit(0)
try:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))
except OSError:
    pass
trips, end = [], time.monotonic() + float(sys.argv[1])
while time.monotonic() < end:
    t, got = time.perf_counter(), 0
    os.write(slave, bytes(52))
    while got < 92 and select.select([slave], [], [], 1.0)[0]:
        got += len(os.read(slave, 4096))
    trips.append(time.perf_counter() - t)
    time.sleep(0.0015)
ms = 1e3 * np.array(trips)
print(f"{len(ms)} round trips, p50 {np.percentile(ms, 50):.2f} ms, p99.9 {np.percentile(ms, 99.9):.1f} ms, max {ms.max():.1f} ms, "
      f"{(ms > 8).sum()} over 8 ms, {(ms > 32).sum()} over 32 ms")
"""
WITHOUT = "from armid.drivers.line_progress import LineProgress; LineProgress.behind = lambda *a: False; from armid.cli import run; run()"


def record(seconds: float, counters: bool, folder: Path) -> str:
    """One recording beside the pinned busy loop and the canaries: its line of figures."""
    cpus = sorted(os.sched_getaffinity(0))
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"], preexec_fn=lambda: os.sched_setaffinity(0, {cpus[0]}))
    canaries = [subprocess.Popen([sys.executable, "-c", CANARY, str(c), str(seconds + 2), str(folder / f"canary{c}.json")]) for c in cpus]
    try:
        time.sleep(0.3)
        load0 = os.getloadavg()[0]
        entry = ["-c", "from armid.cli import run; run()"] if counters else ["-c", WITHOUT]
        out = subprocess.run([sys.executable, *entry, "record", "--rig", str(RIG), "--duration", str(seconds), "--no-zenoh",
                              "--out", str(folder / ("with" if counters else "without"))], capture_output=True, text=True, timeout=seconds + 120)
        load1 = os.getloadavg()[0]
    finally:
        busy.kill()
        busy.wait()
        for c in canaries:
            c.wait()
    lost = re.search(r"(\d+) records, .*lost cycles per joint (\[[^\]]*\])", out.stderr)
    waits = re.search(r"(\d+) reply windows given again", out.stderr)
    stalls = []
    for c in cpus:
        gaps = json.loads((folder / f"canary{c}.json").read_text())
        stalls.append(f"CPU {c}: {len(gaps)} stalls > 2 ms, longest {1e3 * max(gaps, default=0):.1f} ms")
    return (f"{'as shipped' if counters else 'counters ignored'}: "
            + (f"{lost.group(1)} cycles, lost per joint {lost.group(2)}" if lost else f"no summary (exit {out.returncode})")
            + f", {waits.group(1) if waits else 0} windows given again; {'; '.join(stalls)}; load average {load0:.1f} -> {load1:.1f}")


def pty_reference(seconds: float) -> str:
    """The bare pty's round trips beside the pinned busy loop (the reference)."""
    cpus = sorted(os.sched_getaffinity(0))
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"], preexec_fn=lambda: os.sched_setaffinity(0, {cpus[0]}))
    try:
        load0 = os.getloadavg()[0]
        out = subprocess.run([sys.executable, "-c", PTY_ECHO, str(seconds)], capture_output=True, text=True, timeout=seconds + 60)
        load1 = os.getloadavg()[0]
    finally:
        busy.kill()
        busy.wait()
    return f"{out.stdout.strip() or out.stderr.strip()[-200:]}; load average {load0:.1f} -> {load1:.1f}"


def main(seconds: float, rounds: int) -> None:
    print(f"armid record --rig {RIG.relative_to(ROOT)} --duration {seconds:g} --no-zenoh, a busy loop pinned to CPU 0, "
          f"{os.cpu_count()} CPUs", flush=True)
    for r in range(rounds):
        print(f"round {r + 1}, the bare pty (reference): {pty_reference(seconds / 3)}", flush=True)
        for counters in (False, True):
            with tempfile.TemporaryDirectory() as tmp:
                print(f"round {r + 1}, {record(seconds, counters, Path(tmp))}", flush=True)


if __name__ == "__main__":
    args = sys.argv[1:]
    with recorded("serial_load"):
        main(float(args[0]) if args else 30.0, int(args[1]) if len(args) > 1 else 2)

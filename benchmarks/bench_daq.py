"""Acquisition to a Zenoh subscriber in another process: latency, CPU per cycle, shortest period.

    python benchmarks/bench_daq.py [seconds] [period_ms ...]

The simulated arm runs as ``armid sim`` in its own process on ``udp_multicast`` (drives are
separate hardware); this process runs the CANopen driver, the acquisition, the MCAP
recorder, the raw CAN log and the Zenoh stream (what ``armid record`` runs); a subscriber
in a third process stamps each record on arrival. Latency = arrival (wall clock) minus
the record's SYNC time, after the first second (start-up). CPU per cycle is this process's CPU time over the cycles. For
periods below 2 ms the rig's bitrate is raised to 8 Mbit/s so that the bus budget (a
physical limit of a 1 Mbit/s bus, see drivers/pdo_plan.py) does not decide: what is
measured is what this machine sustains.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}

from figures_json import recorded  # noqa: E402

from armid.daq.acquisition import Acquisition, Sink  # noqa: E402
from armid.daq.canlog import BusLog  # noqa: E402
from armid.daq.recorder import McapRecorder  # noqa: E402
from armid.daq.stream import Stream, session_config  # noqa: E402
from armid.drivers.canopen_driver import CanopenDriver  # noqa: E402
from armid.io.rig_file import load_rig  # noqa: E402

RIG = ROOT / "config" / "rigs" / "sim.yaml"


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def run(seconds: float, period_s: float) -> dict[str, float]:
    import dataclasses

    import zenoh

    group = f"239.74.{np.random.default_rng().integers(1, 250)}.{np.random.default_rng().integers(1, 250)}"
    rig = load_rig(RIG).with_bus(interface="udp_multicast", channel=group)
    rig = dataclasses.replace(rig, period_s=period_s)
    if period_s < 0.002:
        rig = rig.with_bus(bitrate=8_000_000)
    tmp = Path(tempfile.mkdtemp())
    rig_file = tmp / "rig.yaml"
    import yaml

    doc = yaml.safe_load(RIG.read_text())
    doc["robot"] = str((RIG.parent / doc["robot"]).resolve())
    doc["period_s"] = period_s
    doc["bus"].update({"interface": "udp_multicast", "channel": group, "bitrate": rig.bus.bitrate})
    rig_file.write_text(yaml.safe_dump(doc))
    ready = tmp / "ready"
    sim = subprocess.Popen([sys.executable, "-m", "armid.cli", "sim", "--rig", str(rig_file), "--ready", str(ready)], cwd=ROOT, env=ENV,
                           stderr=subprocess.DEVNULL)
    endpoint = f"tcp/127.0.0.1:{_port()}"
    sub = subprocess.Popen([sys.executable, str(ROOT / "tests/helpers/latency_subscriber.py"), rig.robot.name, endpoint, str(tmp / "lat.txt"),
                            str(seconds + 30)], env=ENV, stdout=subprocess.PIPE, text=True)
    assert sub.stdout is not None and sub.stdout.readline().strip() == "ready"
    for _ in range(200):
        if ready.exists():
            break
        time.sleep(0.05)
    driver = CanopenDriver(rig)
    session = zenoh.open(session_config(connect=[endpoint]))
    try:
        driver.start()
        recorder = McapRecorder(tmp / "run.mcap", [j.name for j in rig.robot.joints], {"robot": rig.robot.name})
        log = BusLog(driver, tmp / "can.log")
        stream = Stream(session, rig.robot.name, "bench", lambda: {})
        acq = Acquisition(driver, [Sink("recorder", recorder.write, bounded=False), Sink("zenoh", stream.publish, capacity=5000)])
        cpu0, t0 = time.process_time(), time.monotonic()
        acq.start()
        time.sleep(seconds)
        acq.stop()
        cpu = time.process_time() - cpu0
        wall = time.monotonic() - t0
        recorder.close()
        log.stop()
        stream.close()
    finally:
        driver.close()
        session.close()
        time.sleep(1.0)
        sub.send_signal(signal.SIGTERM)
        sub.wait(30)
        sim.terminate()
        sim.wait(10)
    rows = np.loadtxt(tmp / "lat.txt", ndmin=2)
    seq, lat = rows[:, 0].astype(int), rows[:, 1]
    lat = lat[seq >= int(1.0 / period_s)]  # the first second is warm-up (start-up backlog)
    n = acq.sequence
    return {"period_ms": 1000 * period_s, "records": n, "received": len(seq), "gaps": int(np.sum(np.diff(seq) != 1)),
            "lost_cycles": int(driver.lost_cycles.sum()), "invalid": int(acq.invalid.sum()),
            "p50_ms": 1000 * float(np.percentile(lat, 50)), "p99_ms": 1000 * float(np.percentile(lat, 99)), "max_ms": 1000 * float(lat.max()),
            "cpu_per_cycle_ms": 1000 * cpu / max(n, 1), "cycles_per_s": n / wall}


def main() -> None:
    seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 30.0
    periods = [float(x) / 1000 for x in sys.argv[2:]] or [0.002, 0.0015, 0.001]
    for p in periods:
        r = run(seconds, p)
        ok = r["gaps"] == 0 and r["lost_cycles"] == 0 and r["received"] == r["records"]
        print(f"{r['period_ms']:.2f} ms: {r['records']} records, {r['received']} received, gaps {r['gaps']}, lost cycles {r['lost_cycles']}, "
              f"latency p50 {r['p50_ms']:.2f} / p99 {r['p99_ms']:.2f} / max {r['max_ms']:.1f} ms, CPU {r['cpu_per_cycle_ms']:.2f} ms per cycle "
              f"({'no loss' if ok else 'LOSS'})", flush=True)


if __name__ == "__main__":
    with recorded("daq"):
        main()

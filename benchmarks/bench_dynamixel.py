"""Dynamixel chain over a pseudo-terminal, 6 servos: achieved cycle period, its jitter, round trip.

    python benchmarks/bench_dynamixel.py [seconds] [period_ms ...]

The simulated chain (sim_bus.servo_chain) runs in its own process and answers with the
line's timing at 4 Mbaud; the driver cycles Sync Write of Goal Current plus Fast Sync Read
of the present values and holds the arm with PD plus gravity feed-forward. Reported per
period: cycles, the achieved period (mean, std, p99, max: from the reply completion
stamps), lost replies, the read's round trip (request sent to reply complete) and, as the
reference measured in the same process, the round trip of the same bytes echoed back by a
bare pty loop: the ratio is what the protocol, the chain's line timing and the driver add.
"""

from __future__ import annotations

import os
import select
import sys
import threading
import time
import tty
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from figures_json import recorded  # noqa: E402

from armid.chain_process import ServoChainProcess  # noqa: E402
from armid.drivers import dynamixel_protocol as dxl  # noqa: E402
from armid.drivers.dynamixel_driver import DynamixelDriver  # noqa: E402
from armid.identify.control import ComputedTorque  # noqa: E402
from armid.io.rig_file import load_rig  # noqa: E402

RIG = ROOT / "config" / "rigs" / "sim_dynamixel.yaml"


def pty_echo_round_trip(request: bytes, reply_size: int, n: int = 2000) -> np.ndarray:
    """The floor: a thread echoes ``reply_size`` bytes for each request over a bare pty."""
    master, slave = os.openpty()
    tty.setraw(slave)
    reply = bytes(reply_size)

    def echo() -> None:
        while True:
            ready, _, _ = select.select([master], [], [], 1.0)
            if not ready:
                return
            try:
                os.read(master, 4096)
                os.write(master, reply)
            except OSError:
                return

    threading.Thread(target=echo, daemon=True).start()
    out = []
    for _ in range(n):
        t = time.perf_counter()
        os.write(slave, request)
        got = 0
        while got < reply_size:
            select.select([slave], [], [], 0.1)
            got += len(os.read(slave, 4096))
        out.append(time.perf_counter() - t)
        time.sleep(0.001)
    os.close(slave)
    os.close(master)
    return np.array(out)


def run(seconds: float, period_s: float) -> dict[str, float]:
    rig = replace(load_rig(RIG), period_s=period_s)
    with ServoChainProcess(str(RIG)) as chain:
        driver = DynamixelDriver(rig, port=chain.port)
        driver.start()
        control = ComputedTorque(rig.robot, kp=np.full(6, 4.0), kd=np.full(6, 0.15))
        try:
            s = driver.read(1.0)
            q0 = s.position.copy()
            driver.enable()
            driver.reply_times.clear()
            driver.round_trips.clear()
            lost0 = driver.lost_cycles.copy()
            cpu0, t0 = time.process_time(), time.perf_counter()
            cycles = 0
            while time.perf_counter() - t0 < seconds:
                s = driver.read(1.0)
                z = np.zeros(6)
                driver.command_torque(control(s.position, s.velocity, q0, z, z))
                cycles += 1
            cpu = time.process_time() - cpu0
            lost = int((driver.lost_cycles - lost0).max())
        finally:
            driver.disable()
            driver.close()
    period = np.diff(np.array(driver.reply_times))
    trip = np.array(driver.round_trips)
    return {"cycles": cycles, "period_ms": 1e3 * period.mean(), "std_ms": 1e3 * period.std(), "p99_ms": 1e3 * np.percentile(period, 99),
            "max_ms": 1e3 * period.max(), "lost": lost, "late": driver.late_cycles, "trip_p50_ms": 1e3 * np.median(trip),
            "trip_p99_ms": 1e3 * np.percentile(trip, 99), "cpu_ms_per_cycle": 1e3 * cpu / max(cycles, 1)}


def main() -> None:
    seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 10.0
    periods = [float(p) / 1000 for p in sys.argv[2:]] or [0.002, 0.0015, 0.001]
    ids = list(range(1, 7))
    floor = pty_echo_round_trip(dxl.sync_read(ids, *dxl.PRESENT_BLOCK), dxl.fast_sync_read_size(6, dxl.PRESENT_BLOCK[1]))
    budget = dxl.cycle_budget(6, 4_000_000, 0.002, 0, 0.0)
    print(f"reference: bare pty echo of a Fast Sync Read, round trip p50 {1e3 * np.median(floor):.3f} ms; "
          f"the line itself at 4 Mbaud: {1e3 * budget.reply_s:.3f} ms from request end to reply end")
    for period in periods:
        try:
            r = run(seconds, period)
        except dxl.SerialBudgetError as err:
            print(f"period {1e3 * period:g} ms: refused: {err}", flush=True)
            continue
        print(f"period {1e3 * period:g} ms: {r['cycles']} cycles, achieved {r['period_ms']:.3f} ms, jitter std {r['std_ms']:.3f} ms, "
              f"p99 {r['p99_ms']:.3f}, max {r['max_ms']:.1f} ms; lost replies {r['lost']}, late cycles {r['late']}; "
              f"round trip p50 {r['trip_p50_ms']:.3f} ms ({r['trip_p50_ms'] / (1e3 * np.median(floor)):.1f}x the bare pty), "
              f"p99 {r['trip_p99_ms']:.3f} ms; CPU {r['cpu_ms_per_cycle']:.3f} ms per cycle", flush=True)


if __name__ == "__main__":
    with recorded("dynamixel"):
        main()

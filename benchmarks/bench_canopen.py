"""CANopen acquisition at 2 ms with 6 axes: lost cycles, cycle period p50/p99/max, CPU per cycle.

    python benchmarks/bench_canopen.py [seconds] [virtual|udp_multicast ...] [--busy N]

``virtual``: simulated arm and driver in this process, SYNC paced by the consumer as
``armid.simulated`` runs it (co-simulation: the arm's time is SYNC count x period, and the
real-time factor says how fast the wall clock let it run). ``udp_multicast``: the arm runs as
``armid sim`` in another process, on the master's SYNC. The period is measured from the
samples' SYNC times over UDP, and from when each sample was read when paced (a listening bus
instance would unpack every frame again and load the process it measures); CPU per cycle is
this process's CPU time over the cycles (for ``virtual`` it includes the simulated arm).
``--busy N``: N processes each keeping a core busy beside the run (a lab PC's load), killed
by id after it.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import can
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from figures_json import recorded  # noqa: E402

from armid.daq.excite import LOOP_BANDWIDTH_HZ  # noqa: E402
from armid.drivers.canopen_driver import CanopenDriver  # noqa: E402
from armid.identify.control import ComputedTorque  # noqa: E402
from armid.io.rig_file import load_rig  # noqa: E402
from armid.sim_bus.arm import SimulatedArm  # noqa: E402

RIG = ROOT / "config" / "rigs" / "sim.yaml"


def run(interface: str, seconds: float) -> str:
    channel = f"armid-bench-{uuid.uuid4().hex[:6]}" if interface == "virtual" else f"239.74.{np.random.randint(1, 250)}.{np.random.randint(1, 250)}"
    rig = load_rig(RIG).with_bus(interface=interface, channel=channel)
    arm = proc = None
    tmp = tempfile.TemporaryDirectory()
    if interface == "virtual":
        arm = SimulatedArm(rig, bus=can.Bus(interface="virtual", channel=channel))
    else:
        ready = Path(tmp.name) / "ready"
        proc = subprocess.Popen([sys.executable, "-m", "armid.cli", "sim", "--rig", str(RIG), "--interface", interface,
                                 "--channel", channel, "--ready", str(ready)], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
        while not ready.exists():
            time.sleep(0.05)
    driver = CanopenDriver(rig)
    # the bus's own timing, as a real arm would meet it (not co-simulated); the arm in this process paces by its consumer
    driver.pacing = "consumer" if interface == "virtual" else "clock"
    sync_times: list[float] = []
    try:
        driver.start()
        q_ref = np.asarray(rig.simulation["initial_position"], float)
        # the excitation session's loop: through the mass matrix, rotor inertias included, 2 Hz
        control = ComputedTorque(rig.robot, q_nominal=q_ref, armature=[d.units.reflected_inertia for d in rig.drives],
                                 bandwidth_hz=LOOP_BANDWIDTH_HZ, decoupled=True)
        z = np.zeros(rig.n_joints)
        import threading

        enabling = threading.Thread(target=driver.enable)
        enabling.start()
        while enabling.is_alive():  # a paced SYNC waits for this consumer
            driver.acknowledge(driver.read(1.0).cycle)
        enabling.join()
        n = int(seconds / rig.period_s)
        cpu0, wall0 = time.process_time(), time.perf_counter()
        invalid = 0
        for _ in range(n):
            s = driver.read(1.0)
            sync_times.append(time.perf_counter() if driver.pacing == "consumer" else s.time_s)  # when its SYNC went out
            invalid += int(not s.valid.all())
            driver.command_torque(control(s.position, s.velocity, q_ref, z, z))
            driver.acknowledge(s.cycle)
        cpu = time.process_time() - cpu0
        wall = time.perf_counter() - wall0
    finally:
        driver.close()
        if arm is not None:
            arm.close()
        if proc is not None:
            proc.terminate()
            proc.wait(10)
        tmp.cleanup()
    periods = np.diff(np.array(sync_times)) * 1e3
    p50, p99 = np.percentile(periods, [50, 99])
    return (
        f"{interface}: {driver.timing_note}; {n} cycles in {wall:.1f} s (real-time factor {n * rig.period_s / wall:.2f}), 6 axes at {rig.period_s * 1e3:g} ms: lost cycles {int(driver.lost_cycles.max())} "
        f"(samples with a missing joint: {invalid}), late frames {int(driver.late_frames.sum())}; SYNC period p50 {p50:.3f} ms, "
        f"p99 {p99:.3f} ms, max {periods.max():.3f} ms; CPU per cycle {cpu / n * 1e3:.3f} ms"
        + (" (driver and simulated arm)" if interface == "virtual" else " (driver only)")
    )


if __name__ == "__main__":
    args = sys.argv[1:]
    busy = int(args[args.index("--busy") + 1]) if "--busy" in args else 0
    if "--busy" in args:
        del args[args.index("--busy"): args.index("--busy") + 2]
    seconds = float(args[0]) if args else 60.0
    loads = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(busy)]
    try:
        with recorded("canopen" + (f"_busy{busy}" if busy else "")):
            for iface in args[1:] or ["virtual", "udp_multicast"]:
                print(run(iface, seconds) + (f"; beside {busy} busy processes" if busy else ""), flush=True)
    finally:
        for p in loads:
            p.kill()
            p.wait()

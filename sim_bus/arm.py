"""The simulated arm on a CAN bus: one :class:`SimulatedDrive` per joint around one physics.

Lock-step with SYNC: each SYNC the arm latches the drives' synchronous RPDOs, asks each
drive for its current, advances the physics one period, and lets every drive send its
TPDOs. Time on the arm is the SYNC count times the period, whatever the wall clock does,
so a run is deterministic for a given seed and command sequence. It is a co-simulation: a
master that is not scheduled pauses the arm instead of faulting its drives
(:meth:`SimulatedDrive.watchdog`), so that a busy host never stops a run in CI; a master that
stops sending SYNC or its heartbeat still faults them. ``log`` keeps the physics' state per
SYNC for tests that compare what the driver read with the truth.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any

import can
import numpy as np

from armid.drivers.interface import ProcessSettings
from armid.drivers.realtime import one_cpu
from armid.drivers.rig import Rig, canopen_network, open_bus
from armid.drivers.udp_filter import drive_frames, drop_own_frames
from armid.identify.robot import Robot

from .drive import SimulatedDrive
from .physics import ArmPhysics, Measurement, simulation_config

WATCH_S = 0.01  # the drives' heartbeat consumer (150 ms by default) and, between SYNCs, producer: checked this often


class StateLog:
    """The physics' state per SYNC in a ring of arrays (no Python object per entry, so the
    garbage collector has nothing to walk while the arm runs)."""

    def __init__(self, size: int, n: int) -> None:
        self.size = size
        self.count = 0
        self.sync = np.zeros(size, np.int64)
        self.counter = np.zeros(size, np.int64)
        self.time_s = np.zeros(size)
        self.position = np.zeros((size, n))
        self.velocity = np.zeros((size, n))
        self.current = np.zeros((size, n))
        self.true_position = np.zeros((size, n))

    def append(self, sync: int, counter: int | None, m: Measurement) -> None:
        k = self.count % self.size
        self.sync[k], self.counter[k], self.time_s[k] = sync, -1 if counter is None else counter, m.time_s
        self.position[k], self.velocity[k], self.current[k], self.true_position[k] = m.position, m.velocity, m.current, m.true_position
        self.count += 1

    def arrays(self) -> dict[str, np.ndarray]:
        """Oldest first."""
        n = min(self.count, self.size)
        order = (np.arange(n) + (self.count - n)) % self.size
        return {k: getattr(self, k)[order] for k in ("sync", "counter", "time_s", "position", "velocity", "current", "true_position")}


class SimulatedArm:
    """Run the rig's arm on ``bus`` (or on a bus opened from the rig) until :meth:`close`."""

    def __init__(self, rig: Rig[Robot], bus: can.BusABC | None = None, seed: int | None = None, log_size: int = 200_000,
                 own_process: bool = False) -> None:
        """``own_process``: the arm is alone in its process (``armid sim``), standing in for
        drives with processors of their own: its threads run above the master's, on one CPU
        (:func:`~drivers.realtime.one_cpu`: its frames leave in order)."""
        self.rig = rig
        self.cpu = one_cpu() if own_process else None
        self._settings = ProcessSettings()  # put back by close()
        sim = dict(rig.simulation)
        self.seed = int(sim.get("seed", 0) if seed is None else seed)
        self.config = simulation_config(sim, rig.n_joints, f"{rig.source}: simulation")
        self.physics = ArmPhysics(rig.robot, self.config, rig.period_s, self.seed)
        self._own_bus = bus is None
        self.bus = bus if bus is not None else open_bus(**rig.bus.kwargs())
        if self._own_bus:  # udp_multicast loops every frame back to its sender
            drop_own_frames(self.bus, drive_frames(d.node_id for d in rig.drives))
        # a thread waiting for the GIL waits up to the switch interval (5 ms by default):
        # more than two cycles. A 2 ms loop needs the interpreter to switch ten times faster.
        self._settings.fast_switching(rig.period_s)
        self.timing = self._settings.realtime(own_process)  # before the notifier's thread starts: it inherits the policy
        self.network = canopen_network(self.bus)
        sync_timeout = float(sim.get("sync_timeout_s", 0.1))
        self.drives = [SimulatedDrive(d.node_id, d.joint, d.units, self.network, sync_timeout) for d in rig.drives]
        self.step_seconds: deque[float] = deque(maxlen=100_000)  # before the first SYNC can come
        self.network.subscribe(0x80, self._on_sync)
        self.network.subscribe(0x700 + rig.master_node_id, self._on_master_heartbeat)
        self.log = StateLog(log_size, rig.n_joints)
        self.syncs = 0
        self._stop = threading.Event()
        self._watchdog = threading.Thread(target=self._watch, name="armid-sim-watchdog", daemon=True)
        self._settings.freeze()  # see CanopenDriver.start: keep full collections short while running
        self._watchdog.start()

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        start = time.perf_counter()
        counter = data[0] if len(data) >= 1 else None
        for d in self.drives:
            d.latch()
        p, v = self.physics.position, self.physics.velocity
        demand = np.array([d.current_demand(p[d.joint], v[d.joint]) for d in self.drives])
        braked = np.array([not d.powered for d in self.drives])
        m = self.physics.step(demand, braked)
        self.syncs += 1
        self.log.append(self.syncs, counter, m)
        now = time.monotonic()
        for d in self.drives:
            d.heartbeat(now)
            d.on_sync(counter, m, timestamp)
        self.step_seconds.append(time.perf_counter() - start)

    def _on_master_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        for d in self.drives:
            d.on_master_heartbeat(can_id - 0x700, timestamp)

    def _watch(self) -> None:
        while not self._stop.wait(WATCH_S):
            now = time.monotonic()
            for d in self.drives:
                d.heartbeat(now)
                d.watchdog(now)

    def drive(self, joint: int) -> SimulatedDrive:
        return self.drives[joint]

    def status(self) -> dict[str, Any]:
        return {
            "syncs": self.syncs,
            "time_s": self.physics.time_s,
            "states": [d.state.name for d in self.drives],
            "nmt": [d.node.nmt.state for d in self.drives],
            "position": self.physics.position.tolist(),
        }

    def close(self) -> None:
        self._settings.restore()
        self._stop.set()
        self._watchdog.join(timeout=1.0)
        for d in self.drives:
            d.node.nmt.stop_heartbeat()
        if self._own_bus:
            self.network.disconnect()
        elif self.network.notifier is not None:
            self.network.notifier.stop(0.5)

    def __enter__(self) -> SimulatedArm:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

"""One simulated CiA 402 servo drive on ``canopen.LocalNode`` (CiA 301 + CiA 402).

What a master sees is what a real drive shows: NMT with boot-up, an SDO server over the
shipped EDS (``config/drives/armid_cia402.eds``), a heartbeat producer (0x1017, sent by the
thread that answers SYNC, and between SYNCs by the arm's watch thread: see :meth:`heartbeat`), a
heartbeat consumer of the master (0x1016), TPDOs sent on SYNC with the mapping the master
wrote (0x1800/0x1A00, transmission types 1-240), synchronous RPDOs applied at the next SYNC
(0x1400/0x1600), the CiA 402 state machine driven by the controlword, cyclic synchronous
torque (10) and position (8) modes, drive-side limits (0x6072 max torque, 0x607D software
position limits, 0x6080 max speed) and EMCY frames on faults.

Units (see the EDS header): position in encoder increments at the motor, velocity in
increments/s, torque and current in per mille of the motor's rated torque and current.
"""

from __future__ import annotations

import struct
import time
from enum import Enum
from typing import TYPE_CHECKING

import canopen
import numpy as np
from canopen.objectdictionary import ODVariable

from armid.drivers.interface import bus_time
from armid.drivers.rig import DriveUnits, current_of, permille_of
from armid.resources import config_file

if TYPE_CHECKING:
    from .physics import Measurement

EDS = config_file("drives/armid_cia402.eds")  # package data (armid.config)

MODE_CSP = 8
MODE_CST = 10

# EMCY codes the simulated drive raises (CiA 301 / CiA 402)
EMCY_HEARTBEAT = 0x8130  # life guard or heartbeat error
EMCY_SYNC_LOST = 0x8100  # communication, generic (manufacturer data: b"SYNC")
EMCY_PDO_LENGTH = 0x8210  # PDO not processed due to length error
EMCY_POSITION_LIMIT = 0x8612  # reference limit
EMCY_VELOCITY_LIMIT = 0x8400  # velocity speed controller

NMT_STATE_CODES = {name: code for code, name in canopen.nmt.NMT_STATES.items()}  # what a heartbeat carries


PRODUCT_CODE = 0x41524D53  # 0x1018:2, identity ("ARMS"): the recording's metadata names the drive; a master paces by its rig's setting

class State(Enum):
    NOT_READY_TO_SWITCH_ON = 0x0000
    SWITCH_ON_DISABLED = 0x0040
    READY_TO_SWITCH_ON = 0x0021
    SWITCHED_ON = 0x0023
    OPERATION_ENABLED = 0x0027
    QUICK_STOP_ACTIVE = 0x0007
    FAULT_REACTION_ACTIVE = 0x000F
    FAULT = 0x0008


STATUS_REMOTE = 0x0200
STATUS_INTERNAL_LIMIT = 0x0800
POWERED = (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE)


def next_state(state: State, controlword: int, previous_controlword: int) -> State:
    """The CiA 402 device control state machine (transitions 2-12, 15, 16)."""
    if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
        if state == State.FAULT and controlword & 0x80 and not previous_controlword & 0x80:
            return State.SWITCH_ON_DISABLED  # 15: fault reset on the rising edge of bit 7
        return state
    if controlword & 0x80:
        return state
    disable_voltage = (controlword & 0x02) == 0
    quick_stop = (controlword & 0x06) == 0x02
    shutdown = (controlword & 0x07) == 0x06
    switch_on = (controlword & 0x0F) == 0x07
    enable = (controlword & 0x0F) == 0x0F
    if state == State.QUICK_STOP_ACTIVE:
        return State.SWITCH_ON_DISABLED if disable_voltage else state
    if disable_voltage:
        return State.SWITCH_ON_DISABLED
    if quick_stop:
        return State.QUICK_STOP_ACTIVE if state == State.OPERATION_ENABLED else State.SWITCH_ON_DISABLED
    if state == State.SWITCH_ON_DISABLED:
        return State.READY_TO_SWITCH_ON if shutdown else state
    if state == State.READY_TO_SWITCH_ON:
        return State.SWITCHED_ON if (switch_on or enable) else state
    if state == State.SWITCHED_ON:
        return State.READY_TO_SWITCH_ON if shutdown else State.OPERATION_ENABLED if enable else state
    if state == State.OPERATION_ENABLED:
        return State.READY_TO_SWITCH_ON if shutdown else State.SWITCHED_ON if switch_on else state
    return state


_STRUCT = {1: "?", 2: "b", 3: "h", 4: "i", 5: "B", 6: "H", 7: "I"}


class _Pdo:
    """A PDO as mapped in the drive's own object dictionary."""

    def __init__(self, cob_id: int, trans_type: int, entries: list[tuple[int, int]], fmt: str) -> None:
        self.cob_id, self.trans_type, self.entries = cob_id, trans_type, entries
        self.struct = struct.Struct("<" + fmt)


class SimulatedDrive:
    """One joint's CiA 402 drive; :class:`sim_bus.arm.SimulatedArm` calls :meth:`on_sync`."""

    def __init__(self, node_id: int, joint: int, units: DriveUnits, network: canopen.Network, sync_timeout_s: float = 0.0) -> None:
        self.node = canopen.LocalNode(node_id, str(EDS))
        self.id = node_id
        self.joint = joint
        self.units = units
        self.network = network
        self.state = State.NOT_READY_TO_SWITCH_ON
        self.values: dict[tuple[int, int], int] = {}
        self.controlword = 0
        self._previous_controlword = 0
        self._pending: dict[tuple[int, int], int] = {}
        self.tpdos: list[_Pdo] = []
        self.rpdos: list[_Pdo] = []
        self.sync_count = 0
        self.last_sync_stamp = 0.0  # the last SYNC's stamp, as bus_time puts it (its sender's time, on this process's clock)
        self.master_heartbeat: float | None = None
        # co-simulation: each watch needs the other stream as its witness that the master runs
        self.heartbeat_since_sync: float | None = None  # the stamp of the first master heartbeat after the last SYNC
        self.syncs_since_heartbeat = 0
        self.not_following = False
        self.silent = False
        # SYNC is lost after 3 communication cycles (0x1006) or this, whichever is longer
        self.sync_timeout_s = sync_timeout_s
        self.fault_code = 0
        self.internal_limit = False
        self.errors: list[int] = []
        self._raw_cache: dict[tuple[int, int], int] = {}
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)
        self.heartbeat_s = 0.0  # the producer time (0x1017); 0: off
        self._heartbeat_sent = -np.inf  # time.monotonic() of the last heartbeat sent
        # canopen's producer is a periodic-send thread of its own; this drive's is :meth:`heartbeat`
        nmt = self.node.nmt
        nmt.start_heartbeat = self._start_heartbeat  # type: ignore[method-assign]
        nmt.stop_heartbeat = self._stop_heartbeat  # type: ignore[method-assign]
        nmt.update_heartbeat = lambda: None  # type: ignore[method-assign]  # each heartbeat carries the state it is sent in
        self._configure_defaults()
        self.node.associate_network(network)
        network.subscribe(0, self._on_nmt)
        self._boot()

    # --- object dictionary ---
    def _configure_defaults(self) -> None:
        u = self.units
        self.node.data_store.setdefault(0x608F, {})[1] = struct.pack("<I", u.counts_per_rev)
        self.node.data_store[0x608F][2] = struct.pack("<I", 1)
        self.node.data_store.setdefault(0x6091, {})[1] = struct.pack("<I", int(round(u.gear_ratio * 1000)))
        self.node.data_store[0x6091][2] = struct.pack("<I", 1000)
        self.node.data_store.setdefault(0x6075, {})[0] = struct.pack("<I", int(round(u.rated_current_a * 1000)))
        self.node.data_store.setdefault(0x6076, {})[0] = struct.pack("<I", int(round(u.rated_motor_torque_nm * 1000)))
        self.node.data_store.setdefault(0x1018, {})[2] = struct.pack("<I", PRODUCT_CODE)
        self.node.data_store[0x1018][4] = struct.pack("<I", 0x1000 + self.id)

    def _od(self, index: int, subindex: int) -> ODVariable:
        obj = self.node.object_dictionary[index]
        return obj if isinstance(obj, ODVariable) else obj[subindex]

    def _data_type(self, index: int, subindex: int) -> int:
        """The CiA 301 data type of a variable of the EDS (an EDS variable always names one;
        canopen types it optional)."""
        data_type = self._od(index, subindex).data_type
        assert data_type is not None, f"0x{index:04X} sub {subindex}: no data type in the EDS"
        return data_type

    def raw(self, index: int, subindex: int = 0) -> int:
        """A configuration value as the master left it (data store, else EDS default)."""
        key = (index, subindex)
        if key not in self._raw_cache:
            self._raw_cache[key] = self._raw(index, subindex)
        return self._raw_cache[key]

    def _raw(self, index: int, subindex: int) -> int:
        od = self._od(index, subindex)
        data = self.node.data_store.get(index, {}).get(subindex)
        if data is not None:
            return int(od.decode_raw(data))
        return int(od.default if od.default is not None else 0)

    def _on_read(self, index: int, subindex: int, od: ODVariable) -> int | None:
        if index == 0x6041:
            return self.statusword
        if index == 0x6061:
            return self.raw(0x6060)
        if index == 0x603F:
            return self.fault_code
        if index == 0x1001:
            return 0x01 if self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE) else 0
        if index == 0x1003 and subindex > 0:
            return self.errors[-subindex] if subindex <= len(self.errors) else 0
        if index == 0x1003:
            return len(self.errors)
        return self.values.get((index, subindex))

    def _on_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        # called before the store: cache the new value itself, so no reader sees the old one
        self._raw_cache[(index, subindex)] = int(od.decode_raw(data))
        if index == 0x6040:
            self._apply_controlword(int(od.decode_raw(data)))
        elif index == 0x1003 and subindex == 0:
            self.errors.clear()

    @property
    def statusword(self) -> int:
        return self.state.value | STATUS_REMOTE | (STATUS_INTERNAL_LIMIT if self.internal_limit else 0)

    # --- NMT ---
    def _boot(self) -> None:
        self._raw_cache.clear()
        self.state = State.SWITCH_ON_DISABLED
        self.tpdos, self.rpdos = [], []
        self.master_heartbeat = None
        self.node.nmt.send_command(0)  # boot-up message
        self.node.nmt.state = "PRE-OPERATIONAL"

    def _start_heartbeat(self, heartbeat_time_ms: int) -> None:
        self.heartbeat_s = heartbeat_time_ms / 1000.0
        self._heartbeat_sent = -np.inf

    def _stop_heartbeat(self) -> None:
        self.heartbeat_s = 0.0

    def heartbeat(self, now: float) -> None:
        """Send the heartbeat once a producer time has passed since the last one. Called with
        each SYNC by the thread that answers it (before the TPDOs), and between SYNCs by the
        arm's watch thread: a loaded process cannot send TPDOs and starve the heartbeat, as
        canopen's producer (a periodic-send thread per drive) did, and the master lost drives
        that were answering (0.30 s of bus time without a heartbeat, issue 31). Both threads may
        find it due at once and send two: harmless."""
        if self.silent or not self.heartbeat_s or now - self._heartbeat_sent < self.heartbeat_s:
            return
        self._heartbeat_sent = now
        self.network.send_message(0x700 + self.id, bytes([NMT_STATE_CODES[self.node.nmt.state]]))

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.silent or len(data) < 2 or data[1] not in (0, self.id):
            return
        if data[0] in (0x81, 0x82):
            if data[0] == 0x81:
                self.node.data_store.clear()
                self._configure_defaults()
            else:
                for index in [i for i in self.node.data_store if 0x1000 <= i < 0x2000]:
                    del self.node.data_store[index]
            self._boot()
        elif data[0] == 0x01:
            self._load_pdos()

    @property
    def operational(self) -> bool:
        return self.node.nmt.state == "OPERATIONAL"

    def _load_pdos(self) -> None:
        """Read the PDO mapping the master wrote into this drive's dictionary."""
        for pdo in self.rpdos:
            self.network.unsubscribe(pdo.cob_id, self._on_rpdo)
        self.tpdos = self._pdos(0x1800, 0x1A00)
        self.rpdos = self._pdos(0x1400, 0x1600)
        for pdo in self.rpdos:
            self.network.subscribe(pdo.cob_id, self._on_rpdo)

    def _pdos(self, com: int, mapping: int) -> list[_Pdo]:
        out = []
        for k in range(4):
            cob = self.raw(com + k, 1)
            if cob & 0x80000000:
                continue
            entries, fmt = [], ""
            for s in range(1, self.raw(mapping + k, 0) + 1):
                value = self.raw(mapping + k, s)
                index, sub = value >> 16, (value >> 8) & 0xFF
                entries.append((index, sub))
                fmt += _STRUCT[self._data_type(index, sub)]
            out.append(_Pdo(cob & 0x7FF, self.raw(com + k, 2), entries, fmt))
        return out

    # --- PDOs ---
    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.silent or not self.operational:
            return
        for pdo in self.rpdos:
            if pdo.cob_id != can_id:
                continue
            if len(data) != pdo.struct.size:
                self._emcy(EMCY_PDO_LENGTH, f"RPDO 0x{can_id:03X}: {len(data)} bytes, mapping needs {pdo.struct.size}".encode()[:5])
                return
            for key, value in zip(pdo.entries, pdo.struct.unpack(data)):
                self._pending[key] = int(value)

    def on_master_heartbeat(self, node_id: int, timestamp: float) -> None:
        consumer = self.raw(0x1016, 1)
        if consumer >> 16 & 0x7F != node_id:
            return
        self.master_heartbeat = time.monotonic()
        self.syncs_since_heartbeat = 0
        stamp = bus_time(timestamp)
        if self.heartbeat_since_sync is None:
            self.heartbeat_since_sync = stamp
        elif self._sync_lost(stamp, (consumer & 0xFFFF) / 3000.0):
            self.fault(EMCY_SYNC_LOST, b"SYNC")

    def _sync_lost(self, heartbeat_stamp: float, heartbeat_period_s: float) -> bool:
        """SYNC supervision on the bus's own time, co-simulated: SYNC is lost when the master
        sent heartbeats for at least a heartbeat period, and this one more than the SYNC timeout
        after the last SYNC, without a SYNC between them. The senders' stamps, not the time this
        thread reads the frames: a reader that falls behind reads them late but in order; a
        master that was not scheduled sends the heartbeats it owes at once when it resumes
        (python-can's periodic task catching up), then its SYNC."""
        period_s = self.raw(0x1006) / 1e6
        if not (period_s and self.sync_count and self.state in POWERED and self.operational and not self.silent):
            return False
        assert self.heartbeat_since_sync is not None
        timeout = max(3 * period_s, self.sync_timeout_s)
        return (heartbeat_stamp - self.last_sync_stamp > timeout
                and heartbeat_stamp - self.heartbeat_since_sync >= heartbeat_period_s)

    def _apply_controlword(self, controlword: int) -> None:
        self._previous_controlword, self.controlword = self.controlword, controlword
        self.state = next_state(self.state, controlword, self._previous_controlword)

    def watchdog(self, now: float) -> None:
        """Heartbeat consumer, co-simulated; called every few ms by the arm.

        The simulated drive stands in for firmware in a process (and on a host) that may not be
        scheduled: a master that is not running pauses the arm, as a co-simulation's step waits
        for its input, instead of faulting it. So each watch has a witness that the master is
        running: the heartbeat is lost when it stays away for its consumer time on both clocks,
        the wall's and the arm's (SYNCs times the period), while SYNC goes on; SYNC is lost when
        it stays away while the heartbeat goes on (:meth:`_sync_lost`, as each heartbeat comes).
        A master that stops either (a dead SYNC thread, a hung heartbeat task) faults the drive
        as firmware does."""
        if self.silent or not self.operational:
            return
        consumer = self.raw(0x1016, 1)
        limit_s = (consumer & 0xFFFF) / 1000.0
        period_s = self.raw(0x1006) / 1e6
        if (limit_s and self.master_heartbeat is not None and now - self.master_heartbeat > limit_s
                and self.syncs_since_heartbeat * period_s > limit_s):
            self.master_heartbeat = None
            self.fault(EMCY_HEARTBEAT, b"HB")

    def fault(self, code: int, data: bytes = b"") -> None:
        if self.state == State.FAULT:
            return
        self.state = State.FAULT
        self.fault_code = code
        self._emcy(code, data)

    def _emcy(self, code: int, data: bytes) -> None:
        self.errors.append(code)
        self.node.emcy.send(code, 0x01 if self.state == State.FAULT else 0x80, data[:5])

    def current_demand(self, position: float, velocity: float) -> float:
        """Current (A) the drive's power stage asks for this period."""
        if self.silent:
            return 0.0
        u = self.units
        self.internal_limit = False
        if self.state == State.QUICK_STOP_ACTIVE:
            demand = -velocity * 20.0 * u.rated_current_a  # brake to rest on the rated current
        elif self.state != State.OPERATION_ENABLED:
            return 0.0
        elif self.raw(0x6060) == MODE_CSP:
            # the drive's own position loop: rated current at 10 mrad of error or 0.1 rad/s
            target = self.values.get((0x607A, 0), 0) / u.counts_per_rad
            demand = u.rated_current_a * ((target - position) / 0.01 - velocity / 0.1)
        elif self.not_following:
            demand = 0.0  # a broken motor phase: enabled, reporting, producing nothing
        else:  # MODE_CST (and any other mode falls back to torque)
            permille = self.values.get((0x6071, 0), 0)
            demand = permille / 1000.0 * u.rated_motor_torque_nm * u.gear_ratio / u.torque_constant
        limit = current_of(self.raw(0x6072), u.rated_current_a)
        if abs(demand) > limit:
            self.internal_limit = True
            demand = min(max(demand, -limit), limit)
        return float(demand)

    @property
    def powered(self) -> bool:
        """The power stage drives the motor (else the brake holds the joint)."""
        return not self.silent and self.state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE)

    def latch(self) -> None:
        """Apply the synchronous RPDOs received since the last SYNC (CiA 301)."""
        if self.silent or not self.operational:
            return
        pending, self._pending = self._pending, {}
        for key, value in pending.items():
            self.values[key] = value
            if key == (0x6040, 0):
                self._apply_controlword(value)

    def on_sync(self, counter: int | None, m: Measurement, stamp: float) -> None:
        """Update the actual values, check the limits, send the TPDOs due at this SYNC."""
        if self.silent:
            return
        self.sync_count += 1
        self.last_sync_stamp = bus_time(stamp)
        self.heartbeat_since_sync = None
        self.syncs_since_heartbeat += 1
        if not self.operational:
            return
        if self.state == State.QUICK_STOP_ACTIVE and abs(m.velocity[self.joint]) < 1e-3:
            self.state = State.SWITCH_ON_DISABLED  # quick stop option 2: stop, then disable
        u = self.units
        j = self.joint
        pos = min(max(round(float(m.position[j]) * u.counts_per_rad), -(2**31)), 2**31 - 1)
        vel = min(max(round(float(m.velocity[j]) * u.counts_per_rad), -(2**31)), 2**31 - 1)
        cur = int(permille_of(m.current[j], u.rated_current_a))
        self.values.update({(0x6064, 0): pos, (0x606C, 0): vel, (0x6078, 0): cur, (0x6077, 0): cur,
                            (0x6061, 0): self.raw(0x6060)})
        if self.state in POWERED:
            lo, hi = self.raw(0x607D, 1), self.raw(0x607D, 2)
            if not lo <= pos <= hi:
                self.fault(EMCY_POSITION_LIMIT, struct.pack("<i", pos)[:4])
            elif abs(vel) > self.raw(0x6080):
                self.fault(EMCY_VELOCITY_LIMIT, struct.pack("<i", vel)[:4])
        self.values[(0x6041, 0)] = self.statusword
        for pdo in self.tpdos:
            count = counter if counter is not None else self.sync_count
            if 1 <= pdo.trans_type <= 240 and count % pdo.trans_type == 0:
                payload = pdo.struct.pack(*[self._value(k) for k in pdo.entries])
                self.network.send_message(pdo.cob_id, payload)

    def _value(self, key: tuple[int, int]) -> int:
        if key == (0x6041, 0):
            return self.statusword
        value = self.values.get(key)
        return self.raw(*key) if value is None else value

    def stop_following(self) -> None:
        """Fault injection: stay enabled and keep reporting, but produce no torque."""
        self.not_following = True

    def go_silent(self) -> None:
        """Stop answering anything, heartbeat included (a drive that lost power)."""
        self.silent = True
        self.node.nmt.stop_heartbeat()
        self.network.unsubscribe(self.node.sdo.rx_cobid)

"""CiA 402 servo drives over CANopen (python-can + canopen), behind :class:`Driver`.

Start-up, per drive, over SDO: heartbeat producer (0x1017) and consumer of the master
(0x1016), SYNC COB-ID and cycle period (0x1005, 0x1006), mode of operation (0x6060), the
PDO mapping of the rig's plan (:mod:`drivers.pdo_plan`), written and then read back and
compared, and the motor data (encoder 0x608F, gear 0x6091, rated current 0x6075) read
back and compared with the rig. Then NMT start, the master's heartbeat, and SYNC with a
counter: a sequence of 240 frames that the kernel's broadcast manager cycles on socketcan
(each echoed SYNC opens its cycle at its kernel time stamp), a thread otherwise. The master's
heartbeat goes out the same way: from the kernel on socketcan, else from the SYNC thread every
few cycles, so that a loaded process cannot starve one of the two and not the other.

Each cycle's record is keyed by the SYNC counter: a TPDO belongs to the oldest open cycle
that still waits for it and whose SYNC went out before the frame (a drive answers SYNCs in
order, and cannot answer one not yet sent), unless a lost frame shows in the order
(:meth:`CanopenDriver._cycle_answered`). A record goes out as soon as every expected
frame is in, or three periods after its SYNC with the missing joints marked invalid.

A drive's heartbeat is lost when frames read from the bus are stamped more than three
heartbeat periods after its last one: judged on bus time, up to what this process has read,
so a reader thread that runs late (a loaded machine) is not mistaken for a silent drive.
"""

from __future__ import annotations

import functools
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import can
import canopen
import numpy as np
from canopen.sdo import SdoAbortedError, SdoCommunicationError, SdoVariable

from armid.schema import Array, Sample
from armid.schema.errors import DriveConfigError, DriveFault, DriverTimeout, HeartbeatLost, NotOperational

from ..resources import config_file
from .cia_codes import NMT_OPERATIONAL, NMT_STATES, OPERATION_ENABLED, PDO_FORMATS, STATE_MASK, emcy_meaning, is_signed
from .interface import CycleClock, CycleHeartbeat, Driver, bus_time
from .pdo_plan import PLANS, PdoSpec, check_bus_budget
from .realtime import silent_for, stall_sentence
from .rig import Rig, canopen_network, current_of, open_bus, permille_of
from .udp_filter import drop_own_frames, master_frames

EDS = str(config_file("drives/armid_cia402.eds"))  # package data (armid.config)

SYNC_COUNTER_OVERFLOW = 240
SYNC_COB_ID = 0x80
CONTROLWORD_REFRESH = 25
PACE_WAIT_S = 0.05
STALL_S = 0.05  # a watchdog call this late means this process (not the bus) was stalled
STALL_WAIT_S = 10.0  # co-simulation: how long a read waits on through stalls of this process
BUS_SILENT_S = 1.0  # nothing at all read from the bus for this long: every drive is lost (or this process's reader is)
TARGET_POSITION = (0x607A, 0, 32)
EMCY_BYTES = 8  # CiA 301: error code (2), error register (1), manufacturer data (5)
EMCY_KEPT = 100  # canopen keeps every EMCY it decodes: a storm would grow its lists without end

@dataclass
class _Tpdo:
    joint: int
    number: int
    every: int
    unpack: struct.Struct
    fields: list[tuple[int, int]]


@dataclass
class _Cycle:
    cycle: int
    counter: int
    time_s: float
    sample: Sample
    expected: set[tuple[int, int]] = field(default_factory=set)
    written: set[tuple[int, int]] = field(default_factory=set)  # (joint, object index) this cycle's frames carried


_FIELDS = (("position", 0x6064), ("velocity", 0x606C), ("measured_current", 0x6078), ("status", 0x6041))  # (sample field, the drive object it comes from)


class CanopenDriver(Driver):
    """The rig's CiA 402 drives. ``bus`` may be given (tests); else it is opened from the rig."""

    def __init__(self, rig: Rig, bus: can.BusABC | None = None, deadline_periods: float = 3.0) -> None:
        super().__init__(rig)
        self.deadline_periods = deadline_periods
        self.plan: tuple[PdoSpec, ...] = PLANS[rig.pdo_plan]
        self._bus = bus
        self._own_bus = bus is None
        self.network: canopen.Network | None = None
        self.nodes: list[canopen.RemoteNode] = []
        self._tpdo: dict[int, _Tpdo] = {}
        self._lock = threading.Lock()
        self._open: list[_Cycle] = []
        self._last = Sample.empty(0, 0.0, self.n_joints)
        self._paced_s = 0.0  # time the SYNC loop waited for the consumer since the last watchdog call
        self._listen_only = False
        self._t0: float | None = None
        self._ack = threading.Condition()
        self._acknowledged = 0
        self.consumer_late = 0
        self.drives_late = 0  # SYNCs sent before the previous cycle's frames were in (pacing: drives)
        self._target = np.zeros(self.n_joints, np.int64)  # per mille of rated torque
        self._target_position = np.zeros(self.n_joints, np.int64)
        self._position_mode = False
        self._controlword = np.zeros(self.n_joints, np.int64)
        self._sent_controlword = np.full(self.n_joints, -1, np.int64)
        self._heartbeat = np.zeros(self.n_joints)  # bus time (drivers.interface.bus_time) of each drive's last heartbeat
        self._newest_stamp = 0.0  # bus time of the newest frame read, from any node
        self._last_read = time.monotonic()  # when the reader last read a frame
        self._last_watch = time.monotonic()
        self.unscheduled_s = 0.0  # s this process was not scheduled (stalls over STALL_S)
        self.last_sync_sent = time.monotonic()  # when the SYNC thread last sent one
        self.longest_sync_gap = 0.0  # s between two SYNCs the thread sent, the longest since start
        self._nmt = np.full(self.n_joints, -1, np.int64)  # each drive's NMT state as its heartbeat says
        self._not_operational = np.zeros(self.n_joints, bool)  # was operational, reports another state
        self._nmt_supervised = False  # from NMT start all on: before, the drives are sent to pre-operational on purpose
        self._hb_task: can.broadcastmanager.CyclicSendTaskABC | CycleHeartbeat | None = None
        self._bcm_task: can.broadcastmanager.CyclicSendTaskABC | None = None
        self.late_frames = np.zeros(self.n_joints, np.int64)
        self._taken_late: dict[tuple[int, int], float] = {}  # (joint, TPDO): bus time of its last frame, given to a cycle with a later one waiting
        self.error_frames = 0
        self.foreign_syncs = 0  # SYNC frames seen that this master did not send (a second SYNC producer)
        self._foreign_sync_last = 0.0
        self._sync_producer = False  # this master sends SYNC (not a listener)
        self._clock = CycleClock(rig.period_s)
        self._node_ids = {d.node_id: d.joint for d in rig.drives}
        # called under the decoding lock with each SYNC as its cycle opens (stamped with the
        # cycle's time) and each TPDO before it is decoded: frames written from it, in this
        # order, replay into the same records (daq.canlog)
        self.decoded_frames: Callable[[can.Message], None] | None = None
        # a frame's stamp as bus time (:func:`bus_time`, on this process's clock); a replayed
        # log's own stamps are its bus time (daq.canlog.replay_log: a log from a machine whose
        # clock ran ahead of this one's would otherwise read as frames from now)
        self.frame_time: Callable[[float], float] = bus_time

    @property
    def decoded_cob_ids(self) -> set[int]:
        """The frames the records come from: SYNC and the mapped TPDOs (``decoded_frames``)."""
        return {SYNC_COB_ID, *self._tpdo}

    @property
    def bus(self) -> can.BusABC:
        """The bus the driver talks on (opened by :meth:`start` unless one was passed in)."""
        assert self._bus is not None, "the driver is not started"
        return self._bus

    @property
    def sync_late(self) -> int:
        """SYNCs sent more than a period late (the schedule restarted)."""
        return self._clock.late

    # --- start-up ---
    def _start(self) -> None:
        r = self.rig
        # a thread waiting for the GIL waits up to the switch interval (5 ms by default):
        # more than two cycles. A 2 ms loop needs the interpreter to switch ten times faster.
        self._settings.fast_switching(self.period_s)  # put back by close()
        timing = self._settings.realtime()  # before the notifier's and SYNC's threads start: they inherit it
        check_bus_budget(r.pdo_plan, r.n_joints, r.period_s, r.bus.bitrate, r.heartbeat_ms)
        if self._bus is None:
            kwargs = r.bus.kwargs()
            if r.bus.interface == "socketcan":
                kwargs["receive_own_messages"] = True
            self._bus = open_bus(**kwargs)
            drop_own_frames(self._bus, master_frames(self._node_ids, r.master_node_id))  # udp_multicast loops them back
        self.network = canopen_network(self._bus)
        assert self.network.notifier is not None
        self.network.notifier.add_listener(_Watcher(self))
        for d in r.drives:
            node = canopen.RemoteNode(d.node_id, EDS)
            self.network.add_node(node)
            node.sdo.RESPONSE_TIMEOUT = 0.5
            node.emcy.add_callback(functools.partial(self._on_emcy, d.joint, d.node_id))
            # canopen's own decoding of EMCY raises on a frame of another length (a bare
            # "unpack requires a buffer of 8 bytes" line from its listener): checked first here
            self.network.unsubscribe(0x80 + d.node_id, node.emcy.on_emcy)
            self.network.subscribe(0x80 + d.node_id, functools.partial(self._on_emcy_frame, d.joint, node))
            self.network.subscribe(0x700 + d.node_id, self._on_heartbeat)
            self.nodes.append(node)
        self.network.send_message(0, bytes([0x80, 0]))  # all nodes to pre-operational
        for d, node in zip(r.drives, self.nodes):
            self.drive_configuration.append(self._configure(d.joint, node))
        if self.pacing == "drives" and r.bus.interface == "virtual":
            # python-can's virtual bus does not leave its process: drives on it answer as its
            # frames are sent, and an arm simulated here paces by its consumer (armid.simulated)
            self.pacing = "clock"
        # a full garbage collection walks every object of the process and stalls all threads
        # for many milliseconds; what exists after start-up is never garbage, so freeze it.
        # Before the heartbeat starts: the collection that precedes the freeze holds the GIL
        # for 100-170 ms in a large process (measured in the test process), more than the
        # drives' heartbeat consumer time allows once they are started
        self._settings.freeze()
        # as if each drive's heartbeat came with the newest frame read (an SDO answer)
        self._heartbeat[:] = self._newest_stamp
        self._last_watch = self._last_read = time.monotonic()
        heartbeat = can.Message(arbitration_id=0x700 + r.master_node_id, data=[0x05], is_extended_id=False)
        if r.bus.interface == "socketcan":
            self._hb_task = self._bus.send_periodic(heartbeat, r.master_heartbeat_ms / 1000.0)
        else:
            self._hb_task = CycleHeartbeat(heartbeat, round(r.master_heartbeat_ms / 1000.0 / self.period_s))
        # a drive is supervised from its first operational heartbeat after this start: one that
        # was operational before (a previous run) and went pre-operational above is not lost
        self._nmt[:] = -1
        self._nmt_supervised = True
        self.network.send_message(0, bytes([0x01, 0]))  # NMT start all
        self._sync_producer = True
        if r.bus.interface == "socketcan":
            # the kernel's broadcast manager cycles 240 SYNC frames with counters 1..240; the
            # bus echoes each one back (receive_own_messages), and the echo opens its cycle
            frames = [can.Message(arbitration_id=SYNC_COB_ID, data=[c], is_extended_id=False) for c in range(1, SYNC_COUNTER_OVERFLOW + 1)]
            self.network.subscribe(SYNC_COB_ID, self._on_sync_echo)
            self._bcm_task = self._bus.send_periodic(frames, r.period_s)
            self.timing_note = "SYNC from the kernel (SocketCAN BCM); " + timing.sentence("bus threads")
        else:
            self.timing_note = timing.sentence("SYNC thread") + ("; paced by the drives' answers (pacing: drives, a co-simulation)" if self.pacing == "drives" else "")
            self._thread = threading.Thread(target=self._sync_loop, name="armid-sync", daemon=True)
            self._thread.start()

    def _sdo(self, joint: int, node: canopen.RemoteNode, index: int, sub: int, value: int | None = None) -> int:
        if index not in node.object_dictionary:
            raise DriveConfigError(f"joint {joint + 1} (node {node.id}): object 0x{index:04X} is not in the drive's EDS")
        try:
            obj = node.sdo[index]
            if not isinstance(obj, SdoVariable):
                obj = obj[sub]
            if value is None:
                return int(obj.raw)
            obj.raw = value
            return value
        except SdoAbortedError as err:
            raise DriveConfigError(f"joint {joint + 1} (node {node.id}): SDO 0x{index:04X}:{sub:02X} aborted: {err}") from err
        except SdoCommunicationError as err:
            raise DriveConfigError(f"joint {joint + 1} (node {node.id}): no SDO answer for 0x{index:04X}:{sub:02X} ({err})") from err

    def _configure(self, joint: int, node: canopen.RemoteNode) -> dict[str, int]:
        r = self.rig
        u = self.units[joint]
        self._sdo(joint, node, 0x1017, 0, r.heartbeat_ms)
        self._sdo(joint, node, 0x1016, 1, (r.master_node_id << 16) | (3 * r.master_heartbeat_ms))
        self._sdo(joint, node, 0x1005, 0, SYNC_COB_ID)
        self._sdo(joint, node, 0x1006, 0, int(round(r.period_s * 1e6)))
        self._sdo(joint, node, 0x1019, 0, SYNC_COUNTER_OVERFLOW)
        self._sdo(joint, node, 0x6060, 0, 10)
        readback = {
            "encoder_increments": self._sdo(joint, node, 0x608F, 1),
            "encoder_motor_revolutions": self._sdo(joint, node, 0x608F, 2),
            "gear_motor_revolutions": self._sdo(joint, node, 0x6091, 1),
            "gear_shaft_revolutions": self._sdo(joint, node, 0x6091, 2),
            "rated_current_ma": self._sdo(joint, node, 0x6075, 0),
            "rated_torque_mnm": self._sdo(joint, node, 0x6076, 0),
            "max_torque_permille": self._sdo(joint, node, 0x6072, 0),
            "vendor_id": self._sdo(joint, node, 0x1018, 1),
            "product_code": self._sdo(joint, node, 0x1018, 2),
            "serial_number": self._sdo(joint, node, 0x1018, 4),
        }
        counts = readback["encoder_increments"] / max(readback["encoder_motor_revolutions"], 1)
        gear = readback["gear_motor_revolutions"] / max(readback["gear_shaft_revolutions"], 1)
        checks = [("0x608F encoder increments per revolution", counts, u.counts_per_rev),
                  ("0x6091 gear ratio", gear, u.gear_ratio), ("0x6075 rated current (A)", readback["rated_current_ma"] / 1000.0, u.rated_current_a)]
        for what, drive_value, rig_value in checks:
            if abs(drive_value - rig_value) > 1e-3 * abs(rig_value):
                raise DriveConfigError(f"joint {joint + 1} (node {node.id}): {what} is {drive_value:g} in the drive, {rig_value:g} in {r.source}")
        self._map_pdos(joint, node)
        return readback

    def _map_pdos(self, joint: int, node: canopen.RemoteNode) -> None:
        """Write the plan's PDO mapping by SDO, read it back, check it, build the decoders."""
        network, node_id = self.network, node.id
        # started: the network is open, and each node was made with its id (canopen types both optional)
        assert network is not None and node_id is not None
        try:
            node.tpdo.read()
            node.rpdo.read()
            specs = list(self.plan) + [PdoSpec("rpdo", 3, (TARGET_POSITION,), every=0)]
            for pdos, direction, base in ((node.tpdo, "tpdo", 0x180), (node.rpdo, "rpdo", 0x200)):
                for number in range(1, 5):
                    m = pdos[number]
                    spec = next((s for s in specs if s.direction == direction and s.number == number), None)
                    m.clear()
                    if spec is None:
                        m.enabled = False
                        m.cob_id = base + 0x100 * (number - 1) + node_id
                    else:
                        for index, sub, bits in spec.entries:
                            m.add_variable(index, sub, bits)
                        m.enabled = True
                        m.cob_id = base + 0x100 * (number - 1) + node_id
                        m.trans_type = spec.every if (direction == "tpdo" and spec.every) else 1
                pdos.save()
            node.tpdo.read()
            node.rpdo.read()
        except SdoAbortedError as err:
            raise DriveConfigError(f"joint {joint + 1} (node {node.id}): PDO mapping refused by SDO abort: {err}") from err
        for pdos in (node.tpdo, node.rpdo):
            assert pdos.map is not None  # a remote node's PDOs have their maps (canopen types them optional)
            for m in pdos.map.values():
                if m.on_message in network.subscribers.get(m.cob_id, []):
                    network.unsubscribe(m.cob_id, m.on_message)  # we decode TPDOs ourselves
        for spec in self.plan:
            m = (node.tpdo if spec.direction == "tpdo" else node.rpdo)[spec.number]
            got = [(v.index, v.subindex, v.length) for v in m.map]
            if not m.enabled or got != list(spec.entries):
                raise DriveConfigError(f"joint {joint + 1} (node {node.id}): {spec.direction.upper()}{spec.number} reads back as {got}, expected {list(spec.entries)}")
            if spec.direction == "tpdo":
                if m.trans_type != spec.every:
                    raise DriveConfigError(f"joint {joint + 1} (node {node.id}): TPDO{spec.number} transmission type reads back as {m.trans_type}, expected {spec.every}")
                fmt = "<" + "".join(PDO_FORMATS[(is_signed(v.od), v.length)] for v in m.map)
                self._tpdo[m.cob_id] = _Tpdo(joint, spec.number, spec.every, struct.Struct(fmt), [(v.index, v.subindex) for v in m.map])
                network.subscribe(m.cob_id, self._on_tpdo)

    def listen(self) -> None:
        """Decode the bus without taking part in it (a replayed log, another master's bus):
        the rig's PDO plan at the default COB-IDs, signedness from the shipped EDS; cycles
        open on each SYNC seen. Nothing is sent, no drive is supervised."""
        import canopen.objectdictionary

        self._listen_only = True
        self.pacing = "clock"  # a listener sends no SYNC: there is nothing to pace
        if self._bus is None:
            self._bus = open_bus(**self.rig.bus.kwargs())
        self.network = canopen.Network(self._bus)
        self.network.connect()
        od = canopen.objectdictionary.import_od(EDS, 1)
        for d in self.rig.drives:
            for spec in self.plan:
                if spec.direction != "tpdo":
                    continue
                fmt = "<" + "".join(PDO_FORMATS[(is_signed(od[index]), bits)] for index, _, bits in spec.entries)
                cob = 0x180 + 0x100 * (spec.number - 1) + d.node_id
                self._tpdo[cob] = _Tpdo(d.joint, spec.number, spec.every, struct.Struct(fmt), [(i, sub) for i, sub, _ in spec.entries])
                self.network.subscribe(cob, self._on_tpdo)
        self.network.subscribe(SYNC_COB_ID, self._on_sync_echo)

    def flush(self) -> None:
        """Listening: close the cycles still open. Only once every frame has been decoded
        (daq.canlog.replay_log waits for its end-of-log frame): a cycle closed while its
        frames are still on the way comes out invalid."""
        with self._lock:
            while self._open:
                self._emit(self._open.pop(0))

    # --- cyclic ---
    def _sync_loop(self) -> None:
        assert self._bus is not None
        paced = self.paced
        self._clock = clock = CycleClock(self.period_s, max(1, round(PACE_WAIT_S / self.period_s)) if paced else 1)  # the schedule starts with the thread
        counter = 0
        while not self._stop.is_set():
            clock.wait()
            if paced and self._cycle:
                # the schedule is kept: the cycles after a SYNC the pace held up come sooner (the
                # arm steps one period per SYNC and its samples carry the arm's time), so that
                # the waits do not add up over a run (4-11 s of the demo's 59 s of motion)
                self._pace()
            counter = counter % SYNC_COUNTER_OVERFLOW + 1
            self._cycle += 1
            now = time.time()
            with self._lock:
                self._open_cycle(self._cycle, counter, now, bus_time(now))
            try:
                self._bus.send(can.Message(arbitration_id=SYNC_COB_ID, data=[counter], is_extended_id=False))
                sent = time.monotonic()
                self.longest_sync_gap = max(self.longest_sync_gap, sent - self.last_sync_sent)
                self.last_sync_sent = sent
                self._send_commands()
                if isinstance(self._hb_task, CycleHeartbeat) and self._hb_task.due(self._cycle):
                    self._bus.send(self._hb_task.frame)
            except can.CanError as err:
                self._event("bus", f"cannot send SYNC {counter}: {err}")
            self._watchdog()

    def _pace(self) -> None:
        """Co-simulation: the next SYNC waits for the last cycle's consumer (``pacing: consumer``:
        an arm in this process; a busy process slows it instead of the control loop) or frames
        (``pacing: drives``: an arm in another process, which a shared machine stalls, 9 ms seen;
        its late answers were lost cycles), up to PACE_WAIT_S after the last SYNC (inside the
        drives' SYNC timeout)."""
        waited_from = time.monotonic()
        longest = max(PACE_WAIT_S - (waited_from - self.last_sync_sent), 0.0)
        with self._ack:
            if not self._ack.wait_for(lambda: self._paced_through() or self._stop.is_set(), longest):
                self.consumer_late += self.pacing == "consumer" and self._acknowledged < self._cycle
                self.drives_late += self.pacing == "drives" and self._emitted.cycle < self._cycle
        # a wait beyond its longest is this process not scheduled, and counts as a stall (_watchdog)
        self._paced_s += min(time.monotonic() - waited_from, longest)

    def _paced_through(self) -> bool:
        """The last cycle is done with: acted on by the consumer, its frames in, as paced."""
        if self.pacing == "consumer":
            return self._acknowledged >= self._cycle
        return self.pacing != "drives" or self._emitted.cycle >= self._cycle

    def _on_sync_echo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """A SYNC the broadcast manager sent, seen on the bus: its cycle starts at its stamp."""
        self._cycle += 1
        with self._lock:
            self._open_cycle(self._cycle, data[0] if data else 0, timestamp, self.frame_time(timestamp))
        if self._listen_only:
            return
        try:
            self._send_commands()
        except can.CanError as err:
            self._event("bus", f"cannot send commands after SYNC: {err}")
        self._watchdog()

    def _open_cycle(self, cycle: int, counter: int, now: float, bus: float) -> None:
        """Open a cycle at its SYNC: ``now`` on the wall clock (the records' stamps, the CAN
        log's), ``bus`` on the bus time frames are matched by (:func:`bus_time`: a step of the
        wall clock must not hold every later frame off the cycles opened before it)."""
        # Normally a cycle closes when its frames are in, or when a frame stamped after its
        # deadline shows that bus time has passed it (in _on_tpdo). Only when no frame comes
        # at all does the clock close it, later, so that a stall of this process is not
        # mistaken for frames lost on the bus.
        fallback = max(self.deadline_periods * self.period_s, 0.5)
        while self._open and bus - self._open[0].time_s >= fallback:
            self._emit(self._open.pop(0))
        if self._t0 is None:
            self._t0 = now - cycle * self.period_s
        # a paced simulation steps its arm one period per SYNC, whenever the SYNC goes out:
        # its samples carry the arm's time; on a real bus the SYNC's own time is the arm's
        # the newest complete sample carried forward: the previous cycle's frames may not be in yet
        s = self._open_record(cycle, self._t0 + cycle * self.period_s if self.paced else now)
        quiet = self._silent | self._not_operational  # a drive that sends no PDOs is not waited for
        expected = {(t.joint, t.number) for t in self._tpdo.values() if counter % t.every == 0 and not quiet[t.joint]}
        c = _Cycle(cycle, counter, bus, s, expected)
        self._open.append(c)
        self._last = s
        if self.decoded_frames is not None:
            self.decoded_frames(can.Message(timestamp=now, arbitration_id=SYNC_COB_ID, data=[counter], is_extended_id=False, is_rx=False))
        # a cycle that waits for no frame (every drive lost or reset) is complete as it opens:
        # held back, its consumer never acknowledged it and each SYNC waited PACE_WAIT_S (a
        # 3 s recording after a reset of every node took 72 s)
        self._flush_complete()

    def _emit(self, c: _Cycle) -> None:
        s = c.sample
        for joint, _ in c.expected:
            s.valid[joint] = False
            self.lost_cycles[joint] += 1
        # what this cycle's frames did not carry is the last value reported: taken now, from
        # the sample emitted before, not when the cycle opened (its frames were not in yet)
        self._carry_forward(s, [(name, [j for j in range(self.n_joints) if (j, index) not in c.written]) for name, index in _FIELDS])
        self._publish(s)
        if self.pacing == "drives":
            with self._ack:
                self._ack.notify_all()

    def _flush_complete(self) -> None:
        while self._open and not self._open[0].expected:
            self._emit(self._open.pop(0))

    def _on_tpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._lock:
            if self.decoded_frames is not None:
                self.decoded_frames(can.Message(timestamp=timestamp, arbitration_id=can_id, data=data, is_extended_id=False))
            self._decode_tpdo(can_id, data, self.frame_time(timestamp))

    def _decode_tpdo(self, can_id: int, data: bytearray, bus: float) -> None:
        t = self._tpdo[can_id]
        if len(data) != t.unpack.size:
            self._event("frame_length", f"joint {t.joint + 1} (node {can_id & 0x7F}): TPDO{t.number} (COB-ID 0x{can_id:03X}) has {len(data)} bytes, "
                                        f"the mapping has {t.unpack.size}", t.joint)
            return
        values = t.unpack.unpack(data)
        key = (t.joint, t.number)
        target = self._cycle_answered(key, bus)
        if target is None:
            self.late_frames[t.joint] += 1
            return
        target.expected.discard(key)
        u = self.units[t.joint]
        s = target.sample
        for (index, _), v in zip(t.fields, values):
            target.written.add((t.joint, index))
            if index == 0x6064:
                s.position[t.joint] = v / u.counts_per_rad
            elif index == 0x606C:
                s.velocity[t.joint] = v / u.counts_per_rad
                s.velocity_fresh[t.joint] = True
            elif index == 0x6078:
                s.measured_current[t.joint] = current_of(v, u.rated_current_a)
            elif index == 0x6041:
                s.status[t.joint] = v
        if not any(j == t.joint for j, _ in target.expected):
            s.valid[t.joint] = True
        deadline = self.deadline_periods * self.period_s
        while self._open and self._open[0] is not target and bus - self._open[0].time_s > deadline:
            self._emit(self._open.pop(0))
        self._flush_complete()

    def _cycle_answered(self, key: tuple[int, int], bus: float) -> _Cycle | None:
        """The open cycle a TPDO answers: frames keep their order and none answers a later
        SYNC, so the oldest cycle still waiting for it, sent before it. When a later cycle
        waits too, the frame is its predecessor's, late (a drive, or the process simulating
        it, held up past the next SYNCs: its own frames follow at once), or the later one's,
        its predecessor's lost. It is taken as late unless the previous frame was taken so
        and a SYNC went out after it: then that frame was the loss's successor and this one
        answers the newest SYNC. Oldest-first alone let one lost frame shift every later one
        by a cycle and pace each SYNC by the whole wait (issue 31)."""
        waiting = [c for c in self._open if key in c.expected and c.time_s <= bus + 1e-4]
        taken_late = self._taken_late.pop(key, None)
        if len(waiting) < 2:
            return waiting[0] if waiting else None
        if taken_late is None or waiting[-1].time_s <= taken_late:
            self._taken_late[key] = bus
            return waiting[0]
        joint, number = key
        for stale in waiting[:-1]:  # their frames went to their predecessors: lost
            stale.expected.discard(key)
            self.lost_cycles[joint] += 1
        self._event("frame_lost", f"joint {joint + 1}: TPDO{number} of cycle {waiting[0].cycle - 1} was lost and cycle "
                                  f"{waiting[0].cycle}'s took its place; realigned at cycle {waiting[-1].cycle}", joint)
        return waiting[-1]

    def _send_commands(self) -> None:
        assert self.network is not None
        for d in self.rig.drives:
            j = d.joint
            if self._position_mode:
                self.network.send_message(0x400 + d.node_id, struct.pack("<i", int(self._target_position[j])))
            else:
                self.network.send_message(0x200 + d.node_id, struct.pack("<h", int(self._target[j])))
            # sent on change, and refreshed every CONTROLWORD_REFRESH cycles: a controlword that
            # reached a drive before it was operational is not lost (transitions act on edges)
            if self._controlword[j] != self._sent_controlword[j] or self._cycle % CONTROLWORD_REFRESH == 0:
                self.network.send_message(0x300 + d.node_id, struct.pack("<H", int(self._controlword[j])))
                self._sent_controlword[j] = self._controlword[j]

    def _watchdog(self) -> None:
        now = time.monotonic()
        limit = 3 * self.rig.heartbeat_ms / 1000.0
        # waiting for the consumer of a paced arm is not a stall: this process ran, and read
        # every heartbeat that came meanwhile (counted as one, a silent drive's detection in
        # the paced bench came up to 0.12 s late)
        stall = now - self._last_watch - 2 * self.period_s - self._paced_s
        self._paced_s = 0.0
        self._last_watch = now
        if stall > 2 * self.period_s:
            self.last_stall = (now, stall + 2 * self.period_s)
        if stall > STALL_S:
            # this process did not run: frames sent meanwhile wait unread in the socket
            self._last_read += stall
            self.unscheduled_s += stall
            if self.pacing == "consumer":
                # drives simulated in this process stopped with it and sent no heartbeat meanwhile;
                # the first frame read after the stall (one drive's heartbeat) moved bus time on
                # before the others' were read, and lost a drive that was answering (a 0.43 s
                # stall beside two busy loops): the stall does not count against them
                self._heartbeat += stall
        newest = self._newest_stamp  # read before the heartbeats: one read meanwhile only makes them younger
        bus_silent = now - self._last_read > BUS_SILENT_S
        for d in self.rig.drives:
            j = d.joint
            age = newest - self._heartbeat[j]
            if self._silent[j] or not (age > limit or bus_silent):
                continue
            self._silent[j] = True
            silent = age if age > limit else now - self._last_read
            why = (f"no heartbeat for {age:.3f} s of bus time (3 periods: {limit:.3f} s)" if age > limit
                   else f"nothing read from the bus for {silent:.3f} s")
            self._declare_lost(j, HeartbeatLost(j, d.node_id, 0x8130, f"{why}; the other drives were quick-stopped{self._second_sync()}", silent_s=silent),
                               "heartbeat_lost")

    def _on_frame_read(self, stamp: float) -> None:
        """Bus time as far as this process has read it: every frame, after the network's
        handlers (the notifier calls them first), so a heartbeat is in before what follows it."""
        self._newest_stamp = max(self._newest_stamp, stamp)
        self._last_read = time.monotonic()

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        node = can_id - 0x700
        j = self._node_ids[node]
        self._heartbeat[j] = max(self._heartbeat[j], self.frame_time(timestamp))
        if self._silent[j]:
            self._silent[j] = False
            self._event("heartbeat_back", f"joint {j + 1} (node {node}) is back (NMT state 0x{data[0]:02X})" if data else
                        f"joint {j + 1} (node {node}) is back", j)
        if len(data) != 1:
            self._event("frame_length", f"joint {j + 1}: heartbeat (COB-ID 0x{can_id:03X}) has {len(data)} bytes, CiA 301 says 1", j)
            return
        self._supervise_nmt(j, node, data[0] & 0x7F)

    def _supervise_nmt(self, j: int, node: int, state: int) -> None:
        """A drive that was operational and whose heartbeat reports another NMT state is lost
        as a silent one is (the others quick-stopped), until it reports operational again:
        its PDOs stop, and a cycle must not wait for them."""
        was, self._nmt[j] = self._nmt[j], state
        if state == NMT_OPERATIONAL:
            if self._not_operational[j]:
                self._not_operational[j] = False
                self._event("nmt_back", f"joint {j + 1} (node {node}) is operational again", j)
            return
        if was != NMT_OPERATIONAL or self._not_operational[j] or self._listen_only or not self._nmt_supervised:
            return
        self._not_operational[j] = True
        meaning = NMT_STATES.get(state, f"reports NMT state 0x{state:02X} instead of operational")
        self._declare_lost(j, NotOperational(j, node, state, f"{meaning}; the other drives were quick-stopped"), "nmt")

    def _on_emcy_frame(self, joint: int, node: canopen.RemoteNode, can_id: int, data: bytearray, timestamp: float) -> None:
        """An EMCY frame of the CiA 301 length goes to canopen's decoder (and so to :meth:`_on_emcy`);
        another length is an event naming the drive, not an exception in the notifier."""
        if len(data) != EMCY_BYTES:
            self._event("frame_length", f"joint {joint + 1} (node {node.id}): EMCY (COB-ID 0x{can_id:03X}) has {len(data)} bytes, "
                                        f"CiA 301 says {EMCY_BYTES}: not decoded", joint)
            return
        node.emcy.on_emcy(can_id, data, timestamp)
        for kept in (node.emcy.log, node.emcy.active):
            del kept[:-EMCY_KEPT]

    def _on_emcy(self, joint: int, node_id: int, err: canopen.emcy.EmcyError) -> None:
        if err.code == 0:
            self._event("emcy_reset", f"joint {joint + 1} (node {node_id}): error reset", joint)
            return
        meaning = emcy_meaning(err.code, bytes(err.data)) + self._own_stall(err.code) + self._second_sync()
        self._fault(DriveFault(joint, node_id, err.code, meaning), "emcy")

    def _on_foreign_sync(self, msg: can.Message) -> None:
        """A SYNC this master did not send: another device produces SYNC on the bus (every
        drive steps on each SYNC it sees, so their timing and the arm's are not this master's).
        Said once as an event; every fault after it names it (:meth:`_second_sync`)."""
        self.foreign_syncs += 1
        self._foreign_sync_last = time.monotonic()
        if self.foreign_syncs == 1:
            counter = f", counter {msg.data[0]}" if len(msg.data) else ""
            self._event("foreign_sync", f"a second SYNC producer on the bus: a SYNC frame (COB-ID 0x{SYNC_COB_ID:03X}{counter}) that this "
                                        f"master did not send (it sends one every {1000 * self.period_s:g} ms)")

    def _second_sync(self) -> str:
        """What a fault line adds when SYNC frames this master did not send came within the last 2 s."""
        if not self.foreign_syncs or time.monotonic() - self._foreign_sync_last > 2.0:
            return ""
        return (f"; a second SYNC producer on the bus ({self.foreign_syncs:,} SYNC frames this master did not send, the last "
                f"{time.monotonic() - self._foreign_sync_last:.2f} s ago)")

    def _own_stall(self, code: int) -> str:
        """Why a drive timed out on this master, where this process is the cause: its SYNC thread
        silent (or run late) for longer than the drive waits."""
        if code not in (0x8100, 0x8130) or self._thread is None:
            return ""
        now = time.monotonic()
        silent = now - self.last_sync_sent
        when, stall = self.last_stall
        late = stall if now - when < 1.0 else 0.0
        waited = "SYNC" if code == 0x8100 else "the master's heartbeat"
        if late > 0.05:
            return f"; {stall_sentence(late)}: the drives timed out waiting for {waited}"
        if silent > 0.05:
            return f"; this process's SYNC thread has sent nothing for {silent:.3f} s ({stall_sentence(silent).split('(', 1)[1][:-1]})"
        return ""

    # --- the interface ---
    def acknowledge(self, cycle: int) -> None:
        with self._ack:
            self._acknowledged = max(self._acknowledged, cycle)
            self._ack.notify_all()

    def read(self, timeout: float | None = None) -> Sample:
        """The next cycle's sample. With the arm simulated in this process, a wait that ends while
        this process's SYNC thread was as silent waits on (up to :data:`STALL_WAIT_S`): the arm
        waited too (:func:`~drivers.realtime.silent_for`). Elsewhere the timeout names the stall."""
        if self._faults.empty() and self.network is not None:
            self.network.check()
        started = time.monotonic()
        while True:
            began, cycle = time.monotonic(), self._cycle
            try:
                return self._next_sample(timeout, "is SYNC running and the bus up?")
            except DriveFault:
                raise
            except DriverTimeout as err:
                wait = timeout if timeout is not None else 10 * self.period_s + 1.0
                thread = self._thread  # None: the bus sends SYNC itself, and tells nothing of this process
                stall = 0.0 if thread is None else silent_for(self.last_sync_sent, self.last_stall, wait, began, self._cycle - cycle, PACE_WAIT_S)
                if thread is None or not stall or self._stop.is_set():
                    raise
                if not (self.pacing == "consumer" and thread.is_alive() and time.monotonic() - started < STALL_WAIT_S):
                    raise DriverTimeout(f"{err}; {stall_sentence(stall)}") from None
                self._event("stall", f"no cycle for {time.monotonic() - started:.2f} s: {stall_sentence(stall)}; the simulated arm waited")

    def _command_torque(self, tau: Array) -> None:
        current = tau / self.torque_constants
        rated = np.array([u.rated_current_a for u in self.units])
        permille = permille_of(current, rated).astype(np.int64)
        self._target = permille
        self._commanded = current_of(permille, rated)
        self._position_mode = False

    def _command_position(self, q: Array) -> None:
        if not self._position_mode:
            for j, node in enumerate(self.nodes):
                self._sdo(j, node, 0x6060, 0, 8)
            self._position_mode = True
        self._target_position = np.round(q * np.array([u.counts_per_rad for u in self.units])).astype(np.int64)

    def set_controlword(self, joints: list[int], controlword: int) -> None:
        for j in joints:
            self._controlword[j] = controlword

    def enable(self, timeout: float = 1.0) -> None:
        """Shutdown -> switch on -> enable operation, each acknowledged by the statusword."""
        joints = list(range(self.n_joints))
        for cw, state in ((0x80, None), (0x06, 0x21), (0x07, 0x23), (0x0F, OPERATION_ENABLED)):
            self.set_controlword(joints, cw)
            if state is None:
                time.sleep(4 * self.period_s)
                continue
            deadline = time.monotonic() + timeout
            while True:
                status = self._emitted.status.copy()  # the newest complete sample's
                if all((s & STATE_MASK) == state for s in status):
                    break
                if time.monotonic() > deadline:
                    bad = [f"joint {j + 1}: statusword 0x{int(s):04X}" for j, s in enumerate(status) if (s & STATE_MASK) != state]
                    raise DriverTimeout(f"drives did not reach state 0x{state:02X} within {timeout} s ({'; '.join(bad)})")
                time.sleep(self.period_s)

    def disable(self) -> None:
        self.command_torque(np.zeros(self.n_joints))
        self.set_controlword(list(range(self.n_joints)), 0x00)

    def quick_stop(self, joints: list[int] | None = None) -> None:
        joints = list(range(self.n_joints)) if joints is None else joints
        target = self._target.copy()
        target[joints] = 0
        self._target = target
        self.set_controlword(joints, 0x02)

    def _close(self) -> None:
        for task in (self._hb_task, self._bcm_task):
            if task is not None:
                task.stop()
        if self.network is not None:
            if self._own_bus:
                self.network.disconnect()
            elif self.network.notifier is not None:
                self.network.notifier.stop(0.5)
        elif self._own_bus and self._bus is not None:  # a start that failed before the network was up
            self._bus.shutdown()
        self.network = None


class _Watcher(can.Listener):
    """Sees every frame: error frames and frames from nodes the rig does not have."""

    def __init__(self, driver: CanopenDriver) -> None:
        self.driver = driver
        self._errors: list[float] = []
        self._unknown: set[int] = set()

    def on_message_received(self, msg: can.Message) -> None:
        d = self.driver
        d._on_frame_read(d.frame_time(msg.timestamp))
        if msg.is_error_frame:
            d.error_frames += 1
            now = time.monotonic()
            self._errors = [t for t in self._errors if now - t < 0.1] + [now]
            if len(self._errors) == 20:
                d._event("error_frames", f"{len(self._errors)} CAN error frames within 100 ms (total {d.error_frames}): check wiring and termination")
            return
        cob = msg.arbitration_id
        if cob == SYNC_COB_ID:  # this master's own never reach it (a SYNC thread's are not echoed; SocketCAN's echo is not rx)
            if d._sync_producer and (d._thread is not None or msg.is_rx):
                d._on_foreign_sync(msg)
            return
        func, node = cob & 0x780, cob & 0x7F
        if func in (0x080, 0x180, 0x280, 0x380, 0x480, 0x580, 0x700) and node and cob != SYNC_COB_ID:
            if node not in d._node_ids and node != d.rig.master_node_id and node not in self._unknown:
                self._unknown.add(node)
                d._event("unknown_node", f"frame COB-ID 0x{cob:03X} from node {node}, which the rig {d.rig.source} does not have")

"""A simulated chain of Dynamixel X-series servos on the far end of a pseudo-terminal.

The driver opens the pty's slave end as a serial port (:attr:`SimulatedServoChain.port`),
exactly as it opens ``/dev/ttyUSB0``; the chain reads instruction packets from the master
end and answers in Protocol 2.0 with the line's timing: an instruction occupies the line
for its bytes at the baud rate, a reply starts after the servos' Return Delay Time and
completes after its own bytes. The servos run free, like real ones: the arm's physics
(:class:`sim_bus.physics.ArmPhysics`, the CAN simulation's) advances in whole periods
with the wall clock, between requests, and a read returns the state of the last period
boundary (a request is answered at once, whatever the physics costs).

Each servo keeps a control table (the X series' layout); EEPROM (below Torque Enable)
is writable only with torque off; a hardware error turns torque off until a Reboot. With
torque off a joint is held by its brake, as in the CAN simulation. Faults are injected
with :meth:`SimulatedServoChain.inject`: a corrupted CRC, a dropped reply, a partial
packet, line noise before a reply, a stale reply before a reply (what a chain descheduled
past a timeout leaves on the line: the late answer to an earlier request, here the last
one of the other kind, cyclic or one-off, that the chain sent), a hardware error.
"""

from __future__ import annotations

import os
import select
import struct
import threading
import time
import tty
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from armid.drivers import dynamixel_protocol as dxl
from armid.drivers.dynamixel_protocol import ALERT, Address, Instruction
from armid.drivers.line_progress import LineProgress
from armid.drivers.rig import Rig
from armid.identify.robot import Robot
from armid.schema.errors import RigFileError, UsageError

from .physics import ArmPhysics, Measurement, simulation_config

FAULTS = ("crc", "drop", "partial", "noise", "stale", "hardware_error")
MAX_CATCH_UP_PERIODS = 500  # a stall longer than a second of arm time is not replayed in full
READ_ONLY = ((0, Address.ID), (Address.HARDWARE_ERROR_STATUS, Address.HARDWARE_ERROR_STATUS + 1),
             (Address.REALTIME_TICK, dxl.CONTROL_TABLE_SIZE))  # model, firmware; hardware error; present values
POSITION_GAIN_A_PER_RAD, VELOCITY_GAIN_A_S_PER_RAD = 20.0, 0.5  # position mode's loop (a plausible PD)


@dataclass
class _Fault:
    kind: str
    remaining: int
    bits: int = 0


class SimulatedServo:
    """One servo's control table and state."""

    def __init__(self, servo_id: int, joint: int, model: dxl.ServoModel, counts_per_rad: float, gear_ratio: float) -> None:
        self.id, self.joint, self.model = servo_id, joint, model
        self.counts_per_rad, self.gear_ratio = counts_per_rad, gear_ratio
        t = bytearray(dxl.CONTROL_TABLE_SIZE)
        struct.pack_into("<H", t, Address.MODEL_NUMBER, model.number)
        t[Address.FIRMWARE_VERSION] = 46
        t[Address.ID] = servo_id
        t[Address.BAUD_RATE] = 1
        t[Address.RETURN_DELAY_TIME] = 250  # the factory's 500 us
        t[Address.OPERATING_MODE] = dxl.POSITION_MODE
        struct.pack_into("<H", t, Address.CURRENT_LIMIT, model.current_limit)
        t[Address.STATUS_RETURN_LEVEL] = 2
        struct.pack_into("<H", t, Address.PRESENT_INPUT_VOLTAGE, 120)
        t[Address.PRESENT_TEMPERATURE] = 36
        self.table = t
        self.faults: deque[_Fault] = deque()

    @property
    def torque_on(self) -> bool:
        return bool(self.table[Address.TORQUE_ENABLE])

    @property
    def hardware_error(self) -> int:
        return self.table[Address.HARDWARE_ERROR_STATUS]

    def error_field(self, number: int = 0) -> int:
        return number | (ALERT if self.hardware_error else 0)

    def current_demand(self, q: float, qd: float) -> float:
        """The current loop's demand (A) for this period, within Current Limit."""
        if not self.torque_on or self.hardware_error:
            return 0.0
        t = self.table
        limit = struct.unpack_from("<H", t, Address.CURRENT_LIMIT)[0] * self.model.current_lsb_a
        mode = t[Address.OPERATING_MODE]
        if mode == dxl.CURRENT_MODE:
            demand = struct.unpack_from("<h", t, Address.GOAL_CURRENT)[0] * self.model.current_lsb_a
        elif mode == dxl.POSITION_MODE:
            goal = struct.unpack_from("<i", t, Address.GOAL_POSITION)[0] / self.counts_per_rad
            demand = POSITION_GAIN_A_PER_RAD * (goal - q) - VELOCITY_GAIN_A_S_PER_RAD * qd
        else:
            goal_v = struct.unpack_from("<i", t, Address.GOAL_VELOCITY)[0] * self.model.velocity_lsb_rad_s / self.gear_ratio
            demand = 10.0 * VELOCITY_GAIN_A_S_PER_RAD * (goal_v - qd)
        return float(np.clip(demand, -limit, limit))

    def sense(self, m: Measurement, ms: int) -> None:
        """Latch the sensors into the control table, quantised as the servo reports them."""
        t, j = self.table, self.joint
        current = int(np.clip(round(m.current[j] / self.model.current_lsb_a), -32768, 32767))
        velocity = int(round(m.velocity[j] * self.gear_ratio / self.model.velocity_lsb_rad_s))
        position = int(round(m.position[j] * self.counts_per_rad))
        struct.pack_into("<hii", t, Address.PRESENT_CURRENT, current, velocity, position)
        struct.pack_into("<H", t, Address.REALTIME_TICK, ms % 32768)

    def take_fault(self) -> _Fault | None:
        """The fault that applies to this reply (each counts down per reply)."""
        if not self.faults:
            return None
        f = self.faults[0]
        f.remaining -= 1
        if f.remaining <= 0:
            self.faults.popleft()
        return f

    def write(self, address: int, data: bytes) -> int:
        """Apply a write; returns the error number (0 when accepted)."""
        end = address + len(data)
        if address < 0 or end > dxl.CONTROL_TABLE_SIZE or not data:
            return 7
        if address < Address.TORQUE_ENABLE and self.torque_on:
            return 7  # EEPROM is locked while torque is on
        if address <= Address.TORQUE_ENABLE < end and data[Address.TORQUE_ENABLE - address] and self.hardware_error:
            return 1  # torque cannot come on before a reboot clears the hardware error
        if any(address < hi and lo < end for lo, hi in READ_ONLY):
            return 7
        self.table[address:end] = data
        return 0


class SimulatedServoChain:
    """The rig's servos on a pty; ``port`` is the device the driver opens. ``close`` ends it."""

    def __init__(self, rig: Rig[Robot], seed: int | None = None, progress: LineProgress | None = None) -> None:
        if rig.serial is None:
            raise RigFileError(rig.source, "bus.interface", "not a serial rig (bus.interface: dynamixel)")
        self.rig = rig
        self.baudrate = rig.serial.baudrate
        sim = dict(rig.simulation)
        self.seed = int(sim.get("seed", 0) if seed is None else seed)
        self.config = simulation_config(sim, rig.n_joints, f"{rig.source}: simulation")
        self.physics = ArmPhysics(rig.robot, self.config, rig.period_s, self.seed)
        self.servos = [SimulatedServo(d.node_id, d.joint, dxl.SERVO_MODELS[d.model], d.units.counts_per_rad, d.units.gear_ratio)
                       for d in rig.drives]
        self._by_id = {s.id: s for s in self.servos}
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self._buffer = bytearray()
        # request bytes read and reply bytes written, for the master: what it finds unanswered
        # at its deadline while these lag was this process (or the pty) not running, no servo's silence
        self.progress = LineProgress() if progress is None else progress
        self._read_bytes = self._sent_bytes = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._start = time.monotonic()
        self.periods = 0
        self.skipped_periods = 0
        self.line_free_at = 0.0
        self.instructions = 0
        self.bad_instructions: list[str] = []
        self._last_sync_reply = b""  # the last Sync Read / Fast Sync Read reply sent, and the last
        self._last_status = b""  # one-off status: what a "stale" fault puts on the line again
        self._rng = np.random.default_rng(self.seed + 1)
        m = self._measure()
        for s in self.servos:
            s.sense(m, 0)
        self._thread = threading.Thread(target=self._run, name="armid-servo-chain", daemon=True)
        self._physics_thread = threading.Thread(target=self._run_physics, name="armid-servo-chain-physics", daemon=True)
        self._thread.start()
        self._physics_thread.start()

    # --- faults ---
    def inject(self, kind: str, servo_id: int, count: int = 1, bits: int = 0x20) -> None:
        """The next ``count`` replies of ``servo_id`` carry the fault ``kind`` (one of
        FAULTS; ``stale`` applies to one-off replies too, the others to sync reads). ``hardware_error`` sets Hardware Error Status to ``bits`` (default:
        overload) and turns torque off, until a Reboot."""
        if kind not in FAULTS:
            raise UsageError(f"unknown fault {kind!r}; known: {', '.join(FAULTS)}")
        if servo_id not in self._by_id:
            raise UsageError(f"no servo {servo_id} in the chain ({sorted(self._by_id)})")
        servo = self._by_id[servo_id]
        with self._lock:
            if kind == "hardware_error":
                servo.table[Address.HARDWARE_ERROR_STATUS] = bits
                servo.table[Address.TORQUE_ENABLE] = 0
            else:
                servo.faults.append(_Fault(kind, count))

    # --- the arm ---
    def _measure(self) -> Measurement:
        p = self.physics
        zeros = np.zeros(p.n)
        return Measurement(p.time_s, p.position, p.velocity, zeros, p.position, p.velocity, zeros)

    def _due(self, now: float) -> int:
        """Periods the physics is behind the last period boundary before ``now``."""
        return int((now - self._start) / self.rig.period_s) - self.periods - self.skipped_periods

    def _advance(self, now: float, most: int = MAX_CATCH_UP_PERIODS) -> None:
        """Step the physics towards the last period boundary before ``now``, ``most`` periods
        at most. The control tables are locked only to read the demand and to latch the
        sensors, never for the step itself: the line is answered while the physics computes."""
        due = self._due(now)
        if due > MAX_CATCH_UP_PERIODS:
            self.skipped_periods += due - MAX_CATCH_UP_PERIODS
            due = MAX_CATCH_UP_PERIODS
        for _ in range(max(0, min(due, most))):
            with self._lock:
                q, qd = self.physics.position, self.physics.velocity
                demand = np.array([s.current_demand(q[s.joint], qd[s.joint]) for s in self.servos])
                braked = np.array([not s.torque_on or bool(s.hardware_error) for s in self.servos])
            m = self.physics.step(demand, braked)
            ms = int(1000 * m.time_s)
            with self._lock:
                self.periods += 1
                for s in self.servos:
                    s.sense(m, ms)

    # --- the line ---
    def _run(self) -> None:
        # requests are answered at once from the control tables, on this thread; the physics
        # advances on its own thread, at each period boundary, as a servo's own loop does. A
        # period of physics costs about a millisecond of Python (more on a loaded machine):
        # on the line's thread, a request that came during a step waited for it, and one that
        # came while a descheduled chain caught up waited for all of the catch-up (measured
        # beside one busy core: Ping round trips of p50 9 ms, p99 380 ms, replies that came
        # after the driver's timeout and were stale on the line for its next request)
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], 0.05)
            if ready:
                try:
                    chunk = os.read(self._master, 4096)
                except OSError:
                    return
                self._buffer += chunk
                self._read_bytes += len(chunk)
                for item in dxl.split_packets(self._buffer):
                    self._serve(item, time.monotonic())
                self.progress.record(self._read_bytes - len(self._buffer), self._sent_bytes)

    def _run_physics(self) -> None:
        period = self.rig.period_s
        while not self._stop.is_set():
            next_boundary = self._start + (self.periods + self.skipped_periods + 1) * period
            delay = next_boundary - time.monotonic()
            if delay > 0 and self._stop.wait(delay):
                return
            self._advance(time.monotonic(), most=1)

    def _wire(self, n_bytes: int) -> float:
        return n_bytes * dxl.BITS_PER_BYTE / self.baudrate

    def _send_at(self, when: float, data: bytes) -> None:
        delay = when - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        if data:
            self._sent_bytes += os.write(self._master, data)

    def _serve(self, item: dxl.Packet | dxl.ProtocolError, arrived: float) -> None:
        self.instructions += 1
        if isinstance(item, dxl.ProtocolError):
            # a servo whose id it was would answer a CRC error; the id is not trustworthy
            if len(self.bad_instructions) < 100:
                self.bad_instructions.append(str(item))
            return
        p = item
        n_in = 10 + len(dxl.stuff(bytes([p.instruction]) + p.params))
        request_end = max(arrived, self.line_free_at) + self._wire(n_in)
        self.line_free_at = request_end
        with self._lock:
            replies = self._answer(p)
            if p.instruction not in (Instruction.SYNC_READ, Instruction.FAST_SYNC_READ) and replies:
                servo = self._by_id.get(p.id)
                if servo is not None and servo.faults and servo.faults[0].kind == "stale":
                    servo.take_fault()
                    replies = [(0.0, self._last_sync_reply or self._last_status or self._stale_for(servo))] + replies
        when = request_end
        for delay_s, data in replies:
            when += delay_s + self._wire(len(data))
            self._send_at(when, data)
        if replies:
            last = replies[-1][1]
            if p.instruction in (Instruction.SYNC_READ, Instruction.FAST_SYNC_READ):
                self._last_sync_reply = last
            else:
                self._last_status = last
        self.line_free_at = max(self.line_free_at, when)

    def _return_delay(self, servo: SimulatedServo) -> float:
        return servo.table[Address.RETURN_DELAY_TIME] * 2e-6

    def _answer(self, p: dxl.Packet) -> list[tuple[float, bytes]]:
        """(return delay, bytes) of each reply, in order on the line."""
        ins, params = p.instruction, p.params
        if ins == Instruction.SYNC_WRITE:
            address, length = struct.unpack_from("<HH", params)
            for k in range(4, len(params) - length + 1, 1 + length):
                servo = self._by_id.get(params[k])
                if servo is not None:
                    servo.write(address, params[k + 1:k + 1 + length])
            return []
        if ins in (Instruction.SYNC_READ, Instruction.FAST_SYNC_READ):
            address, length = struct.unpack_from("<HH", params)
            ids = list(params[4:])
            return self._sync_read(ids, address, length, fast=ins == Instruction.FAST_SYNC_READ)
        servo = self._by_id.get(p.id)
        if p.id == dxl.BROADCAST_ID:
            if ins == Instruction.WRITE:
                for s in self.servos:
                    s.write(struct.unpack_from("<H", params)[0], params[2:])
            return []
        if servo is None:
            return []  # nobody answers an id that is not on the chain
        if ins == Instruction.PING:
            data = struct.pack("<HB", servo.model.number, servo.table[Address.FIRMWARE_VERSION])
            return [(self._return_delay(servo), dxl.encode_status(servo.id, servo.error_field(), data))]
        if ins == Instruction.READ:
            address, length = struct.unpack_from("<HH", params)
            if address + length > dxl.CONTROL_TABLE_SIZE:
                return [(self._return_delay(servo), dxl.encode_status(servo.id, servo.error_field(7)))]
            return [(self._return_delay(servo), dxl.encode_status(servo.id, servo.error_field(), bytes(servo.table[address:address + length])))]
        if ins == Instruction.WRITE:
            number = servo.write(struct.unpack_from("<H", params)[0], params[2:]) if len(params) > 2 else 5
            return [(self._return_delay(servo), dxl.encode_status(servo.id, servo.error_field(number)))]
        if ins == Instruction.REBOOT:
            servo.table[Address.HARDWARE_ERROR_STATUS] = 0
            servo.table[Address.TORQUE_ENABLE] = 0
            servo.faults.clear()
            return [(self._return_delay(servo), dxl.encode_status(servo.id, 0))]
        return [(self._return_delay(servo), dxl.encode_status(servo.id, servo.error_field(2)))]

    def _sync_read(self, ids: list[int], address: int, length: int, fast: bool) -> list[tuple[float, bytes]]:
        servos = [self._by_id.get(i) for i in ids]
        if fast:
            # built block by block as the servos put it on the line: each appends its block
            # and the CRC of everything heard so far (a corrupted CRC included)
            size = 1 + len(ids) * (4 + length)
            reply = bytearray(dxl.HEADER + bytes([dxl.BROADCAST_ID, size & 0xFF, size >> 8, Instruction.STATUS]))
            noise = b""
            for s in servos:
                if s is None:
                    break  # the servos after a missing one never get their turn
                f = s.take_fault()
                if f is not None and f.kind == "drop":
                    break
                start = len(reply)
                reply += bytes([s.error_field(), s.id]) + bytes(s.table[address:address + length])
                crc = bytearray(dxl.crc16(reply).to_bytes(2, "little"))
                if f is not None and f.kind == "crc":
                    crc[1] ^= 0xA5
                reply += crc
                if f is not None and f.kind == "partial":
                    del reply[start + (4 + length) // 2:]
                    break
                if f is not None and f.kind == "noise":
                    noise = self._rng.integers(0, 256, 5, dtype=np.uint8).tobytes()
                if f is not None and f.kind == "stale":
                    noise = self._stale_for(s)
            first = servos[0] if servos and servos[0] is not None else None
            delay = self._return_delay(first) if first is not None else 0.0
            return [(delay, noise + bytes(reply))] if len(reply) > 8 else []
        out = []
        for s in servos:
            if s is None:
                continue
            f = s.take_fault()
            packet = bytearray(dxl.encode_status(s.id, s.error_field(), bytes(s.table[address:address + length])))
            if f is not None:
                if f.kind == "drop":
                    continue
                if f.kind == "crc":
                    packet[-1] ^= 0xA5
                elif f.kind == "partial":
                    packet = packet[: len(packet) // 2]
                elif f.kind == "noise":
                    packet = bytearray(self._rng.integers(0, 256, 5, dtype=np.uint8).tobytes()) + packet
                elif f.kind == "stale":
                    packet = bytearray(self._stale_for(s)) + packet
            out.append((self._return_delay(s), bytes(packet)))
        return out

    def _stale_for(self, servo: SimulatedServo) -> bytes:
        """A stale one-off status: the last one sent, or another servo's answer to a Ping."""
        if self._last_status:
            return self._last_status
        other = next((s for s in self.servos if s is not servo), servo)
        return dxl.encode_status(other.id, 0, struct.pack("<HB", other.model.number, other.table[Address.FIRMWARE_VERSION]))

    def status(self) -> dict[str, Any]:
        return {"periods": self.periods, "skipped_periods": self.skipped_periods, "time_s": self.physics.time_s,
                "torque": [s.torque_on for s in self.servos], "hardware_error": [s.hardware_error for s in self.servos],
                "position": self.physics.position.tolist(), "instructions": self.instructions}

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._physics_thread.join(timeout=1.0)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> SimulatedServoChain:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

"""Dynamixel X-series servos over Protocol 2.0 on a serial line (pyserial), behind :class:`Driver`.

Start-up, per servo: Ping (the model number must be the rig's), Hardware Error Status,
torque off, Return Delay Time and Operating Mode (current control) written and read back,
Current Limit read. The line's time budget is checked first (:func:`check_budget`): a
period the baud rate cannot keep is refused with the numbers.

Each cycle, on one thread that alone touches the port: the one-off requests queued since
the last cycle (torque, reboot, mode), a Sync Write of Goal Current (no reply), and a Fast
Sync Read (or Sync Read) of Present Current, Velocity and Position. A sample is stamped
when its reply completes. A servo whose block is missing, cut or corrupted is marked
invalid for that cycle (its values are the last known ones) and an event names the
error; after ``silent_cycles`` such cycles in a row it is declared lost (a fault, and the
others are quick-stopped); it is back as soon as it answers. A status whose alert bit is
set makes the driver read Hardware Error Status and raise a :class:`DriveFault` once;
:meth:`DynamixelDriver.enable` reboots such a servo before enabling. Every read has a
timeout, so no fault on the line can hang the cycle.
"""

from __future__ import annotations

import os
import queue
import select
import struct
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from armid.schema import Array
from armid.schema.errors import ServoLost

from . import dynamixel_protocol as dxl
from .dynamixel_protocol import Address, ProtocolError, ReplyTimeout, StatusError
from .interface import CycleClock, DriveConfigError, DriveFault, Driver, DriverError, DriverTimeout, Sample
from .line_progress import LineProgress
from .port_errors import serial_open_error
from .rig import Rig

REBOOT_WAIT_S = 1.0  # a rebooting servo answers a ping again within this
ONE_OFF_TIMEOUT_S = 0.05  # a one-off transaction's reply timeout, at least (a loaded machine deschedules the chain for tens of ms)
ONE_OFF_ATTEMPTS = 3
STALL_S = 0.002  # a wait that returns this much after its timeout: this process was not running
MAX_STALL_WAITS = 3  # new reply windows one read gets for stalls of this process (a silent servo still times out)


def serial_budget(rig: Rig) -> dxl.SerialBudget:
    """The time budget of one cycle of the rig's servo chain (:func:`dxl.check_budget` refuses it)."""
    cfg = rig.serial
    assert cfg is not None, "a serial rig (bus.interface: dynamixel)"
    return dxl.cycle_budget(rig.n_joints, cfg.baudrate, rig.period_s, cfg.return_delay_us, cfg.host_latency_ms / 1000.0, cfg.read_mode)


class DynamixelDriver(Driver):
    """The rig's servo chain on ``port`` (default: the rig's ``bus.port``); on a simulated chain,
    ``progress`` is its count of what it has served (:mod:`drivers.line_progress`)."""

    def __init__(self, rig: Rig, port: str | None = None, progress: LineProgress | None = None) -> None:
        if rig.serial is None:
            raise DriveConfigError(f"{rig.source}: bus.interface is {rig.bus.interface!r}, not dynamixel")
        if (port or rig.serial.port) == "sim":
            raise DriveConfigError(f"{rig.source}: bus.port is 'sim': start the simulated chain (sim_bus.servo_chain) and pass its port")
        super().__init__(rig)
        cfg = rig.serial
        self.cfg = cfg
        self.port_name = port or cfg.port
        self.ids = [d.node_id for d in rig.drives]
        self.models = [dxl.SERVO_MODELS[d.model] for d in rig.drives]
        self.fast = cfg.read_mode == "fast_sync_read"
        self.budget = serial_budget(rig)
        self.reply_timeout_s = (cfg.reply_timeout_ms / 1000.0 if cfg.reply_timeout_ms is not None
                                else self.budget.reply_s + 2.0 * self.budget.host_latency_s + 0.002)
        self._lsb = np.array([m.current_lsb_a for m in self.models])
        self._counts_per_rad = np.array([u.counts_per_rad for u in self.units])
        self._velocity_lsb = np.array([m.velocity_lsb_rad_s for m in self.models]) / np.array([u.gear_ratio for u in self.units])
        self._limit_raw = np.array([m.current_limit for m in self.models], np.int64)
        self._serial: Any = None
        self._fd = -1
        self._rx = bytearray()
        self._requests: queue.Queue[tuple[Callable[[], Any], queue.Queue[Any]]] = queue.Queue()
        self._goal = np.zeros(self.n_joints, np.int64)  # current LSBs
        self._goal_position = np.zeros(self.n_joints, np.int64)
        self._position_mode = False
        self._stopped: set[int] = set()  # joints quick-stopped since the last enable
        self.torque_enabled = np.zeros(self.n_joints, bool)
        self.hardware_error = np.zeros(self.n_joints, np.int64)
        self._fail_run = np.zeros(self.n_joints, np.int64)
        self.errors_by_kind: dict[str, int] = {}
        self._clock = CycleClock(rig.period_s)
        self.noise_bytes = 0
        self.stale_replies = 0  # packets on the line that answered no request of ours (late replies), skipped
        self.stalled_waits = 0  # reply waits that overran their timeout while this process was not running (given a new window)
        self.progress = progress
        self.far_end_waits = 0  # reply windows shut before a simulated chain had served the request or its reply had come (given a new window)
        self._written = self._read = 0  # bytes on the line, each way
        self.reply_times: deque[float] = deque(maxlen=200_000)  # completion stamps (time.perf_counter)
        self.round_trips: deque[float] = deque(maxlen=200_000)  # read request sent -> reply complete (s)

    @property
    def late_cycles(self) -> int:
        """Cycles started more than a period late (the schedule restarted)."""
        return self._clock.late

    def waits_note(self) -> str:
        if not self.far_end_waits:
            return ""
        return (f"{self.far_end_waits} reply window{'s' if self.far_end_waits != 1 else ''} given again: the simulated chain or "
                "its pty was not scheduled in time (not a silent servo)")

    # --- the line ---
    def _open(self) -> None:
        import serial

        try:
            self._serial = serial.Serial(self.port_name, self.cfg.baudrate, timeout=0, write_timeout=0.1)
        except (serial.SerialException, OSError) as err:
            raise serial_open_error(self.port_name, err) from err
        self._fd = self._serial.fileno()
        if self.progress is not None:
            self.progress.start()

    def _send(self, packet: bytes) -> None:
        view = memoryview(packet)
        while view:
            try:
                n = os.write(self._fd, view)
            except BlockingIOError:
                select.select([], [self._fd], [], 0.01)
                continue
            self._written += n
            view = view[n:]

    def _receive(self, deadline: float, size: int | None = None, packet_id: int | None = None) -> bytes:
        """The next packet from its header: whole (``size`` bytes, or as its length field
        says), or what arrived of it by ``deadline`` (empty when nothing did). With
        ``packet_id``, whole packets of another id before it are stale (a late reply to an
        earlier request): they are skipped and counted in ``stale_replies``. A wait that
        overran its timeout, or began after it, by more than :data:`STALL_S` was this process
        not running: the line gets a new reply window (:data:`MAX_STALL_WAITS` at most), counted
        in ``stalled_waits``."""
        buf = self._rx
        stalls = 0
        while True:
            start = buf.find(dxl.HEADER)
            if start > 0 or (start < 0 and len(buf) > 3):
                skip = start if start > 0 else len(buf) - 3
                self.noise_bytes += skip
                del buf[:skip]
                start = buf.find(dxl.HEADER)
            if start == 0 and packet_id is not None and len(buf) > 4 and buf[4] != packet_id:
                n = dxl.packet_length(buf)
                if n is not None and not 10 <= n <= 4096:
                    self.noise_bytes += 4  # a header in noise, with no packet's length behind it
                    del buf[:4]
                    continue
                if n is not None and len(buf) >= n:
                    self.stale_replies += 1
                    del buf[:n]
                    continue
            elif start == 0:
                total = size if size is not None else dxl.packet_length(buf)
                if total is not None and len(buf) >= total:
                    out = bytes(buf[:total])
                    del buf[:total]
                    return out
            # bytes already on the line are read even past the deadline: a process descheduled
            # while the reply arrived must not call a reply that came in time a timeout
            asked = time.perf_counter()
            remaining = deadline - asked
            ready, _, _ = select.select([self._fd], [], [], max(0.0, remaining))
            if ready:
                try:
                    chunk = os.read(self._fd, 4096)
                except BlockingIOError:
                    chunk = b""
                if chunk:
                    self._read += len(chunk)
                    buf += chunk
                    continue
            now = time.perf_counter()
            # past its timeout while this process was not running: in the wait, or before it (a
            # process descheduled between the request and its read came to a window already shut)
            overran = now - asked - max(0.0, remaining) + max(0.0, -remaining)
            if now >= deadline and stalls < MAX_STALL_WAITS and overran > STALL_S:
                # a machine that pauses this process (a host's steal, SIGSTOP) paused the chain's
                # answer too: the line gets its reply window again, from when this process runs
                stalls += 1
                self.stalled_waits += 1
                self.last_stall = (time.monotonic(), overran)
                deadline = now + self.reply_timeout_s
                continue
            if now >= deadline and stalls < MAX_STALL_WAITS and self.progress is not None and self.progress.behind(self._written, self._read):
                # a simulated chain that has not yet served what this process wrote, or whose reply the
                # pty still holds, was not running (its CPU stopped by the host, the pty's kernel
                # worker not scheduled): its window again; a servo that does not answer is still
                # one the chain served without a reply
                stalls += 1
                self.far_end_waits += 1
                deadline = now + self.reply_timeout_s
                continue
            if remaining <= 0:
                out = bytes(buf) if start == 0 and (packet_id is None or len(buf) <= 4 or buf[4] == packet_id) else b""
                buf.clear()
                return out

    def _flush_input(self) -> None:
        """Stale bytes (a reply that came after its timeout) must not answer the next request."""
        self._rx.clear()
        while select.select([self._fd], [], [], 0)[0]:
            try:
                chunk = os.read(self._fd, 4096)
            except BlockingIOError:
                break
            if not chunk:
                break
            self._read += len(chunk)

    def _transact(self, servo_id: int, packet: bytes, timeout: float | None = None, attempts: int = ONE_OFF_ATTEMPTS,
                  data_length: int | None = None) -> dxl.Packet:
        """Send an instruction to one servo and return its status packet (or raise why not).

        One-off transactions (configuration, torque, reboot) are not on the cycle's clock:
        they wait at least ONE_OFF_TIMEOUT_S and are tried ``attempts`` times, since a reply
        lost on a half-duplex line is nothing to give up on (all of them are idempotent).
        Each attempt starts on an empty input, and only a status packet of ``servo_id``
        (with ``data_length`` bytes of data, when given, or an error) answers it: a stale
        reply still on the line (a Fast Sync Read that came after its timeout, another
        servo's late status) is skipped, counted in ``stale_replies``, and the wait goes on
        to the deadline."""
        wait = timeout if timeout is not None else max(self.reply_timeout_s, ONE_OFF_TIMEOUT_S)
        problem: ProtocolError | None = None
        for _attempt in range(attempts):
            self._flush_input()
            self._send(packet)
            deadline = time.perf_counter() + wait
            while True:
                raw = self._receive(deadline)
                if not raw:
                    if problem is None:
                        problem = ReplyTimeout(f"servo {servo_id}: no reply within {1e3 * wait:.1f} ms ({attempts} attempts)", servo_id)
                    break
                try:
                    reply = dxl.decode(raw, servo_id)
                except dxl.PartialPacket as err:
                    problem = err  # cut at the deadline: nothing follows it in this attempt
                    break
                except ProtocolError as err:
                    problem = err  # corrupted: another packet may still come before the deadline
                    continue
                if reply.id != servo_id or reply.instruction != dxl.Instruction.STATUS or (
                        data_length is not None and len(reply.data) != data_length and not reply.error & 0x7F):
                    self.stale_replies += 1
                    problem = dxl.MalformedPacket(f"servo {servo_id}: only a reply from id {reply.id} with instruction "
                                                  f"0x{reply.instruction:02X} and {len(reply.params)} parameter bytes "
                                                  f"(not the answer) within {1e3 * wait:.1f} ms ({attempts} attempts)", servo_id)
                    continue
                if reply.error & 0x7F:
                    raise StatusError(servo_id, reply.error)
                return reply
        assert problem is not None
        raise problem

    def _read_table(self, servo_id: int, address: int, length: int) -> bytes:
        data = self._transact(servo_id, dxl.read(servo_id, address, length), data_length=length).data
        if len(data) != length:
            raise dxl.MalformedPacket(f"servo {servo_id}: read of {length} bytes at {address} returned {len(data)}", servo_id)
        return data

    def _write_table(self, servo_id: int, address: int, data: bytes) -> None:
        self._transact(servo_id, dxl.write(servo_id, address, data), data_length=0)

    def _sync_write(self, address: int, values: list[bytes], joints: list[int] | None = None) -> None:
        """``values[k]`` to joint ``joints[k]`` (default: every joint, in order)."""
        joints = list(range(self.n_joints)) if joints is None else joints
        self._send(dxl.sync_write(address, [(self.ids[j], v) for j, v in zip(joints, values, strict=True)]))

    # --- start-up ---
    def _start(self) -> None:
        """Check the budget, open the port, configure every servo, start cycling (torque off)."""
        self._settings.fast_switching(self.period_s)  # put back by close()
        dxl.check_budget(self.budget)
        self._open()
        for j in range(self.n_joints):
            self.drive_configuration.append(self._configure(j))
        timing = self._settings.realtime()  # the port's thread, started next, inherits it
        # a full collection of the master's process held the interpreter for 80-155 ms (the
        # excitation command's, measured beside one busy core): 40 to 77 periods without a read.
        # What exists after start-up is never garbage (CanopenDriver.start does the same)
        self._settings.freeze()
        self.timing_note = timing.sentence("the port's cycle thread")
        self._thread = threading.Thread(target=self._run, name="armid-dynamixel", daemon=True)
        self._thread.start()

    def _where(self, j: int) -> str:
        return f"joint {j + 1} (servo {self.ids[j]} on {self.port_name})"

    def _configure(self, j: int) -> dict[str, int]:
        servo_id, model = self.ids[j], self.models[j]
        try:
            try:
                number = struct.unpack("<H", self._transact(servo_id, dxl.ping(servo_id), data_length=3).data[:2])[0]
            except ReplyTimeout as err:
                if isinstance(err, dxl.PartialPacket):
                    raise
                # not a byte from this id, each attempt: no such servo on the line (id, baud rate)
                raise DriveConfigError(f"{self._where(j)}: {err}: is servo {servo_id} on the line at "
                                       f"{self.cfg.baudrate:,} baud?") from err
            if number != model.number:
                found = next((m.name for m in dxl.SERVO_MODELS.values() if m.number == number), "unknown")
                raise DriveConfigError(f"{self._where(j)}: model number {number} ({found}), the rig {self.rig.source} says {model.name} ({model.number})")
            hardware = self._read_table(servo_id, Address.HARDWARE_ERROR_STATUS, 1)[0]
            if hardware:
                self._hardware_fault(j, hardware)
            self._write_table(servo_id, Address.TORQUE_ENABLE, b"\x00")
            self._write_table(servo_id, Address.RETURN_DELAY_TIME, bytes([self.cfg.return_delay_us // 2]))
            self._write_table(servo_id, Address.OPERATING_MODE, bytes([dxl.CURRENT_MODE]))
            back = self._read_table(servo_id, Address.RETURN_DELAY_TIME, 3)
            limit = struct.unpack("<H", self._read_table(servo_id, Address.CURRENT_LIMIT, 2))[0]
        except StatusError as err:  # the servo refused a value: the configuration's problem
            raise DriveConfigError(f"{self._where(j)}: {err}") from err
        except ProtocolError as err:  # the line failed under a servo that answered: a runtime fault, not bad input
            raise DriverError(f"{self._where(j)}: communication failed during start-up: {err}") from err
        if back[0] != self.cfg.return_delay_us // 2 or back[2] != dxl.CURRENT_MODE:
            raise DriveConfigError(f"{self._where(j)}: Return Delay Time / Operating Mode read back as {back[0]} / {back[2]}, "
                                   f"written {self.cfg.return_delay_us // 2} / {dxl.CURRENT_MODE}")
        self._limit_raw[j] = limit
        return {"model_number": number, "return_delay_time": back[0], "operating_mode": back[2], "current_limit": limit,
                "hardware_error_status": hardware}

    def _hardware_fault(self, j: int, bits: int) -> None:
        self.hardware_error[j] = bits
        self.torque_enabled[j] = False
        self._fault(DriveFault(j, self.ids[j], bits, f"{dxl.hardware_error_meaning(bits)}: the servo turned its torque off; enable() reboots it"),
                    "hardware_error")

    # --- cyclic ---
    def _run(self) -> None:
        self._clock = clock = CycleClock(self.period_s)  # the schedule starts with the thread
        while not self._stop.is_set():
            clock.wait()
            if clock.last_late[0] > self.last_stall[0]:
                self.last_stall = clock.last_late
            self._serve_requests()
            try:
                self._cycle_once()
            except OSError as err:  # the port went away (adapter unplugged)
                self._event("port", f"{self.port_name}: {err}")
                self._faults.put(DriveFault(0, self.ids[0], 0, f"serial port {self.port_name} failed: {err}"))
                time.sleep(0.1)

    def _serve_requests(self) -> None:
        while True:
            try:
                fn, reply = self._requests.get_nowait()
            except queue.Empty:
                return
            try:
                reply.put((True, fn()))
            except Exception as err:  # handed back to the caller
                reply.put((False, err))

    def _call(self, fn: Callable[[], Any], timeout: float) -> Any:
        """Run ``fn`` on the cycle thread between two cycles (only it touches the port)."""
        if self._thread is None or not self._thread.is_alive():
            return fn()
        reply: queue.Queue[Any] = queue.Queue()
        self._requests.put((fn, reply))
        try:
            ok, value = reply.get(timeout=timeout)
        except queue.Empty:
            raise DriverTimeout(f"{self.port_name}: the cycle thread did not serve a request within {timeout} s") from None
        if not ok:
            raise value
        return value

    def _cycle_once(self) -> None:
        if self._position_mode:
            self._sync_write(Address.GOAL_POSITION, [struct.pack("<i", int(v)) for v in self._goal_position])
        else:
            self._sync_write(Address.GOAL_CURRENT, [struct.pack("<h", int(v)) for v in self._goal])
        self._flush_input()
        address, length = dxl.PRESENT_BLOCK
        self._send(dxl.sync_read(self.ids, address, length, fast=self.fast))
        sent = time.perf_counter()
        deadline = sent + self.reply_timeout_s
        if self.fast:
            raw = self._receive(deadline, dxl.fast_sync_read_size(self.n_joints, length), packet_id=dxl.BROADCAST_ID)
            blocks = dxl.decode_fast_sync_read(raw, self.ids, length)
        else:
            blocks = [self._sync_read_block(servo_id, length, deadline) for servo_id in self.ids]
        done = time.perf_counter()
        self.reply_times.append(done)
        self.round_trips.append(done - sent)
        self._cycle += 1
        s = self._open_record(self._cycle, time.time())  # a servo without a usable block keeps its last values
        alerts = []
        for j, b in enumerate(blocks):
            if b.ok:
                current, velocity, position = dxl.PRESENT_FORMAT.unpack(b.data)
                s.position[j] = position / self._counts_per_rad[j]
                s.velocity[j] = velocity * self._velocity_lsb[j]
                s.measured_current[j] = current * self._lsb[j]
                s.velocity_fresh[j] = s.valid[j] = True
                s.status[j] = int(self.hardware_error[j]) << 8 | b.error
                if b.error & dxl.ALERT and not self.hardware_error[j]:
                    alerts.append(j)
                if b.error & 0x7F:
                    self._event("status_error", f"{self._where(j)}: {dxl.status_error_meaning(b.error)}", j)
                if self._fail_run[j]:
                    self._event("reply_back", f"{self._where(j)}: answers again after {self._fail_run[j]} cycles without a usable reply", j)
                    self._fail_run[j] = 0
                if self._silent[j]:
                    self._silent[j] = False
            else:
                assert b.problem is not None
                kind = type(b.problem).__name__
                self.errors_by_kind[kind] = self.errors_by_kind.get(kind, 0) + 1
                self.lost_cycles[j] += 1
                if not self._fail_run[j]:
                    self._event("reply", f"{self._where(j)}: {kind}: {b.problem}", j)
                self._fail_run[j] += 1
                if self._fail_run[j] == self.cfg.silent_cycles and not self._silent[j]:
                    self._silent[j] = True
                    self._declare_lost(j, ServoLost(j, self.ids[j], 0x8130, f"no usable reply for {self.cfg.silent_cycles} cycles "
                                                                            f"({b.problem}); the other servos were quick-stopped"), "servo_lost")
        for j in alerts:  # what the alert is about: one read, on the cycle thread
            try:
                bits = self._read_table(self.ids[j], Address.HARDWARE_ERROR_STATUS, 1)[0]
                self._hardware_fault(j, bits)
                s.status[j] = bits << 8 | (int(s.status[j]) & 0xFF)
            except ProtocolError as err:
                self._event("reply", f"{self._where(j)}: alert set, but Hardware Error Status could not be read: {err}", j)
        self._publish(s)

    def _sync_read_block(self, servo_id: int, length: int, deadline: float) -> dxl.Block:
        raw = self._receive(deadline)
        if not raw:
            return dxl.Block(servo_id, problem=ReplyTimeout(f"servo {servo_id}: no status packet within the reply timeout", servo_id))
        try:
            p = dxl.decode(raw, servo_id)
        except ProtocolError as err:
            return dxl.Block(servo_id, problem=err)
        if p.id != servo_id or len(p.data) != length:
            # a servo missing in the middle: the packet is the next one's; keep it for them
            if p.id in self.ids[self.ids.index(servo_id) + 1:]:
                self._rx[:0] = raw
            return dxl.Block(servo_id, problem=dxl.MalformedPacket(f"servo {servo_id}: got a packet from id {p.id} with {len(p.data)} bytes", servo_id))
        return dxl.Block(servo_id, p.error, p.data)

    # --- the interface ---
    @property
    def silent_limit_s(self) -> float:
        """The rig's ``bus.silent_cycles`` in seconds: a servo silent that long is declared lost."""
        return self.cfg.silent_cycles * self.period_s

    def read(self, timeout: float | None = None) -> Sample:
        return self._next_sample(timeout, f"is {self.port_name} cycling?")

    def _command_torque(self, tau: Array) -> None:
        raw = np.clip(np.round(tau / self.torque_constants / self._lsb), -self._limit_raw, self._limit_raw).astype(np.int64)
        if self._stopped:
            raw[list(self._stopped)] = 0
        self._goal = raw
        self._commanded = raw * self._lsb
        if self._position_mode:
            self._call(lambda: self._switch_mode(dxl.CURRENT_MODE), 1.0)

    def _command_position(self, q: Array) -> None:
        self._goal_position = np.round(q * self._counts_per_rad).astype(np.int64)
        if not self._position_mode:
            self._call(lambda: self._switch_mode(dxl.POSITION_MODE), 1.0)

    def _switch_mode(self, mode: int) -> None:
        """Operating Mode is EEPROM: torque off, mode, goal, torque back on where it was."""
        on = [j for j in range(self.n_joints) if self.torque_enabled[j]]
        self._sync_write(Address.TORQUE_ENABLE, [b"\x00"] * self.n_joints)
        self._sync_write(Address.OPERATING_MODE, [bytes([mode])] * self.n_joints)
        self._position_mode = mode == dxl.POSITION_MODE
        if self._position_mode:
            self._sync_write(Address.GOAL_POSITION, [struct.pack("<i", int(v)) for v in self._goal_position])
        if on:
            self._sync_write(Address.TORQUE_ENABLE, [b"\x01"] * len(on), on)

    def enable(self, timeout: float = 1.0) -> None:
        """Reboot servos with a hardware error, zero the goals, torque on, read back.
        ``timeout`` is for the transactions; each reboot may add REBOOT_WAIT_S."""
        self._call(self._enable, timeout + REBOOT_WAIT_S * self.n_joints + 1.0)

    def _enable(self) -> None:
        for j in range(self.n_joints):
            if self.hardware_error[j]:
                servo_id = self.ids[j]
                try:
                    self._transact(servo_id, dxl.reboot(servo_id), data_length=0)
                    deadline = time.perf_counter() + REBOOT_WAIT_S
                    while True:
                        try:
                            self._transact(servo_id, dxl.ping(servo_id), attempts=1, data_length=3)
                            break
                        except ProtocolError:
                            if time.perf_counter() > deadline:
                                raise
                    bits = self._read_table(servo_id, Address.HARDWARE_ERROR_STATUS, 1)[0]
                except ProtocolError as err:
                    raise DriverError(f"{self._where(j)}: reboot failed: {err}") from err
                if bits:
                    raise DriverError(f"{self._where(j)}: still {dxl.hardware_error_meaning(bits)} after a reboot")
                self.hardware_error[j] = 0
                self._event("rebooted", f"{self._where(j)}: rebooted, hardware error cleared", j)
        self._goal[:] = 0
        self._commanded[:] = 0
        self._stopped.clear()
        self._sync_write(Address.GOAL_CURRENT, [b"\x00\x00"] * self.n_joints)
        bad = []
        for j in range(self.n_joints):
            try:
                self._write_table(self.ids[j], Address.TORQUE_ENABLE, b"\x01")
                if self._read_table(self.ids[j], Address.TORQUE_ENABLE, 1)[0] != 1:
                    bad.append(f"{self._where(j)}: Torque Enable reads back 0")
            except ProtocolError as err:
                bad.append(f"{self._where(j)}: {err}")
        if bad:
            self._sync_write(Address.TORQUE_ENABLE, [b"\x00"] * self.n_joints)
            raise DriverError("servos not enabled (all torque off again): " + "; ".join(bad))
        self.torque_enabled[:] = True

    def disable(self) -> None:
        self.command_torque(np.zeros(self.n_joints))

        def off() -> None:
            self._sync_write(Address.TORQUE_ENABLE, [b"\x00"] * self.n_joints)
            self.torque_enabled[:] = False

        self._call(off, 1.0)

    def quick_stop(self, joints: list[int] | None = None) -> None:
        """Goal current 0 now, torque off before the next cycle (on the simulated chain, a
        brake holds; an arm without brakes needs its own holding strategy)."""
        joints = list(range(self.n_joints)) if joints is None else list(joints)
        self._stopped.update(joints)
        goal = self._goal.copy()
        goal[joints] = 0
        self._goal = goal
        self._commanded = goal * self._lsb

        def off() -> None:
            self._sync_write(Address.TORQUE_ENABLE, [b"\x00"] * len(joints), joints)
            self.torque_enabled[joints] = False

        if threading.current_thread() is self._thread:
            off()
        else:
            self._requests.put((off, queue.Queue()))

    def _close(self) -> None:
        if self._serial is not None:
            self._serial.close()
            self._serial = None

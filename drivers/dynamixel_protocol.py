"""ROBOTIS Dynamixel Protocol 2.0: packets, CRC, byte stuffing, the X series' control table,
and the serial line's time budget.

Bytes in, bytes out: the driver (:mod:`drivers.dynamixel_driver`) and the simulated servo
chain (:mod:`sim_bus.servo_chain`) share these functions, and nothing here does I/O.

A packet is ``FF FF FD 00 | id | length (u16 LE) | instruction | parameters | CRC (u16 LE)``,
where ``length`` counts instruction, parameters and CRC, the parameters are byte-stuffed
(``FF FF FD`` is followed by an extra ``FD``, so that a header never appears inside a
packet), and the CRC is CRC-16 with polynomial 0x8005, initial value 0, not reflected
(CRC-16/BUYPASS), over everything before it. A status packet's first parameter is its
error field: bit 7 is the alert (a hardware error, see Hardware Error Status), bits 0-6
the error number.

Fast Sync Read is answered by the whole chain as one packet with id 0xFE: per servo
``error | id | data | CRC``, each CRC covering every byte of the packet before it (the last
one is the packet's CRC), so a corrupted or missing servo costs its own block and those
after it, not the ones before; its blocks are not stuffed.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum

from armid.schema.errors import (  # noqa: F401  (re-exported: the protocol's errors)
    CrcError,
    DriveConfigError,
    DriverError,
    MalformedPacket,
    PartialPacket,
    ProtocolError,
    ReplyTimeout,
    SerialBudgetError,
)

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
MAX_ID = 252
BITS_PER_BYTE = 10  # 8N1: start bit, 8 data bits, stop bit
ALERT = 0x80


class Instruction(IntEnum):
    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REBOOT = 0x08
    STATUS = 0x55
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83
    FAST_SYNC_READ = 0x8A


class Address(IntEnum):
    """The X series' control table (XM430, XM540, XH430, XH540: the same layout)."""

    MODEL_NUMBER = 0  # u16
    FIRMWARE_VERSION = 6  # u8
    ID = 7  # u8
    BAUD_RATE = 8  # u8, a code: BAUD_CODES
    RETURN_DELAY_TIME = 9  # u8, 2 us units
    OPERATING_MODE = 11  # u8: 0 current, 1 velocity, 3 position
    CURRENT_LIMIT = 38  # u16, current LSBs
    VELOCITY_LIMIT = 44  # u32
    MAX_POSITION_LIMIT = 48  # u32
    MIN_POSITION_LIMIT = 52  # u32
    TORQUE_ENABLE = 64  # u8; EEPROM (addresses < 64) is writable only with torque off
    STATUS_RETURN_LEVEL = 68  # u8
    HARDWARE_ERROR_STATUS = 70  # u8, HARDWARE_ERRORS bits
    GOAL_CURRENT = 102  # s16
    GOAL_VELOCITY = 104  # s32
    GOAL_POSITION = 116  # s32
    REALTIME_TICK = 120  # u16, ms
    PRESENT_CURRENT = 126  # s16
    PRESENT_VELOCITY = 128  # s32
    PRESENT_POSITION = 132  # s32
    PRESENT_INPUT_VOLTAGE = 144  # u16, 0.1 V
    PRESENT_TEMPERATURE = 146  # u8, deg C


CURRENT_MODE, VELOCITY_MODE, POSITION_MODE = 0, 1, 3
PRESENT_BLOCK = (int(Address.PRESENT_CURRENT), 10)  # current, velocity, position: read every cycle
PRESENT_FORMAT = struct.Struct("<hii")
CONTROL_TABLE_SIZE = 147

BAUD_CODES = {0: 9_600, 1: 57_600, 2: 115_200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000, 6: 4_000_000, 7: 4_500_000}

STATUS_ERRORS = {
    1: "result fail: the servo could not process the instruction",
    2: "instruction error: undefined instruction, or Action without Reg Write",
    3: "CRC error: the servo received a corrupted instruction",
    4: "data range error: a value out of range",
    5: "data length error: data shorter than the address needs",
    6: "data limit error: a value beyond its limit",
    7: "access error: address not writable or not readable, or EEPROM written with torque on",
}

HARDWARE_ERRORS = {
    0: "input voltage error",
    2: "overheating error",
    3: "motor encoder error",
    4: "electrical shock error",
    5: "overload error",
}


def hardware_error_meaning(bits: int) -> str:
    names = [text for bit, text in HARDWARE_ERRORS.items() if bits & (1 << bit)]
    return ", ".join(names) if names else f"hardware error status 0x{bits:02X}"


def status_error_meaning(error: int) -> str:
    number = error & 0x7F
    text = STATUS_ERRORS.get(number, f"error number {number}") if number else ""
    if error & ALERT:
        text = (text + "; " if text else "") + "alert: hardware error (read Hardware Error Status)"
    return text or "no error"


@dataclass(frozen=True)
class ServoModel:
    """A servo model's identity and units (ROBOTIS e-Manual, X series control tables)."""

    name: str
    number: int  # Model Number (address 0)
    current_lsb_a: float  # Goal/Present Current unit
    velocity_lsb_rad_s: float  # Present Velocity unit: 0.229 rev/min
    counts_per_rev: int  # Present Position increments per output revolution
    current_limit: int  # default Current Limit, in current LSBs

    @property
    def max_current_a(self) -> float:
        return self.current_limit * self.current_lsb_a


_RPM = 0.229 * 2.0 * math.pi / 60.0
SERVO_MODELS = {m.name: m for m in (
    ServoModel("XM430-W350", 1020, 2.69e-3, _RPM, 4096, 1193),
    ServoModel("XM430-W210", 1030, 2.69e-3, _RPM, 4096, 1193),
    ServoModel("XM540-W270", 1120, 2.69e-3, _RPM, 4096, 2047),
    ServoModel("XM540-W150", 1130, 2.69e-3, _RPM, 4096, 2047),
    ServoModel("XH430-W350", 1010, 1.34e-3, _RPM, 4096, 648),
    ServoModel("XH540-W270", 1110, 2.69e-3, _RPM, 4096, 2047),
)}


# --- errors ---
class StatusError(ProtocolError):
    """The servo answered with a non-zero error number (see STATUS_ERRORS)."""

    def __init__(self, servo_id: int, error: int) -> None:
        self.error = error
        super().__init__(f"servo {servo_id}: {status_error_meaning(error)} (error field 0x{error:02X})", servo_id)


# --- CRC and stuffing ---
def _crc_table() -> tuple[int, ...]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else crc << 1
        table.append(crc & 0xFFFF)
    return tuple(table)


CRC_TABLE = _crc_table()


def crc16(data: bytes | bytearray | memoryview, crc: int = 0) -> int:
    """CRC-16 of Protocol 2.0 (polynomial 0x8005, initial 0, MSB first), continued from ``crc``."""
    table = CRC_TABLE
    for byte in bytes(data):
        crc = ((crc << 8) ^ table[((crc >> 8) ^ byte) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """Insert ``FD`` after every ``FF FF FD`` so that no header appears inside a packet."""
    if b"\xff\xff\xfd" not in body:
        return body
    out = bytearray()
    for byte in body:
        out.append(byte)
        if byte == 0xFD and out[-3:-1] == b"\xff\xff":
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    """Undo :func:`stuff`: drop the ``FD`` that follows each ``FF FF FD``."""
    if b"\xff\xff\xfd\xfd" not in body:
        return body
    out = bytearray()
    i = 0
    while i < len(body):
        out.append(body[i])
        if body[i] == 0xFD and i >= 2 and body[i - 2:i] == b"\xff\xff" and i + 1 < len(body) and body[i + 1] == 0xFD:
            i += 1  # the stuffed FD
        i += 1
    return bytes(out)


# --- packets ---
@dataclass(frozen=True)
class Packet:
    """A decoded packet; ``params`` unstuffed. For a status packet ``error`` and ``data``."""

    id: int
    instruction: int
    params: bytes

    @property
    def error(self) -> int:
        return self.params[0] if self.instruction == Instruction.STATUS and self.params else 0

    @property
    def data(self) -> bytes:
        return self.params[1:] if self.instruction == Instruction.STATUS else self.params


def encode(packet_id: int, instruction: int, params: bytes = b"") -> bytes:
    """One packet, stuffed, with its CRC."""
    if not 0 <= packet_id <= BROADCAST_ID:
        raise ValueError(f"packet id must be 0..{BROADCAST_ID}, got {packet_id}")
    body = stuff(bytes([instruction]) + bytes(params))
    length = len(body) + 2
    head = HEADER + bytes([packet_id, length & 0xFF, length >> 8]) + body
    return head + crc16(head).to_bytes(2, "little")


def encode_status(servo_id: int, error: int, data: bytes = b"") -> bytes:
    return encode(servo_id, Instruction.STATUS, bytes([error]) + bytes(data))


def packet_length(buffer: bytes | bytearray, start: int = 0) -> int | None:
    """Bytes of the packet that starts at ``start`` (None until its length field is in)."""
    if len(buffer) - start < 7:
        return None
    return 7 + (buffer[start + 5] | buffer[start + 6] << 8)


def decode(frame: bytes, servo_id: int | None = None) -> Packet:
    """Check and decode one whole packet (header, length, CRC); unstuffs its parameters."""
    who = f"servo {servo_id}" if servo_id is not None else "packet"
    if frame[:4] != HEADER[:len(frame)] or len(frame) < 4:
        raise MalformedPacket(f"{who}: {len(frame)} bytes that do not start with a Protocol 2.0 header ({frame[:8].hex(' ')})", servo_id)
    n = packet_length(frame)
    if n is None or len(frame) < n:
        need = "at least 10" if n is None else str(n)
        raise PartialPacket(f"{who}: {len(frame)} of {need} bytes", servo_id)
    if len(frame) < n:
        raise PartialPacket(f"{who}: {len(frame)} of {n} bytes", servo_id)
    if n < 10:
        raise MalformedPacket(f"{who}: length field {n - 7} is shorter than instruction and CRC", servo_id)
    frame = frame[:n]
    got, want = int.from_bytes(frame[-2:], "little"), crc16(frame[:-2])
    if got != want:
        raise CrcError(f"{who}: CRC 0x{got:04X} in the packet, 0x{want:04X} computed over its {n - 2} bytes", servo_id)
    return Packet(frame[4], frame[7], unstuff(frame[8:-2]))


def split_packets(buffer: bytearray) -> list[Packet | ProtocolError]:
    """Take every whole packet (or the error it makes) from the front of ``buffer``; bytes
    before a header are skipped, an incomplete packet stays in the buffer."""
    out: list[Packet | ProtocolError] = []
    while True:
        start = buffer.find(HEADER[:3])
        if start < 0:
            del buffer[: max(0, len(buffer) - 2)]  # keep a possible header start
            return out
        if start:
            del buffer[:start]
        n = packet_length(buffer)
        if n is None or len(buffer) < n:
            return out
        if n < 10 or n > 4096:
            out.append(MalformedPacket(f"length field {n - 7} is not a packet's"))
            del buffer[:3]
            continue
        frame = bytes(buffer[:n])
        del buffer[:n]
        try:
            out.append(decode(frame))
        except ProtocolError as err:
            out.append(err)


# --- instructions ---
def ping(servo_id: int) -> bytes:
    return encode(servo_id, Instruction.PING)


def read(servo_id: int, address: int, length: int) -> bytes:
    return encode(servo_id, Instruction.READ, struct.pack("<HH", address, length))


def write(servo_id: int, address: int, data: bytes) -> bytes:
    return encode(servo_id, Instruction.WRITE, struct.pack("<H", address) + bytes(data))


def reboot(servo_id: int) -> bytes:
    return encode(servo_id, Instruction.REBOOT)


def sync_read(ids: list[int], address: int, length: int, fast: bool = True) -> bytes:
    instruction = Instruction.FAST_SYNC_READ if fast else Instruction.SYNC_READ
    return encode(BROADCAST_ID, instruction, struct.pack("<HH", address, length) + bytes(ids))


def sync_write(address: int, items: list[tuple[int, bytes]]) -> bytes:
    length = len(items[0][1]) if items else 0
    if any(len(data) != length for _, data in items):
        raise ValueError("sync write: every servo's data must have the same length")
    params = struct.pack("<HH", address, length) + b"".join(bytes([i]) + bytes(d) for i, d in items)
    return encode(BROADCAST_ID, Instruction.SYNC_WRITE, params)


def fast_sync_read_reply(blocks: list[tuple[int, int, bytes]], n_servos: int | None = None) -> bytes:
    """The chain's answer to a Fast Sync Read: ``blocks`` are (error, id, data) in request
    order. The length field is the whole chain's (``n_servos``, default all blocks): the
    first servo writes it, so a servo that stays silent leaves the packet short of it."""
    data_length = len(blocks[0][2]) if blocks else 0
    length = 1 + (len(blocks) if n_servos is None else n_servos) * (4 + data_length)
    out = bytearray(HEADER + bytes([BROADCAST_ID, length & 0xFF, length >> 8, Instruction.STATUS]))
    for error, servo_id, data in blocks:
        out += bytes([error, servo_id]) + bytes(data)
        out += crc16(out).to_bytes(2, "little")
    return bytes(out)


def fast_sync_read_size(n_servos: int, length: int) -> int:
    return 8 + n_servos * (4 + length)


@dataclass(frozen=True)
class Block:
    """One servo's part of a sync read: its error field and data, or why it is unusable."""

    servo_id: int
    error: int = 0
    data: bytes = b""
    problem: ProtocolError | None = None

    @property
    def ok(self) -> bool:
        return self.problem is None


def decode_fast_sync_read(raw: bytes, ids: list[int], length: int) -> list[Block]:
    """Split a Fast Sync Read reply (starting at its header) into per-servo blocks, each
    checked by its cumulative CRC; a block that is missing, cut or corrupted says which."""
    blocks: list[Block] = []
    if len(raw) < 8:
        why = ReplyTimeout if not raw else PartialPacket
        return [Block(i, problem=why(f"servo {i}: Fast Sync Read reply has {len(raw)} bytes, no block", i)) for i in ids]
    if raw[:5] != HEADER + bytes([BROADCAST_ID]) or raw[7] != Instruction.STATUS:
        return [Block(i, problem=MalformedPacket(f"servo {i}: not a Fast Sync Read reply ({raw[:8].hex(' ')})", i)) for i in ids]
    declared = 7 + (raw[5] | raw[6] << 8)
    expected = fast_sync_read_size(len(ids), length)
    if declared != expected:
        return [Block(i, problem=MalformedPacket(f"servo {i}: reply declares {declared} bytes, {len(ids)} servos x {length} need {expected}", i)) for i in ids]
    crc = crc16(raw[:8])
    offset = 8
    broken: ProtocolError | None = None
    for k, servo_id in enumerate(ids):
        end = offset + 4 + length
        if broken is not None:
            blocks.append(Block(servo_id, problem=type(broken)(f"servo {servo_id}: no usable block (servo {broken.servo_id}'s came first: {broken})", servo_id)))
            continue
        if len(raw) < end:
            have = max(0, len(raw) - offset)
            cls = PartialPacket if have else ReplyTimeout
            broken = cls(f"servo {servo_id}: block {k + 1} of {len(ids)} has {have} of {4 + length} bytes", servo_id)
            blocks.append(Block(servo_id, problem=broken))
            continue
        crc = crc16(raw[offset:end - 2], crc)
        got = int.from_bytes(raw[end - 2:end], "little")
        error, who = raw[offset], raw[offset + 1]
        if got != crc:
            blocks.append(Block(servo_id, problem=CrcError(f"servo {servo_id}: block CRC 0x{got:04X}, 0x{crc:04X} computed", servo_id)))
        elif who != servo_id:
            blocks.append(Block(servo_id, problem=MalformedPacket(f"servo {servo_id}: block {k + 1} carries id {who}", servo_id)))
        else:
            blocks.append(Block(servo_id, error, bytes(raw[offset + 2:end - 2])))
        crc = crc16(raw[end - 2:end], crc)
        offset = end
    return blocks


# --- the line's time budget ---
@dataclass(frozen=True)
class SerialBudget:
    """What one cycle costs on a half-duplex line: a Sync Write of the goal currents (no
    reply) and a (Fast) Sync Read of the present values, with the servos' return delay and
    the host's turnaround (a USB-serial adapter's latency timer)."""

    n_servos: int
    baudrate: int
    return_delay_s: float
    host_latency_s: float
    period_s: float
    read_mode: str
    write_bytes: int
    request_bytes: int
    reply_bytes: int
    usable_fraction: float = 0.8

    @property
    def byte_s(self) -> float:
        return BITS_PER_BYTE / self.baudrate

    @property
    def wire_s(self) -> float:
        return (self.write_bytes + self.request_bytes + self.reply_bytes) * self.byte_s

    @property
    def delay_s(self) -> float:
        """Return delays: once for a Fast Sync Read (the chain answers as one packet), once
        per servo for a Sync Read (each waits after the one before)."""
        return self.return_delay_s * (1 if self.read_mode == "fast_sync_read" else self.n_servos)

    @property
    def cycle_s(self) -> float:
        return self.wire_s + self.delay_s + self.host_latency_s

    @property
    def reply_s(self) -> float:
        """From the end of the read request to the reply's last byte, on the line."""
        return self.delay_s + self.reply_bytes * self.byte_s

    @property
    def feasible(self) -> bool:
        return self.cycle_s <= self.usable_fraction * self.period_s

    def describe(self) -> str:
        return (f"{self.n_servos} servos at {self.baudrate:,} baud, {self.read_mode}: "
                f"{self.write_bytes + self.request_bytes + self.reply_bytes} bytes on the line "
                f"({self.write_bytes} sync write + {self.request_bytes} request + {self.reply_bytes} reply) = {1e3 * self.wire_s:.3f} ms, "
                f"return delay {1e3 * self.delay_s:.3f} ms, host latency {1e3 * self.host_latency_s:.3f} ms: "
                f"{1e3 * self.cycle_s:.3f} ms of the {1e3 * self.period_s:.3f} ms period ({100 * self.cycle_s / self.period_s:.0f} %)")


def cycle_budget(n_servos: int, baudrate: int, period_s: float, return_delay_us: float = 0.0, host_latency_s: float = 0.0,
                 read_mode: str = "fast_sync_read", read_length: int = PRESENT_BLOCK[1], write_length: int = 2) -> SerialBudget:
    """The budget of one cycle (see :class:`SerialBudget`)."""
    if read_mode not in ("fast_sync_read", "sync_read"):
        raise ValueError(f"read mode must be fast_sync_read or sync_read, got {read_mode!r}")
    write_bytes = 14 + n_servos * (1 + write_length)
    request_bytes = 14 + n_servos
    if read_mode == "fast_sync_read":
        reply_bytes = fast_sync_read_size(n_servos, read_length)
    else:
        reply_bytes = n_servos * (11 + read_length)
    return SerialBudget(n_servos, baudrate, return_delay_us * 1e-6, host_latency_s, period_s, read_mode, write_bytes, request_bytes, reply_bytes)


def check_budget(budget: SerialBudget) -> SerialBudget:
    """Refuse a period the line cannot keep, with the numbers and what would help."""
    if not budget.feasible:
        fastest = cycle_budget(budget.n_servos, max(BAUD_CODES.values()), budget.period_s, 0.0, budget.host_latency_s, "fast_sync_read")
        raise SerialBudgetError(
            f"period {1e3 * budget.period_s:g} ms is not feasible: {budget.describe()}, more than {100 * budget.usable_fraction:.0f} % "
            f"of the period. Raise the baud rate, set the return delay time to 0, use fast_sync_read, or lengthen the period "
            f"(at 4.5 Mbaud, no return delay, fast sync read: {1e3 * fastest.cycle_s:.3f} ms)")
    return budget

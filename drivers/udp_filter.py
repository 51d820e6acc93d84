"""A kernel filter for a ``udp_multicast`` bus: a process does not receive the frames it sends.

On python-can's ``udp_multicast`` every member of the group, the sender included, gets every
datagram back (multicast loop-back is how processes on one host hear each other), and each
received frame costs the Python side about 60 us (select, receive, msgpack, ``can.Message``,
the notifier, canopen's dispatch). With a simulated six-axis arm at 2 ms, 16 frames a cycle,
the simulator and the master each spent a fifth to a quarter of a core on the 7-9 frames a
cycle they had sent themselves, on a 2-core machine where the two lost cycles (issue 31). A classic BPF socket filter drops them in the
kernel, as SocketCAN's ``CAN_RAW_FILTER`` would.

The filter reads python-can's wire format (a msgpack map whose first entries are
``timestamp`` as a float64 and ``arbitration_id``) and drops a datagram only when that prefix
is exactly as expected and its standard (11-bit) identifier is one of the given ones; any other
datagram is kept. A change of format therefore costs the saving, never a frame.
"""

from __future__ import annotations

import ctypes
import socket
import struct
import sys
from collections.abc import Iterable

import can

SO_ATTACH_FILTER = 26  # linux/socket.h
PAYLOAD = 8  # the filter sees the datagram from its UDP header
KEEP, DROP = 0xFFFFFFFF, 0

# classic BPF opcodes (linux/filter.h)
_LD_W, _LD_H, _LD_B = 0x20, 0x28, 0x30  # BPF_LD | size | BPF_ABS
_JEQ, _JGE, _JA, _RET = 0x15, 0x35, 0x05, 0x06  # BPF_JMP | op | BPF_K; BPF_RET | BPF_K

# python-can's pack_message: {"timestamp": <float64>, "arbitration_id": <uint>, "is_extended_id": <bool>, ...}
_PREFIX = b"\x8b\xa9timestamp\xcb"  # an 11-entry map, the key, the float64 marker
_ID_KEY = b"\xaearbitration_id"
_EXT_KEY_LEN = 15  # b"\xaeis_extended_id"
_FALSE = 0xC2


def master_frames(node_ids: Iterable[int], master_id: int) -> list[int]:
    """What a CANopen master sends at the predefined connection set's identifiers: NMT, SYNC,
    its heartbeat, and to each node its RPDOs 1-4 and SDO requests."""
    return [0x000, 0x080, 0x700 + master_id] + [base + n for n in node_ids for base in (0x200, 0x300, 0x400, 0x500, 0x600)]


def drive_frames(node_ids: Iterable[int]) -> list[int]:
    """What CANopen drives send at the predefined connection set's identifiers: EMCY, TPDOs
    1-4, SDO responses, heartbeat (a PDO moved to another identifier is simply not filtered)."""
    return [base + n for n in node_ids for base in (0x080, 0x180, 0x280, 0x380, 0x480, 0x580, 0x700)]


def drop_own_frames(bus: can.BusABC, cob_ids: Iterable[int]) -> bool:
    """Attach to ``bus`` a socket filter that drops datagrams carrying one of ``cob_ids``
    (standard identifiers: each has one sender on a CAN bus, here this process). Returns
    whether it is attached: only ``udp_multicast`` buses on Linux take one."""
    ids = sorted({int(c) for c in cob_ids})
    if not ids or not sys.platform.startswith("linux") or "UdpMulticastBus" not in {c.__name__ for c in type(bus).__mro__}:
        return False
    if len(ids) > 250:  # a conditional jump reaches 255 instructions
        return False
    program = _program(ids)
    code = (ctypes.c_ubyte * (8 * len(program)))(*b"".join(struct.pack("HBBI", *ins) for ins in program))
    fprog = struct.pack("HL", len(program), ctypes.addressof(code))
    sock = socket.socket(fileno=bus.fileno())
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, fprog)
    except OSError:
        return False
    finally:
        sock.detach()  # the bus owns the descriptor
    return True


def _program(ids: list[int]) -> list[tuple[int, int, int, int]]:
    """The filter: check the wire format's prefix, read the identifier in whichever width
    msgpack gave it (fixint, uint8, uint16), keep extended frames, drop the listed ids."""
    asm = _Assembler()
    for offset in range(0, 12, 4):  # the prefix is 12 bytes: three words
        asm.load(_LD_W, PAYLOAD + offset)
        asm.unless_equal(int.from_bytes(_PREFIX[offset:offset + 4], "big"), "keep")
    key = PAYLOAD + 20  # after the 9 bytes of the float64
    for offset in range(0, 12, 4):
        asm.load(_LD_W, key + offset)
        asm.unless_equal(int.from_bytes(_ID_KEY[offset:offset + 4], "big"), "keep")
    asm.load(_LD_H, key + 12)
    asm.unless_equal(int.from_bytes(_ID_KEY[12:14], "big"), "keep")
    asm.load(_LD_B, key + 14)
    asm.unless_equal(_ID_KEY[14], "keep")
    marker = key + 15
    for width, (tag, load) in enumerate(((None, _LD_B), (0xCC, _LD_B), (0xCD, _LD_H))):
        value = marker + (1 if tag else 0)
        asm.load(_LD_B, marker)
        if tag is None:
            asm.jump_if(_JGE, 0x80, f"width{width + 1}")  # not a positive fixint
        else:
            asm.unless_equal(tag, f"width{width + 1}")
        size = (1, 2, 3)[width]
        asm.load(_LD_B, marker + size + _EXT_KEY_LEN)
        asm.unless_equal(_FALSE, "keep")  # an extended frame, or not the layout known
        asm.load(load, value)
        asm.jump("compare")
        asm.label(f"width{width + 1}")
    asm.jump("keep")  # wider than 16 bits: not a standard identifier
    asm.label("compare")
    for cob in ids:
        asm.jump_if(_JEQ, cob, "drop")
    asm.label("keep")
    asm.ret(KEEP)
    asm.label("drop")
    asm.ret(DROP)
    return asm.resolve()


class _Assembler:
    """Classic BPF with forward jumps to labels (conditional jumps reach 255 instructions)."""

    def __init__(self) -> None:
        self.code: list[tuple[int, str | None, str | None, int]] = []
        self.labels: dict[str, int] = {}

    def load(self, op: int, offset: int) -> None:
        self.code.append((op, None, None, offset))

    def unless_equal(self, value: int, target: str) -> None:
        self.code.append((_JEQ, None, target, value))

    def jump_if(self, op: int, value: int, target: str) -> None:
        self.code.append((op, target, None, value))

    def jump(self, target: str) -> None:
        self.code.append((_JA, target, None, 0))

    def ret(self, value: int) -> None:
        self.code.append((_RET, None, None, value))

    def label(self, name: str) -> None:
        self.labels[name] = len(self.code)

    def resolve(self) -> list[tuple[int, int, int, int]]:
        """The program with each label made the relative offset its jumps need."""
        out = []
        for pc, (op, jt, jf, k) in enumerate(self.code):
            if op == _JA:
                out.append((op, 0, 0, self._offset(jt, pc)))
            else:
                out.append((op, self._offset(jt, pc), self._offset(jf, pc), k))
        return out

    def _offset(self, target: str | None, pc: int) -> int:
        return 0 if target is None else self.labels[target] - pc - 1

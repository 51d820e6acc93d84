"""The CANopen standards' codes in one place: EMCY meanings (CiA 301/402), NMT states as a
heartbeat carries them, the CiA 402 statusword's state bits, and the signed types a PDO maps."""

from __future__ import annotations

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable

NMT_OPERATIONAL = 0x05
NMT_STATES = {0x00: "reset: its boot-up message came (an NMT reset or a power cycle); it is unconfigured until the recording restarts",
              0x04: "stopped by an NMT command (NMT state STOPPED): it sends no PDOs and takes no commands",
              0x7F: "sent back to pre-operational by an NMT command: it sends no PDOs and takes no commands"}

EMCY_MEANINGS = {
    0x0000: "error reset or no error",
    0x1000: "generic error",
    0x2310: "continuous over-current",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x4310: "drive over-temperature",
    0x5530: "EEPROM fault",
    0x7121: "motor blocked",
    0x7305: "incremental encoder fault",
    0x8100: "communication error (SYNC lost when the data say SYNC)",
    0x8110: "CAN overrun, frames lost",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard or heartbeat error: the drive lost the master's heartbeat",
    0x8140: "recovered from bus off",
    0x8210: "PDO not processed due to length error",
    0x8220: "PDO length exceeded",
    0x8250: "RPDO timeout",
    0x8400: "velocity limit exceeded (velocity speed controller)",
    0x8611: "following error",
    0x8612: "position limit exceeded (reference limit)",
    0xFF00: "device-specific fault",
}

PDO_FORMATS = {  # (signed, bits): the struct format of a mapped entry
    (True, 8): "b", (True, 16): "h", (True, 32): "i", (False, 8): "B", (False, 16): "H", (False, 32): "I"}

STATE_MASK = 0x006F  # CiA 402 statusword: the bits that name the state
OPERATION_ENABLED = 0x0027

SIGNED_INTEGERS = (2, 3, 4)
"""CiA 301 data types INTEGER8, INTEGER16 and INTEGER32: the signed values a PDO maps."""


def is_signed(entry: ODArray | ODRecord | ODVariable) -> bool:
    """Whether a PDO-mapped entry of the object dictionary holds a signed integer. A PDO maps
    variables only (canopen types the entry as any object of the dictionary)."""
    assert isinstance(entry, ODVariable), f"object 0x{entry.index:04X} is not a variable"
    return entry.data_type in SIGNED_INTEGERS


def emcy_meaning(code: int, data: bytes = b"") -> str:
    """An EMCY code in words (CiA 301/402), with its manufacturer data when there is any."""
    if code in EMCY_MEANINGS:
        text = EMCY_MEANINGS[code]
    else:
        text = canopen.emcy.EmcyError(code, 0, data, 0.0).get_desc() or "unknown code"
    return f"{text} (data {data.hex()})" if data.strip(b"\x00") else text

"""Why a CAN bus or a serial port would not open, in words a lab can act on.

The one place where the errors of ``can.Bus(...)`` and ``serial.Serial(...)`` (``OSError``
with an errno, python-can's ``CanInitializationError``, pyserial's ``SerialException``)
become a :class:`~armid.schema.errors.BusOpenError`: the interface, the channel, the cause
and what to do, on one line. :func:`can_open_error` for a CAN interface, :func:`serial_open_error`
for a serial port (a Dynamixel chain, or python-can's serial-based interfaces: ``slcan``,
``serial``, ``seeedstudio``, ``robotell``). A SocketCAN channel that opened is checked once
more against the kernel's view of the link (:func:`socketcan_link_problem`): a bound socket on
an interface that is down or not CAN fails only at its first frame, with ``ENETDOWN``.
"""

from __future__ import annotations

import errno
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from armid.schema.errors import BusOpenError

SERIAL_BACKED = ("slcan", "serial", "seeedstudio", "robotell")
"""python-can interfaces whose channel is a serial port: their failures are a serial port's."""

ARPHRD_CAN = 280
"""``/sys/class/net/<if>/type`` of a CAN interface (``linux/if_arp.h``)."""

IFF_UP = 0x1

SYS_NET = Path("/sys/class/net")


@dataclass(frozen=True)
class LinkState:
    """A network interface as the kernel shows it in ``/sys/class/net``: present, up, its link type."""

    name: str
    exists: bool
    up: bool = False
    link_type: int | None = None
    bitrate: int | None = None  # a CAN controller's bit rate (``ip -details link``); None: unknown, or virtual (vcan)

    @property
    def is_can(self) -> bool:
        return self.link_type == ARPHRD_CAN


def link_state(name: str) -> LinkState:
    """The kernel's view of interface ``name`` (``/sys/class/net/<name>/{flags,type}``)."""
    folder = SYS_NET / name
    if "/" in name or not name or not folder.is_dir():
        return LinkState(name, exists=False)
    try:
        flags = int((folder / "flags").read_text().strip(), 16)
        link_type = int((folder / "type").read_text().strip())
    except (OSError, ValueError):
        return LinkState(name, exists=True)
    bitrate = _can_bitrate(name) if link_type == ARPHRD_CAN else None
    return LinkState(name, exists=True, up=bool(flags & IFF_UP), link_type=link_type, bitrate=bitrate)


def _can_bitrate(name: str) -> int | None:
    """The bit rate the kernel set on CAN interface ``name`` (``ip -details -json link``), if any."""
    import json
    import subprocess

    try:
        done = subprocess.run(["ip", "-details", "-json", "link", "show", "dev", name], capture_output=True, text=True, timeout=5)
        info = json.loads(done.stdout)[0]["linkinfo"]["info_data"]["bittiming"]
        return int(info["bitrate"])
    except (OSError, subprocess.SubprocessError, ValueError, LookupError, TypeError):
        return None


def socketcan_link_problem(state: LinkState, bitrate: int) -> str | None:
    """What keeps a SocketCAN channel from carrying frames (None: nothing the kernel shows)."""
    name = state.name
    if not state.exists:
        return (f"socketcan {name}: no such interface (`ip -details link show type can` lists the CAN interfaces; "
                f"a USB adapter: plugged in, its driver loaded?)")
    if state.link_type is not None and not state.is_can:
        return (f"socketcan {name}: not a CAN interface (link type {state.link_type}); "
                f"name the CAN interface (`ip -details link show type can`) in the rig file's bus.channel or --channel")
    if not state.up:
        return f"socketcan {name} is down: `sudo ip link set {name} up type can bitrate {bitrate}` (the drives' bit rate)"
    if state.bitrate is not None and state.bitrate != bitrate:
        return (f"socketcan {name} runs at {state.bitrate} bit/s, the rig's bus.bitrate is {bitrate}: "
                f"`sudo ip link set {name} down && sudo ip link set {name} up type can bitrate {bitrate}` (the drives' bit rate)")
    return None


def _errno_of(err: BaseException) -> int | None:
    """The errno of an error or of the error it wraps (pyserial and python-can put it in the text)."""
    for e in (err, err.__cause__, err.__context__):
        code = getattr(e, "errno", None)
        if isinstance(code, int):
            return code
    found = re.search(r"\[Errno (\d+)\]|\((\d+), '", str(err))
    return int(found.group(1) or found.group(2)) if found else None


def serial_open_error(port: str, err: BaseException, what: str = "serial port") -> BusOpenError:
    """A serial port that would not open: the port, the cause, what to do."""
    code = _errno_of(err)
    if code == errno.ENOENT:
        cause = f"{port}: no such device (is the adapter plugged in? `ls /dev/serial/by-id/` lists the serial adapters)"
    elif code in (errno.EACCES, errno.EPERM):
        cause = (f"permission denied on {port}: add the user to the dialout group "
                 f"(`sudo usermod -aG dialout $USER`, then log in again)")
    elif code == errno.EBUSY:
        cause = f"{port} is busy: another process holds it (`fuser -v {port}` names it)"
    elif code in (errno.ENOTTY, errno.EISDIR, errno.ENXIO, errno.ENODEV):
        cause = f"{port}: not a serial port ({os.strerror(code)}); name the adapter's device, e.g. /dev/ttyUSB0"
    else:
        cause = f"{port}: cannot open the {what} ({_reason(err)})"
    return BusOpenError("serial", port, cause)


def can_open_error(interface: str, channel: Any, bitrate: int, err: BaseException) -> BusOpenError:
    """A CAN interface that would not open (``can.Bus(...)`` raised ``err``): the interface,
    the channel, the cause and what to do."""
    import can

    if interface in SERIAL_BACKED:
        e = serial_open_error(str(channel), err)
        return BusOpenError(interface, str(channel), f"{interface} {e.cause}")
    code = _errno_of(err)
    where = f"{interface} {channel}"
    if interface == "socketcan":
        if code == errno.EAFNOSUPPORT:
            cause = (f"socketcan {channel}: SocketCAN is not available in this kernel (no AF_CAN): "
                     f"on Linux `sudo modprobe can_raw`, else a python-can interface this machine has (bus.interface, --interface)")
        elif code == errno.ENODEV or isinstance(err, OSError) and "no interface" in str(err):
            cause = socketcan_link_problem(LinkState(str(channel), exists=False), bitrate) or ""
        elif code == errno.ENETDOWN:
            cause = socketcan_link_problem(LinkState(str(channel), exists=True, up=False), bitrate) or ""
        elif code in (errno.EACCES, errno.EPERM):
            cause = f"socketcan {channel}: permission denied ({_reason(err)})"
        else:
            cause = f"socketcan {channel}: cannot open the bus ({_reason(err)})"
    elif isinstance(err, can.CanInterfaceNotImplementedError) or isinstance(err, ImportError):
        cause = f"{where}: the interface is not available on this machine ({_reason(err)}): install its library or driver"
    elif isinstance(err, OSError) and "library not found" in str(err):
        cause = f"{where}: {_reason(err)}: install the adapter vendor's driver and library"
    elif interface == "udp_multicast":
        cause = (f"{where}: cannot open the multicast group ({_reason(err)}); the channel is an IPv4 group address "
                 f"(e.g. 239.74.163.2), bus.multicast_interface an address of this machine (default 127.0.0.1; `ip -4 addr` lists them)")
    else:
        cause = f"{where}: cannot open the bus ({_reason(err)})"
    return BusOpenError(interface, str(channel), cause)


def _reason(err: BaseException) -> str:
    """The error's own words, without pyserial's "could not open port" prefix, on one line."""
    text = " ".join(str(err).split()) or type(err).__name__
    return re.sub(r"^could not open port \S+: ", "", text).rstrip(".")

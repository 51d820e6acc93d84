"""python-can's ``udp_multicast`` bus pinned to one interface: loopback unless the rig says otherwise.

python-can's own bus joins its group on ``INADDR_ANY`` and sends with the kernel's default
multicast interface and a TTL of 1: its frames (and the join's IGMP report) go out of the
machine's default interface, onto the lab's network. :class:`PinnedMulticastBus` sends
(``IP_MULTICAST_IF``) and joins (``IP_ADD_MEMBERSHIP``) on one interface address only:
``127.0.0.1`` by default, with a TTL of 0, so that nothing leaves the machine; a rig that
spans machines names the address of the interface on the lab's network (the rig file's
``bus.multicast_interface``) and gets a TTL of 1 (``bus.hop_limit`` to change it).
:func:`drivers.rig.open_bus` opens every ``udp_multicast`` bus with it: the one place.
"""

from __future__ import annotations

import ipaddress
import socket
import struct
import sys
from typing import Any

import can
from can.interfaces.udp_multicast.bus import SO_TIMESTAMPNS, GeneralPurposeUdpMulticastBus, UdpMulticastBus
from can.interfaces.udp_multicast.utils import is_msgpack_installed

LOOPBACK = "127.0.0.1"
IP_MULTICAST_ALL = getattr(socket, "IP_MULTICAST_ALL", 49)
"""Linux's option (``<linux/in.h>``): by default a socket bound to a port receives the datagrams sent to
every group that any socket of the machine joined on that port, so two rigs on one machine, on two
groups, would each read the other's frames (a boot-up of the other arm's node 1 taken for a reset of
its own, measured). Off, a bus reads its own group only."""


class PinnedMulticastSocket(GeneralPurposeUdpMulticastBus):
    """python-can's multicast socket, sending and joining on ``interface_address`` only (IPv4)."""

    def __init__(self, group: str, port: int, hop_limit: int, interface_address: str) -> None:
        self.interface_address = interface_address
        self._failure: OSError | None = None
        try:
            super().__init__(group, port, hop_limit)
        except can.CanInitializationError as err:  # python-can logs why and says only "could not connect"
            raise (self._failure or err) from err

    def _create_socket(self, address_family: socket.AddressFamily) -> socket.socket:
        """As python-can's, with the interface set for sending and for the group's membership."""
        if address_family != socket.AF_INET:
            self._failure = OSError(f"an IPv4 group is needed to pin the bus to {self.interface_address}")
            raise self._failure
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            here = socket.inet_aton(self.interface_address)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, struct.pack("@I", self.hop_limit))
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, here)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if hasattr(socket, "SO_REUSEPORT"):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            try:
                sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
                self.timestamp_nanosecond = True
            except OSError:
                self.timestamp_nanosecond = False
            if sys.platform.startswith("linux"):  # only this group's datagrams, not every group joined on the port;
                sock.setsockopt(socket.IPPROTO_IP, IP_MULTICAST_ALL, 0)  # before the bind: after it, a cycle of another rig's came in first
            sock.bind(("", self.port))
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, socket.inet_aton(self.group) + here)
        except OSError as err:
            sock.close()
            self._failure = err
            raise
        return sock


class PinnedMulticastBus(UdpMulticastBus):
    """``udp_multicast`` on one interface: ``multicast_interface`` (an address of this machine,
    default ``127.0.0.1``); ``hop_limit`` (the TTL) defaults to 0 on loopback, 1 otherwise."""

    def __init__(self, channel: str = UdpMulticastBus.DEFAULT_GROUP_IPv4, port: int = 43113, hop_limit: int | None = None,
                 multicast_interface: str = LOOPBACK, receive_own_messages: bool = False, fd: bool = True, **kwargs: Any) -> None:
        is_msgpack_installed()
        if receive_own_messages:
            raise can.CanInterfaceNotImplementedError("receiving own messages is not yet implemented")
        address = ipaddress.ip_address(str(multicast_interface))  # ValueError: not an address
        hop = (0 if address.is_loopback else 1) if hop_limit is None else int(hop_limit)
        can.BusABC.__init__(self, channel, **kwargs)  # UdpMulticastBus.__init__ would open python-can's own socket
        try:
            self._multicast = PinnedMulticastSocket(channel, port, hop, str(address))
        except BaseException:
            self._is_shutdown = True  # nothing is open: no "not properly shut down" warning
            raise
        self._can_protocol = can.CanProtocol.CAN_FD if fd else can.CanProtocol.CAN_20


def socket_pinning(sock: socket.socket) -> tuple[str, int]:
    """The sending interface's address and the TTL of a multicast socket, as the kernel has them."""
    interface = socket.inet_ntoa(sock.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, 4))
    ttl = struct.unpack("@I", sock.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 4))[0]
    return interface, ttl

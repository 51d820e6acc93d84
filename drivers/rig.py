"""A rig (``config/rigs/*.yaml``): which robot, which bus, which drive on which joint.

The configuration as the drivers take it; reading and checking the file is
:mod:`armid.io.rig_file`.

A rig binds a robot description to hardware: the CAN interface and channel, the cycle
period, the CANopen node id and motor of each joint (encoder, gear, rated current), the PDO
plan, heartbeat times, and, for the simulated arm, what the simulation adds. Every error
names the file and the field.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Generic, Literal, Protocol, TypeVar, get_args

import numpy as np

from armid.schema.errors import BusOpenError, RigFileError


class ArmDescription(Protocol):
    """What the drivers need of the robot a rig binds (``armid.identify.robot.Robot`` is one);
    the rig file is read, and the robot description loaded, by :mod:`armid.io.rig_file`."""

    @property
    def name(self) -> str: ...

    @property
    def source(self) -> str: ...

    @property
    def n_joints(self) -> int: ...


ArmT = TypeVar("ArmT", bound=ArmDescription)
"""The robot description a rig binds: ``Rig[Robot]`` as :func:`armid.io.rig_file.load_rig` reads it,
so that code that simulates or identifies the arm gets the full description, typed."""


def permille_of(current_a: Any, rated_current_a: Any) -> Any:
    """Current (A) in whole per mille of the rated current, as a CiA 402 drive counts it
    (``0x6071``, ``0x6078``: int16); the one place this conversion is written. A scalar
    stays in Python arithmetic (a simulated drive converts one per TPDO, and numpy's clip
    costs ten times more on a scalar); Python's round and numpy's both round half to even."""
    if isinstance(current_a, (float, int)) and isinstance(rated_current_a, (float, int)):  # np.float64 is a float
        return float(min(max(round(current_a / rated_current_a * 1000.0), -32768), 32767))
    return np.clip(np.round(current_a / rated_current_a * 1000.0), -32768, 32767)


def current_of(permille: Any, rated_current_a: Any) -> Any:
    """Per mille of the rated current back to A: :func:`permille_of`'s inverse."""
    return permille / 1000.0 * rated_current_a


@dataclass(frozen=True)
class DriveUnits:
    """A drive's motor: encoder, gear, rating; the joint's torque constant (gear included).

    Position is counted in encoder increments at the motor, velocity in increments/s,
    torque and current in per mille of the motor's rated torque and current (CiA 402).
    """

    counts_per_rev: int = 4096
    gear_ratio: float = 100.0
    rated_current_a: float = 5.0
    torque_constant: float = 10.0  # N*m per A at the joint
    rotor_inertia_kgm2: float = 0.0  # the motor's, motor side (datasheet); 0 when unknown

    @property
    def reflected_inertia(self) -> float:
        """The rotor's inertia seen at the joint: ``J_m n^2`` (kg m^2)."""
        return self.rotor_inertia_kgm2 * self.gear_ratio**2

    @property
    def counts_per_rad(self) -> float:
        return self.counts_per_rev * self.gear_ratio / (2.0 * np.pi)

    @property
    def rated_motor_torque_nm(self) -> float:
        return self.torque_constant / self.gear_ratio * self.rated_current_a


@dataclass(frozen=True)
class DriveConfig:
    node_id: int  # the CANopen node id, or the Dynamixel servo id
    joint: int  # 0-based
    units: DriveUnits
    model: str = ""  # a serial servo's model (drivers.dynamixel_protocol.SERVO_MODELS)


@dataclass(frozen=True)
class BusConfig:
    interface: str = "virtual"
    channel: str = "armid"
    bitrate: int = 1_000_000
    options: dict[str, Any] = field(default_factory=dict)

    def kwargs(self) -> dict[str, Any]:
        """Keyword arguments of ``can.Bus``."""
        out: dict[str, Any] = {"interface": self.interface, "channel": self.channel}
        if self.interface not in ("virtual", "udp_multicast"):
            out["bitrate"] = self.bitrate
        return {**out, **self.options}


@dataclass(frozen=True)
class SerialConfig:
    """A serial servo chain (``bus: {interface: dynamixel, ...}``): port, line and timing.

    ``port: sim`` runs the simulated servo chain on a pseudo-terminal. ``host_latency_ms`` is
    what the host adds per request-reply (a USB-serial adapter's latency timer: 1 ms at
    best on an FTDI/U2D2). ``reply_timeout_ms`` bounds every read (default: the budget's
    reply time plus twice the host latency plus 2 ms, as ROBOTIS's SDK does).
    """

    port: str = "sim"
    baudrate: int = 4_000_000
    return_delay_us: int = 0
    host_latency_ms: float = 1.0
    read_mode: str = "fast_sync_read"
    reply_timeout_ms: float | None = None
    silent_cycles: int = 50  # consecutive cycles without a reply before a servo is declared lost


Pacing = Literal["clock", "drives", "consumer"]
"""What a driver's cycle waits for, besides its period (the rig file's ``pacing``):

- ``clock``: nothing, the period's schedule alone (real drives: the default);
- ``drives``: each SYNC waits, up to 50 ms, for the previous cycle's answers (drives simulated in
  another process, which a shared machine stalls: a co-simulation, as ``config/rigs/sim.yaml`` sets);
- ``consumer``: each SYNC waits for the consumer's :meth:`~drivers.interface.Driver.acknowledge`
  (an arm simulated in the consumer's own process, as :mod:`armid.simulated` sets).

A paced cycle's samples carry the simulated arm's time (cycle x period)."""

PACINGS: tuple[str, ...] = get_args(Pacing)


@dataclass(frozen=True)
class Rig(Generic[ArmT]):
    name: str
    robot: ArmT
    bus: BusConfig
    drives: tuple[DriveConfig, ...]
    period_s: float = 0.002
    pdo_plan: str = "alternate_velocity"
    master_node_id: int = 127
    heartbeat_ms: int = 100  # the drives' producer time
    master_heartbeat_ms: int = 50
    simulation: dict[str, Any] = field(default_factory=dict)
    source: str = "<rig>"
    serial: SerialConfig | None = None  # set for a Dynamixel chain (bus.interface: dynamixel)
    driver: str = "canopen"  # the registry's name (armid.drivers.BACKENDS) of the driver this rig needs
    control_bandwidth_hz: float | None = None  # the excitation loop's PD bandwidth (None: daq.excite.LOOP_BANDWIDTH_HZ)
    pacing: Pacing = "clock"  # what each cycle waits for besides the period (Pacing)

    @property
    def is_serial(self) -> bool:
        return self.serial is not None

    @property
    def n_joints(self) -> int:
        return self.robot.n_joints

    def with_bus(self, **changes: Any) -> Rig[ArmT]:
        """The rig on another bus (``--interface``, ``--channel``); the interface is checked."""
        from dataclasses import replace

        if "interface" in changes:
            check_interface(str(changes["interface"]), self.source, "bus.interface (--interface)")
        return replace(self, bus=replace(self.bus, **changes))


UDP_RECEIVE_BUFFER_BYTES = 4 * 1024 * 1024
"""A process that stalls for tens of ms (GIL, start-up) must not lose frames: at 2 ms and
about 20 frames a cycle, Linux's default 212 KB receive buffer overflows in about 25 ms
(the kernel counts ~800 bytes a datagram); 4 MB holds half a second."""


NOTIFIER_WAKE_S = 0.05
"""How often a canopen network's reader thread wakes on a quiet bus (canopen's own 1 s): a
network is stopped only once its reader wakes, and the simulated arm's, on a bus gone quiet,
took the notifier's whole 0.5 s stop timeout at each close (twice on the demo's path)."""


def canopen_network(bus: Any) -> Any:
    """A ``canopen.Network`` on ``bus``, connected: its reader thread started, waking every
    :data:`NOTIFIER_WAKE_S` on a quiet bus."""
    import canopen

    network = canopen.Network(bus)
    network.NOTIFIER_CYCLE = NOTIFIER_WAKE_S
    return network.connect()


def open_bus(**kwargs: Any) -> Any:
    """``can.Bus(**kwargs)``, with a receive buffer that survives a stall on ``udp_multicast``
    (pinned to loopback: :class:`~drivers.multicast.PinnedMulticastBus`), and on ``virtual``
    :class:`~drivers.virtual_bus.FieldCopyVirtualBus`. A bus that will not
    open, or a SocketCAN link that is down or not CAN, raises
    :class:`~armid.schema.errors.BusOpenError` (:mod:`drivers.port_errors` words it)."""
    import socket

    import can

    from .port_errors import can_open_error, link_state, socketcan_link_problem

    interface, channel = kwargs.get("interface"), kwargs.get("channel")
    if interface == "virtual":
        from .virtual_bus import FieldCopyVirtualBus

        return FieldCopyVirtualBus(**{k: v for k, v in kwargs.items() if k != "interface"})
    bitrate = int(kwargs.get("bitrate") or 1_000_000)
    bus: can.BusABC
    try:
        if interface == "udp_multicast":  # pinned to loopback unless the rig names an interface (drivers.multicast)
            from .multicast import PinnedMulticastBus

            bus = PinnedMulticastBus(**{k: v for k, v in kwargs.items() if k != "interface"})
        else:
            bus = can.Bus(**kwargs)
    except Exception as err:  # OSError, CanError, ImportError, ValueError: each interface raises its own
        raise can_open_error(str(interface), channel, bitrate, err) from err
    if interface == "socketcan" and (problem := socketcan_link_problem(link_state(str(channel)), bitrate)) is not None:
        bus.shutdown()
        raise BusOpenError("socketcan", str(channel), problem)
    sock = getattr(getattr(bus, "_multicast", None), "_socket", None)
    if sock is not None:
        for option in (getattr(socket, "SO_RCVBUFFORCE", None), socket.SO_RCVBUF):
            if option is None:
                continue
            try:
                sock.setsockopt(socket.SOL_SOCKET, option, UDP_RECEIVE_BUFFER_BYTES)
                break
            except OSError:  # SO_RCVBUFFORCE needs CAP_NET_ADMIN; SO_RCVBUF is capped at rmem_max
                continue
    return bus


def check_interface(interface: Any, src: str, where: str) -> None:
    """A python-can interface name (``can.interfaces.VALID_INTERFACES``)."""
    from can.interfaces import VALID_INTERFACES

    if not isinstance(interface, str) or interface not in VALID_INTERFACES:
        raise RigFileError(src, where, f"unknown CAN interface {interface!r}; python-can knows "
                                       f"{', '.join(sorted(VALID_INTERFACES))} (or dynamixel for a servo chain)")

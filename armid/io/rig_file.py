"""Rig files (``config/rigs/*.yaml``) into a :class:`~armid.drivers.rig.Rig`: the I/O layer.

The robot path is relative to the rig file; every error is a
:class:`~armid.schema.errors.RigFileError` naming the file and the field.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, cast

import numpy as np

from armid.drivers.rig import PACINGS, BusConfig, DriveConfig, DriveUnits, Pacing, Rig, SerialConfig, check_interface
from armid.identify.robot import Robot
from armid.schema.errors import RigFileError

from .robot_file import load_robot


def load_rig(path: str | Path) -> Rig[Robot]:
    """Read and check a rig YAML file; the robot path is relative to the rig file."""
    import yaml

    path = Path(path)
    src = str(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise RigFileError(src, "", "no such file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise RigFileError(src, "", f"cannot read ({err})") from None
    except RecursionError:
        raise RigFileError(src, "", "nested too deeply to be a rig file") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        raise RigFileError(src, f"line {mark.line + 1}" if mark else "YAML", "not valid YAML") from err
    return rig_from_dict(doc, src, path.parent)


def _check_multicast(bus_doc: dict[str, Any], src: str) -> None:
    """``bus.multicast_interface`` (an IPv4 address of this machine's interface that carries a
    ``udp_multicast`` bus; 127.0.0.1 when absent) and ``bus.hop_limit`` (its TTL, 0..255)."""
    import ipaddress

    if "multicast_interface" in bus_doc:
        value = bus_doc["multicast_interface"]
        try:
            ipaddress.IPv4Address(value if isinstance(value, str) else "")
        except ValueError:
            raise RigFileError(src, "bus.multicast_interface", f"must be an IPv4 address of this machine's interface "
                                                               f"(127.0.0.1 keeps the bus on this machine), got {value!r}") from None
    if "hop_limit" in bus_doc:
        _int(bus_doc["hop_limit"], src, "bus.hop_limit", 0, 255)


def rig_from_dict(doc: Any, src: str = "<rig>", base_dir: Path | None = None) -> Rig[Robot]:
    if not isinstance(doc, dict):
        raise RigFileError(src, "", "must be a mapping")
    base_dir = base_dir or Path.cwd()

    def need(key: str) -> Any:
        if key not in doc:
            raise RigFileError(src, key, "missing")
        return doc[key]

    robot_ref = need("robot")
    if not isinstance(robot_ref, Robot | str):
        raise RigFileError(src, "robot", f"must be the path of a robot description, got {robot_ref!r}")
    robot = load_robot(base_dir / str(robot_ref)) if not isinstance(robot_ref, Robot) else robot_ref
    bus_doc = doc.get("bus", {}) or {}
    if not isinstance(bus_doc, dict):
        raise RigFileError(src, "bus", "must be a mapping")
    if not isinstance(doc.get("simulation") or {}, dict):
        raise RigFileError(src, "simulation", f"must be a mapping of settings, got {doc['simulation']!r}")
    if not isinstance(doc.get("name", ""), str):
        raise RigFileError(src, "name", f"must be a string, got {doc['name']!r}")
    for key in ("channel", "port"):
        if key in bus_doc and (isinstance(bus_doc[key], bool) or not isinstance(bus_doc[key], str | int)):
            raise RigFileError(src, f"bus.{key}", f"must be a name or a number, got {bus_doc[key]!r}")
    if bus_doc.get("interface") == "dynamixel":
        rig = _serial_rig(doc, bus_doc, robot, src)
        _check_simulation(rig.simulation, robot, src)
        return rig
    known_bus = {"interface", "channel", "bitrate"}
    interface = bus_doc.get("interface", "virtual")
    if "interface" in bus_doc:
        check_interface(interface, src, "bus.interface")
    _check_multicast(bus_doc, src)
    bus = BusConfig(
        interface=str(interface),
        channel=str(bus_doc.get("channel", "armid")),
        bitrate=_int(bus_doc.get("bitrate", 1_000_000), src, "bus.bitrate", 10_000, 8_000_000),
        options={k: v for k, v in bus_doc.items() if k not in known_bus},
    )
    drives = []
    for j, where, d, node in _drive_rows(doc, robot, src, "drive", "node_id", "node id", 1, 127):
        units = DriveUnits(
            counts_per_rev=_int(d.get("counts_per_rev", 4096), src, f"{where}.counts_per_rev", 1, 2**31),
            gear_ratio=_float(d.get("gear_ratio", 1.0), src, f"{where}.gear_ratio", positive=True),
            rated_current_a=_float(d.get("rated_current_a"), src, f"{where}.rated_current_a", positive=True),
            torque_constant=robot.joints[j].torque_constant,
            rotor_inertia_kgm2=_float(d.get("rotor_inertia_kgm2", 0.0), src, f"{where}.rotor_inertia_kgm2"),
        )
        drives.append(DriveConfig(node, j, units))
    rig = Rig(
        name=str(doc.get("name", robot.name)),
        robot=robot,
        bus=bus,
        drives=tuple(drives),
        period_s=_float(doc.get("period_s", 0.002), src, "period_s", positive=True),
        pdo_plan=str(doc.get("pdo_plan", "alternate_velocity")),
        master_node_id=_int(doc.get("master_node_id", 127), src, "master_node_id", 1, 127),
        heartbeat_ms=_int(doc.get("heartbeat_ms", 100), src, "heartbeat_ms", 1, 65535),
        master_heartbeat_ms=_int(doc.get("master_heartbeat_ms", 50), src, "master_heartbeat_ms", 1, 65535),
        simulation=dict(doc.get("simulation") or {}),
        source=src,
        driver=_driver(doc, src, "canopen"),
        control_bandwidth_hz=_bandwidth(doc, src),
        pacing=_pacing(doc, src),
    )
    if rig.master_node_id in {d.node_id for d in drives}:
        raise RigFileError(src, "master_node_id", f"{rig.master_node_id} is also a drive's node id")
    from armid.drivers.pdo_plan import PLANS

    if rig.pdo_plan not in PLANS:
        raise RigFileError(src, "pdo_plan", f"unknown plan {rig.pdo_plan!r}; known: {', '.join(PLANS)}")
    if not isinstance(doc.get("bus"), dict) or "interface" not in doc["bus"]:
        # checked last, so that a rig's other fields are reported first; no bus never means a simulated one
        raise RigFileError(src, "bus.interface", "missing: name the bus (virtual for the simulated arm; socketcan, pcan, "
                                                 "kvaser, ... for drives; dynamixel for a servo chain)")
    _check_simulation(rig.simulation, robot, src)
    return rig


SIMULATION_KEYS = ("seed", "current_noise_a", "current_time_constant_s", "substeps", "sync_timeout_s", "initial_position",
                   "effects", "gravity_tilt_rad")


def _check_simulation(sim: dict[str, Any], robot: Robot, src: str) -> None:
    """The ``simulation:`` values the simulated arm reads, against their ranges and the robot's limits."""
    unknown = sorted(set(sim) - set(SIMULATION_KEYS))
    if unknown:
        raise RigFileError(src, f"simulation.{unknown[0]}", f"unknown setting; known: {', '.join(SIMULATION_KEYS)}")
    if "seed" in sim:
        _int(sim["seed"], src, "simulation.seed", 0, 2**32 - 1)
    if "substeps" in sim:
        _int(sim["substeps"], src, "simulation.substeps", 1, 1000)
    for key in ("current_noise_a", "current_time_constant_s"):
        if key in sim and _float(sim[key], src, f"simulation.{key}") < 0:
            raise RigFileError(src, f"simulation.{key}", f"must not be negative, got {sim[key]}")
    if "sync_timeout_s" in sim:
        _float(sim["sync_timeout_s"], src, "simulation.sync_timeout_s", positive=True)
    if sim.get("gravity_tilt_rad") is not None:
        tilt = sim["gravity_tilt_rad"]
        if not isinstance(tilt, list) or len(tilt) != 2:
            raise RigFileError(src, "simulation.gravity_tilt_rad", f"must be a list of 2 numbers, got {tilt!r}")
        for k, v in enumerate(tilt):
            _float(v, src, f"simulation.gravity_tilt_rad[{k}]")
    q0 = sim.get("initial_position")
    if q0 is not None:
        n = robot.n_joints
        if not isinstance(q0, list) or len(q0) != n:
            raise RigFileError(src, "simulation.initial_position", f"must be a list of {n} numbers (one per joint), got {q0!r}")
        for j, v in enumerate(q0):
            where = f"simulation.initial_position[{j}]"
            x = _float(v, src, where)
            limits = robot.joints[j].limits.position
            if limits is not None and not limits[0] <= x <= limits[1]:
                raise RigFileError(src, where, f"{x:g} is beyond joint {j + 1}'s position limits [{limits[0]:g}, {limits[1]:g}] "
                                               f"({robot.source})")
    effects = sim.get("effects")
    if effects is not None:
        if not isinstance(effects, list):
            raise RigFileError(src, "simulation.effects", "must be a list like [{joint: all, viscous: 0.5}]")
        for k, e in enumerate(effects):
            where = f"simulation.effects[{k}]"
            if not isinstance(e, dict) or "joint" not in e:
                raise RigFileError(src, where, "must be a mapping with a 1-based 'joint' (or all) and effect values")
            joint = e["joint"]
            if joint not in (None, "all") and (isinstance(joint, bool) or not isinstance(joint, int) or not 1 <= joint <= robot.n_joints):
                raise RigFileError(src, f"{where}.joint", f"must be 1..{robot.n_joints} or all, got {joint!r}")
            for name, value in e.items():
                if name != "joint":
                    _float(value, src, f"{where}.{name}")


def _serial_rig(doc: dict[str, Any], bus_doc: dict[str, Any], robot: Robot, src: str) -> Rig[Robot]:
    """A Dynamixel chain: ``bus`` gives the port and line, each drive its servo id and model."""
    from armid.drivers.dynamixel_protocol import BAUD_CODES, MAX_ID, SERVO_MODELS

    known = {"interface", "port", "baudrate", "return_delay_us", "host_latency_ms", "read_mode", "reply_timeout_ms", "silent_cycles"}
    for key in bus_doc:
        if key not in known:
            raise RigFileError(src, f"bus.{key}", f"unknown setting for a dynamixel bus; known: {', '.join(sorted(known))}")
    baud = _int(bus_doc.get("baudrate", 4_000_000), src, "bus.baudrate", 9_600, 4_500_000)
    if baud not in BAUD_CODES.values():
        raise RigFileError(src, "bus.baudrate", f"{baud} is not a Dynamixel baud rate; known: {', '.join(str(b) for b in BAUD_CODES.values())}")
    read_mode = str(bus_doc.get("read_mode", "fast_sync_read"))
    if read_mode not in ("fast_sync_read", "sync_read"):
        raise RigFileError(src, "bus.read_mode", f"must be fast_sync_read or sync_read, got {read_mode!r}")
    timeout = bus_doc.get("reply_timeout_ms")
    serial = SerialConfig(
        port=str(bus_doc.get("port", "sim")),
        baudrate=baud,
        return_delay_us=_int(bus_doc.get("return_delay_us", 0), src, "bus.return_delay_us", 0, 508),
        host_latency_ms=_float(bus_doc.get("host_latency_ms", 1.0), src, "bus.host_latency_ms"),
        read_mode=read_mode,
        reply_timeout_ms=None if timeout is None else _float(timeout, src, "bus.reply_timeout_ms", positive=True),
        silent_cycles=_int(bus_doc.get("silent_cycles", 50), src, "bus.silent_cycles", 1, 100_000),
    )
    drives = []
    for j, where, d, servo_id in _drive_rows(doc, robot, src, "servo", "id", "servo id", 0, MAX_ID):
        name = d.get("model")
        if name not in SERVO_MODELS:
            raise RigFileError(src, f"{where}.model", f"unknown servo model {name!r}; known: {', '.join(SERVO_MODELS)}")
        model = SERVO_MODELS[name]
        units = DriveUnits(
            counts_per_rev=model.counts_per_rev,
            gear_ratio=_float(d.get("gear_ratio", 1.0), src, f"{where}.gear_ratio", positive=True),
            rated_current_a=model.max_current_a,
            torque_constant=robot.joints[j].torque_constant,
            rotor_inertia_kgm2=_float(d.get("rotor_inertia_kgm2", 0.0), src, f"{where}.rotor_inertia_kgm2"),
        )
        drives.append(DriveConfig(servo_id, j, units, model.name))
    return Rig(
        name=str(doc.get("name", robot.name)),
        robot=robot,
        bus=BusConfig(interface="dynamixel", channel=serial.port, bitrate=baud),
        drives=tuple(drives),
        period_s=_float(doc.get("period_s", 0.002), src, "period_s", positive=True),
        simulation=dict(doc.get("simulation") or {}),
        source=src,
        serial=serial,
        driver=_driver(doc, src, "dynamixel"),
        control_bandwidth_hz=_bandwidth(doc, src),
        pacing=_pacing(doc, src),
    )


def _bandwidth(doc: dict[str, Any], src: str) -> float | None:
    """``control_bandwidth_hz``: the excitation loop's PD bandwidth, where the rig's joints need
    another than the default (light joints in gear friction need a stiffer loop)."""
    value = doc.get("control_bandwidth_hz")
    if value is None:
        return None
    hz = _float(value, src, "control_bandwidth_hz", positive=True)
    if hz > 20.0:
        raise RigFileError(src, "control_bandwidth_hz", f"{hz:g} Hz leaves no phase margin for a cycle's delay: at most 20")
    return hz


def _drive_rows(doc: dict[str, Any], robot: Robot, src: str, noun: str, key: str, label: str,
                lo: int, hi: int) -> list[tuple[int, str, dict[str, Any], int]]:
    """``drives``: one mapping per joint, each with a unique id under ``key``; returns
    (joint, field name, mapping, id) per drive."""
    drives_doc = doc.get("drives")
    if drives_doc is None:
        raise RigFileError(src, "drives", "missing")
    if not isinstance(drives_doc, list) or len(drives_doc) != robot.n_joints:
        raise RigFileError(src, "drives", f"must list one {noun} per joint ({robot.n_joints})")
    rows = []
    seen: set[int] = set()
    for j, d in enumerate(drives_doc):
        where = f"drives[{j}]"
        if not isinstance(d, dict):
            raise RigFileError(src, where, "must be a mapping")
        ident = _int(d.get(key), src, f"{where}.{key}", lo, hi)
        if ident in seen:
            raise RigFileError(src, f"{where}.{key}", f"{label} {ident} is used twice")
        seen.add(ident)
        rows.append((j, where, d, ident))
    return rows


def _int(value: Any, src: str, where: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | float) or int(value) != value:
        raise RigFileError(src, where, f"must be an integer, got {value!r}")
    if not lo <= int(value) <= hi:
        raise RigFileError(src, where, f"must be in {lo}..{hi}, got {value}")
    return int(value)


def _float(value: Any, src: str, where: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
        raise RigFileError(src, where, f"must be a number, got {value!r}")
    if positive and value <= 0:
        raise RigFileError(src, where, f"must be positive, got {value}")
    return float(value)


def _driver(doc: dict[str, Any], src: str, default: str) -> str:
    """The rig's ``driver:`` (a name in the registry, ``armid.drivers.BACKENDS``), else the bus's usual one."""
    from armid.drivers import driver_names

    name = doc.get("driver", default)
    known = driver_names()
    if not isinstance(name, str) or name not in known:
        raise RigFileError(src, "driver", f"unknown driver {name!r}; known: {', '.join(known)}")
    return name


def _pacing(doc: dict[str, Any], src: str) -> Pacing:
    """The rig's ``pacing:`` (:data:`~armid.drivers.rig.Pacing`): ``clock`` unless the rig says otherwise."""
    value = doc.get("pacing", "clock")
    if isinstance(value, str) and value in PACINGS:
        return cast(Pacing, value)
    raise RigFileError(src, "pacing", f"must be one of {', '.join(PACINGS)}, got {value!r}")

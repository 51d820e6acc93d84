"""The rig at the command line: its file with the bus overridden, its driver (on the simulated
hardware when simulating), and stopping on SIGINT/SIGTERM or after a duration."""

from __future__ import annotations

import argparse
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any


def rig_from_arguments(args: argparse.Namespace) -> Any:
    """The rig file, with ``--interface``/``--channel`` replacing its CAN bus's."""
    from armid.io.rig_file import load_rig

    rig = load_rig(args.rig)
    changes = {k: v for k, v in (("interface", args.interface), ("channel", args.channel)) if v}
    return rig.with_bus(**changes) if changes and not rig.is_serial else rig


def simulating(rig: Any, args: argparse.Namespace) -> bool:
    """``--simulate``/``--no-simulate``, else: a serial rig on ``port: sim``, a CAN rig on ``virtual``."""
    if args.simulate is not None:
        return bool(args.simulate)
    if rig.serial is not None:
        return (getattr(args, "channel", None) or rig.serial.port) == "sim"
    return bool(rig.bus.interface == "virtual")


def open_rig_driver(rig: Any, args: argparse.Namespace) -> tuple[Any, Any]:
    """The rig's driver (the registry names it), on the simulated hardware when simulating: (driver, simulator or None)."""
    from armid.drivers import open_driver

    if simulating(rig, args):
        from ..simulated import simulated_driver

        return simulated_driver(rig)
    kwargs = {"port": args.channel} if rig.serial is not None and getattr(args, "channel", None) else {}
    return open_driver(rig, **kwargs), None


def check_rig_budget(rig: Any) -> str:
    """The rig's bus budget, checked as its driver checks it at start-up, without the bus (a
    refusal raises ``BusBudgetError`` or ``SerialBudgetError``): what was checked, as a phrase."""
    if rig.serial is not None:
        from armid.drivers import dynamixel_protocol as dxl
        from armid.drivers.dynamixel_driver import serial_budget

        return f"the line's budget ({dxl.check_budget(serial_budget(rig)).describe()})"
    from armid.drivers.pdo_plan import check_bus_budget

    load = check_bus_budget(rig.pdo_plan, rig.n_joints, rig.period_s, rig.bus.bitrate, rig.heartbeat_ms).load
    return (f"the PDO plan and the bus budget ({rig.pdo_plan}: {load:.1%} of {rig.bus.bitrate / 1e6:g} Mbit/s "
            f"at {rig.period_s * 1000:g} ms, {rig.n_joints} axes)")


def rest_pose(rig: Any) -> Any:
    """Where a dry run designs from when the drives cannot say where the arm is: the rig's
    simulated start, else every joint at 0 rad (moved inside its limits)."""
    import numpy as np

    from armid.identify.excitation import Limits

    if "initial_position" in rig.simulation:
        return np.asarray(rig.simulation["initial_position"], float)
    limits = Limits.of(rig.robot)
    return np.clip(np.zeros(rig.n_joints), limits.position_low, limits.position_high)


@contextmanager
def stopped_by_signals() -> Iterator[threading.Event]:
    """An event that SIGINT and SIGTERM set while the block runs; the handlers before are put
    back after it. A command started in the background by a shell inherits SIGINT ignored, and
    one stopped only by ``KeyboardInterrupt`` heard no stop at all. Off the main thread (where
    handlers cannot be set) the event is only set by the caller."""
    import signal

    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def run_until(stop: Any, duration: float | None) -> None:
    """Until ``stop`` is set (a signal) or ``duration`` seconds have passed."""
    import time

    start = time.monotonic()
    while not stop.wait(0.05):
        if duration and time.monotonic() - start > duration:
            return

"""armid drivers: the amplifiers behind one :class:`~armid.drivers.interface.Driver`.

A registry in the manner of python-can's ``BACKENDS``: a rig file names its driver
(``driver: canopen`` or ``driver: dynamixel``; by default ``dynamixel`` for a serial
chain and ``canopen`` otherwise), :func:`open_driver` builds it. Classes are imported
lazily, so that a missing optional library fails only the driver that needs it, with a
clear "not available" error. Another distribution adds a driver through the entry point
group ``armid.drivers`` (``name = "package.module:Class"``).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from armid.schema.errors import DriverError

if TYPE_CHECKING:
    from .interface import Driver
    from .rig import Rig

BACKENDS: dict[str, tuple[str, str]] = {
    "canopen": ("armid.drivers.canopen_driver", "CanopenDriver"),
    "dynamixel": ("armid.drivers.dynamixel_driver", "DynamixelDriver"),
}
"""Driver name -> (module, class), imported on first use."""


def _entry_points() -> dict[str, tuple[str, str]]:
    from importlib.metadata import entry_points

    out = {}
    for ep in entry_points(group="armid.drivers"):
        module, _, attr = ep.value.partition(":")
        out[ep.name] = (module, attr)
    return out


def driver_names() -> list[str]:
    """Every driver a rig may name: the built-in ones and those entry points add."""
    return sorted({**_entry_points(), **BACKENDS})


def driver_class(name: str) -> type[Driver]:
    """The class registered as ``name``; raises :class:`DriverError` when unknown or not available."""
    known = {**_entry_points(), **BACKENDS}
    if name not in known:
        raise DriverError(f"no driver {name!r}; known: {', '.join(sorted(known))}")
    module, attr = known[name]
    try:
        return getattr(importlib.import_module(module), attr)  # type: ignore[no-any-return]
    except ImportError as err:
        raise DriverError(f"driver {name!r} is not available: {err}") from err


def open_driver(rig: Rig, **kwargs: Any) -> Driver:
    """The rig's driver (``rig.driver``), built with ``kwargs`` (``bus=`` for CANopen, ``port=`` for Dynamixel)."""
    # every registered class is built from the rig and its own keywords: a constructor the
    # abstract Driver (built with none) cannot spell, so the class is called as a factory
    factory: Callable[..., Driver] = driver_class(rig.driver)
    return factory(rig, **kwargs)

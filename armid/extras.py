"""The optional parts of armid and which command needs which: the one table.

``pyproject.toml`` lists what each extra installs. The core (``pip install armid``) is what
every side of the work shares: the arrays, the robot and rig files, the simulated arm's
physics (Pinocchio), the trajectory designer (SciPy, the compiled regressor), MCAP and
Zenoh. ``daq`` adds the buses (python-can, canopen, pyserial); ``identify`` adds the convex
solver of the physically consistent estimate (cvxpy, Clarabel) and the reports' plots
(matplotlib); ``mujoco`` lets ``--mjcf`` write the model MuJoCo simulates; ``all`` is the
three. A command that needs an extra this install lacks ends in one
line naming it, before anything starts (:func:`require`), or, should an import still fail
on the way, at the command line's boundary (:func:`missing_module`).
"""

from __future__ import annotations

import importlib.util
from collections.abc import Iterable
from dataclasses import dataclass

from armid.schema.errors import MissingExtraError


@dataclass(frozen=True)
class Extra:
    """One extra of ``pyproject.toml``: what the error line calls it and the
    modules whose presence says it is installed (``tests/test_extras.py`` checks that its
    distributions provide them)."""

    purpose: str
    modules: tuple[str, ...]


_DAQ = Extra("acquisition extra", ("can", "canopen", "serial"))
_IDENTIFY = Extra("identification extra", ("cvxpy", "clarabel", "matplotlib"))
EXTRAS: dict[str, Extra] = {
    "daq": _DAQ,
    "identify": _IDENTIFY,
    "all": Extra("acquisition and identification extras", _DAQ.modules + _IDENTIFY.modules),
    "fleet": Extra("fleet extra (Ray)", ("ray",)),
    "mujoco": Extra("MuJoCo extra", ("mujoco",)),
}
"""Every extra a command may need, by its name in ``pyproject.toml``."""

NEEDS: dict[str, str] = {
    "record": "daq", "excite": "daq", "sim": "daq",
    "identify": "identify", "diagnose": "identify", "check": "identify", "estimate": "identify", "serve": "identify", "fleet": "identify",
    "demo": "all",
}
"""Command -> the extra it needs (a DAQ PC beside the arm installs ``daq``; the machine that
identifies installs ``identify``; the demo runs both sides)."""


OPTION_NEEDS: dict[str, str] = {"mjcf": "mujoco"}
"""Option (its name on the parsed command line) -> the extra it needs beyond its command's
(``--mjcf``: MuJoCo compiles the model before it is written)."""


def install_command(extra: str) -> str:
    """What installs ``extra``, as a user types it."""
    return f'pip install "armid[{extra}]"'


def missing(extra: str) -> list[str]:
    """The modules of ``extra`` that cannot be imported here (none when it is installed)."""
    return [name for name in EXTRAS[extra].modules if not _importable(name)]


def _importable(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):  # a finder that refuses it, or a module set to None
        return False


def error(extra: str, modules: list[str]) -> MissingExtraError:
    """The one line (after the command line's ``armid COMMAND: error:``): which extra, what
    is missing, what installs it."""
    what = f"{', '.join(modules)} {'is' if len(modules) == 1 else 'are'} not installed"
    return MissingExtraError(f"this command needs the {EXTRAS[extra].purpose} ({what}): {install_command(extra)}")


def require(command: str, options: Iterable[str] = ()) -> None:
    """Raise :class:`MissingExtraError` when ``command``, or one of the ``options`` given to it
    (:data:`OPTION_NEEDS`), needs an extra this install lacks."""
    for extra in [NEEDS.get(command), *(OPTION_NEEDS.get(o) for o in options)]:
        if extra is not None and (absent := missing(extra)):
            raise error(extra, absent)


def missing_module(command: str, err: ModuleNotFoundError) -> MissingExtraError | None:
    """An import that failed under ``command``, as the one line naming the extra that holds
    the module (or the command's own extra); None for armid's own modules (a bug)."""
    top = (err.name or "").split(".")[0]
    if not top or top == "armid":
        return None
    holder = next((name for name, extra in EXTRAS.items() if top in extra.modules and name != "all"), NEEDS.get(command, "all"))
    return error(holder, [top])

"""The files armid ships as package data (``armid.config``), found with importlib.resources.

``config_file("rigs/sim.yaml")`` is a real path on disk: what canopen and YAML readers need.
"""

from __future__ import annotations

import atexit
from contextlib import ExitStack
from importlib import resources
from pathlib import Path

_extracted = ExitStack()
atexit.register(_extracted.close)


def config_file(relative: str) -> Path:
    """The path of ``config/<relative>`` as installed (``armid.config`` package data)."""
    entry = resources.files("armid.config").joinpath(*relative.split("/"))
    if isinstance(entry, Path):
        return entry
    return Path(_extracted.enter_context(resources.as_file(entry)))  # a zipped install: extracted once

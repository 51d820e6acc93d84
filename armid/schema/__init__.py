"""The bottom layer: the joint-state record (:class:`JointStates`) and its units, its codecs, and the exception tree.

Every other part of armid imports from here; this package imports nothing of armid's.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from .errors import ArmidError, InputError

if TYPE_CHECKING:
    from .joint_state import Array, JointStateRecord, Sample
    from .joint_states import JointStates

__all__ = ["Array", "ArmidError", "InputError", "JointStateRecord", "JointStates", "Sample", "versions"]

_LAZY = {"Array": "joint_state", "JointStateRecord": "joint_state", "Sample": "joint_state", "JointStates": "joint_states"}
"""Names whose modules need NumPy, imported when first asked for: the command line imports
:mod:`armid.schema.errors` on every start, ``--help`` included, and must not pay for NumPy."""


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def versions(*distributions: str) -> dict[str, str]:
    """Installed versions (``importlib.metadata``) of armid, Python and ``distributions``."""
    import platform
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": platform.python_version()}
    for dist in ("armid", *distributions):
        try:
            out[dist] = version(dist)
        except PackageNotFoundError:
            out[dist] = "?"
    return out

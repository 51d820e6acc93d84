"""The bottom layer: the joint-state record (:class:`JointStates`) and its units, its codecs, and the exception tree.

Every other part of armid imports from here; this package imports nothing of armid's.
"""

from __future__ import annotations

from .errors import ArmidError, InputError
from .joint_state import Array, JointStateRecord, Sample
from .joint_states import JointStates

__all__ = ["Array", "ArmidError", "InputError", "JointStateRecord", "JointStates", "Sample", "versions"]


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

"""JSON that every parser reads: ``null`` where a value is not finite, never a bare ``NaN``.

The one place armid turns its documents (identification, diagnosis, estimates, the service's
status, the fleet's tables) into JSON text.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any


def finite_or_none(value: Any) -> Any:
    """``value`` with every non-finite float (NaN, inf) replaced by None and numpy scalars and
    arrays made plain Python, recursively. NumPy is not imported for it: before anything else
    imported it, no value can be one of its types (a command's ``--help`` stays cheap)."""
    return _plain(value, sys.modules.get("numpy"))


def _plain(value: Any, np: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _plain(v, np) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v, np) for v in value]
    if np is None:
        return value
    if isinstance(value, np.floating):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.ndarray):
        return _plain(value.tolist(), np)
    return value


def json_safe(value: Any) -> Any:
    """:func:`finite_or_none`, checked first by the C encoder: a document with nothing to
    replace (the usual case, many times a second in a live stream) is returned as it is."""
    if isinstance(value, dict):
        try:
            json.dumps(value, allow_nan=False)
            return value
        except (ValueError, TypeError):
            pass
    return finite_or_none(value)


def strict_json(doc: Any, **kwargs: Any) -> str:
    """``doc`` as JSON text, non-finite values as ``null`` (:func:`finite_or_none`)."""
    return json.dumps(finite_or_none(doc), allow_nan=False, **kwargs)


def write_json(path: Path, doc: Any) -> None:
    """Write ``doc`` as strict JSON (:func:`strict_json`, one space indent), making the folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(strict_json(doc, indent=1, default=float) + "\n")

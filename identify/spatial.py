"""Small batched rotation and transform helpers (arrays in, arrays out).

Vectors are ``(..., 3)``, rotations ``(..., 3, 3)``, homogeneous transforms ``(4, 4)``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

Array = NDArray[Any]
ArrayLike = Array | list[float] | tuple[float, ...]


def skew(v: Array) -> Array:
    """``[v x]``: the matrix with ``skew(v) @ b == cross(v, b)``; batched over leading axes."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def cross(a: Array, b: Array) -> Array:
    """Cross product over the last axis, written out (``np.cross`` is slow on small axes)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1]
    out[..., 1] = a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2]
    out[..., 2] = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    return out


def axis_rotation(axis: Array, angle: Array) -> Array:
    """Rodrigues' rotation about a unit ``axis`` (3,) by ``angle`` (n,) -> (n, 3, 3)."""
    angle = np.asarray(angle, dtype=float)
    c = np.cos(angle)[:, None, None]
    s = np.sin(angle)[:, None, None]
    u = np.asarray(axis, dtype=float)
    return c * np.eye(3) + s * skew(u) + (1.0 - c) * np.outer(u, u)


def rot_x(angle: float) -> Array:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_z(angle: float) -> Array:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def transform(rotation: ArrayLike | None = None, translation: ArrayLike | None = None) -> Array:
    """A 4x4 homogeneous transform from a rotation and a translation."""
    out = np.eye(4)
    if rotation is not None:
        out[:3, :3] = rotation
    if translation is not None:
        out[:3, 3] = translation
    return out


def invert(t: Array) -> Array:
    """Inverse of a rigid 4x4 transform."""
    r = t[:3, :3]
    return transform(r.T, -r.T @ t[:3, 3])


def rpy_rotation(roll: float, pitch: float, yaw: float) -> Array:
    """URDF's fixed-axis roll-pitch-yaw: ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    cp, sp = np.cos(pitch), np.sin(pitch)
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    return rot_z(yaw) @ ry @ rot_x(roll)

"""Robot description: the kinematic chain, limits, modeled inertial values, declared effects.

Every joint, whatever convention described it, is held in one form: the transform from the
frame of link ``i-1`` to the frame of link ``i`` is

.. math:: T_{i-1,i}(q_i) = \\mathrm{pre}_i \\; J(\\mathrm{axis}_i, q_i) \\; \\mathrm{post}_i

with ``J`` a rotation about (revolute) or a translation along (prismatic) ``axis`` given in
the joint frame. Standard DH (Khosla's ``A_i``, ``p_i``) is ``pre = E``, ``J = Rz(q)`` or
``Tz(q)``, ``post = Rz(theta) Tz(d) Tx(a) Rx(alpha)``; modified DH (Craig) is
``pre = Rx(alpha) Tx(a)``, ``post = Rz(theta) Tz(d)``; a URDF joint is
``pre = origin``, ``post = E``. The link frame, in which the parameters of link ``i`` are
expressed, is frame ``i`` of the convention.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .spatial import Array, ArrayLike, rot_x, rot_z, skew, transform

PARAMETERS_PER_LINK = 10
LINK_PARAMETER_NAMES = ("m", "msx", "msy", "msz", "Ixx", "Ixy", "Ixz", "Iyy", "Iyz", "Izz")
"""Khosla's order of the dynamics parameters of one link (phi_i, after eq. 17)."""


class JointType(enum.Enum):
    REVOLUTE = "revolute"
    PRISMATIC = "prismatic"


@dataclass(frozen=True)
class JointLimits:
    """Limits in joint units: rad (or m), rad/s (or m/s), N*m (or N)."""

    position: tuple[float, float] | None = None
    velocity: float | None = None
    acceleration: float | None = None
    torque: float | None = None


@dataclass(frozen=True)
class Inertial:
    """Modeled inertial values of one link: mass, centre of mass and inertia about the COM.

    Axes parallel to the link frame (Khosla Table 1); inertia as tensor entries
    ``xx xy xz yy yz zz`` (off-diagonal entries are the tensor's, as in URDF).
    """

    mass_kg: float
    com_m: tuple[float, float, float]
    inertia_kgm2: tuple[float, float, float, float, float, float]


@dataclass(frozen=True, eq=False)
class Joint:
    name: str
    type: JointType
    pre: Array
    axis: Array
    post: Array
    torque_constant: float = 1.0
    limits: JointLimits = field(default_factory=JointLimits)
    inertial: Inertial | None = None
    torque_constant_std: float = 0.0  # relative standard uncertainty of torque_constant (a datasheet's)

    @property
    def revolute(self) -> bool:
        return self.type is JointType.REVOLUTE


@dataclass(frozen=True)
class DeclaredEffect:
    """An effect the robot file declares as part of the model (``joint`` is 1-based)."""

    effect: str
    joint: int | None
    options: dict[str, Any] = field(default_factory=dict)

    def per_joint(self, n_joints: int) -> list[DeclaredEffect]:
        """One effect per joint it applies to (``joint: null``: every joint), a ``modeled`` list
        (a value per joint, in the order of those joints) resolved to that joint's value."""
        joints = range(1, n_joints + 1) if self.joint is None else [self.joint]
        modeled = self.options.get("modeled")
        return [DeclaredEffect(self.effect, j, {**self.options, "modeled": modeled[k]} if isinstance(modeled, list) else dict(self.options))
                for k, j in enumerate(joints)]


@dataclass(frozen=True, eq=False)
class Robot:
    name: str
    gravity: Array
    joints: tuple[Joint, ...]
    effects: tuple[DeclaredEffect, ...] = ()
    source: str = ""
    # what a ROS 2 JointState's ``effort`` holds for this arm (a rosbag2 bag, a live source):
    # "torque", joint torque (N*m, or N); "current", motor current (A) that each joint's
    # torque_constant makes a torque (UR's driver publishes current by default)
    effort: str = "torque"

    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def n_parameters(self) -> int:
        return PARAMETERS_PER_LINK * self.n_joints

    @property
    def parameter_names(self) -> list[str]:
        return parameter_names(self.n_joints)

    def modeled_parameters(self) -> Array:
        """Khosla's phi (10 N,) from the modeled inertial values; NaN for a link without them."""
        phi = np.full(self.n_parameters, np.nan)
        for i, joint in enumerate(self.joints):
            if joint.inertial is not None:
                phi[10 * i : 10 * i + 10] = link_parameters(joint.inertial)
        return phi


def parameter_names(n_joints: int) -> list[str]:
    """``m1, msx1, ..., Izz1, m2, ...``: the names INTERFACES.md gives the parameters."""
    return [f"{name}{i + 1}" for i in range(n_joints) for name in LINK_PARAMETER_NAMES]


def inertia_matrix(xx_xy_xz_yy_yz_zz: ArrayLike) -> Array:
    """The symmetric 3x3 tensor from its six entries ``xx xy xz yy yz zz``."""
    xx, xy, xz, yy, yz, zz = np.asarray(xx_xy_xz_yy_yz_zz, dtype=float)
    return np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])


def inertia_entries(tensor: Array) -> Array:
    """Inverse of :func:`inertia_matrix`."""
    t = np.asarray(tensor, dtype=float)
    return np.array([t[0, 0], t[0, 1], t[0, 2], t[1, 1], t[1, 2], t[2, 2]])


def link_parameters(inertial: Inertial) -> Array:
    """Khosla's phi_i from mass, COM and inertia about the COM, by Steiner's law (eq. 10).

    .. math:: I'_i = I_i + m_i (s_i^T s_i E - s_i s_i^T)
    """
    m = inertial.mass_kg
    s = np.asarray(inertial.com_m, dtype=float)
    i_link = inertia_matrix(inertial.inertia_kgm2) + m * (s @ s * np.eye(3) - np.outer(s, s))
    return np.concatenate([[m], m * s, inertia_entries(i_link)])


def inertial_from_parameters(phi: Array) -> Inertial:
    """Inverse of :func:`link_parameters` (eq. 10 read backwards); needs ``m > 0``."""
    m = float(phi[0])
    s = np.asarray(phi[1:4], dtype=float) / m
    i_com = inertia_matrix(phi[4:10]) - m * (s @ s * np.eye(3) - np.outer(s, s))
    e = inertia_entries(i_com)
    return Inertial(m, (float(s[0]), float(s[1]), float(s[2])), tuple(float(x) for x in e))  # type: ignore[arg-type]


def change_link_frame(phi: Array, rotation: Array, translation: Array) -> Array:
    """Parameters of one link re-expressed in another frame (linear in phi).

    ``rotation``, ``translation`` give the link frame in the new frame
    (``x_new = R x_link + t``). The inertia is moved by the general parallel-axis law
    ``I_new = R I R^T - [h x][t x] - [t x][h x] - m [t x]^2`` with ``h = R m s``.
    """
    m = phi[0]
    h = rotation @ phi[1:4]
    t = np.asarray(translation, dtype=float)
    st, sh = skew(t), skew(h)
    i_new = rotation @ inertia_matrix(phi[4:10]) @ rotation.T - sh @ st - st @ sh - m * st @ st
    return np.concatenate([[m], h + m * t, inertia_entries(i_new)])


def dh_joint(kind: JointType, a: float, alpha: float, d: float, theta: float) -> tuple[Array, Array, Array]:
    """(pre, axis, post) of a standard DH row: ``Rz(theta + q) Tz(d) Tx(a) Rx(alpha)``."""
    post = transform(rot_z(theta)) @ transform(None, [0.0, 0.0, d]) @ transform(None, [a, 0.0, 0.0])
    post = post @ transform(rot_x(alpha))
    return np.eye(4), np.array([0.0, 0.0, 1.0]), post


def mdh_joint(kind: JointType, a: float, alpha: float, d: float, theta: float) -> tuple[Array, Array, Array]:
    """(pre, axis, post) of a modified DH row: ``Rx(alpha) Tx(a) Rz(theta + q) Tz(d)``."""
    pre = transform(rot_x(alpha)) @ transform(None, [a, 0.0, 0.0])
    post = transform(rot_z(theta)) @ transform(None, [0.0, 0.0, d])
    return pre, np.array([0.0, 0.0, 1.0]), post

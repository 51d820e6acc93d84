"""The same robot as a Pinocchio model, and the map between the two parameter conventions.

Pinocchio is armid's independent reference: its ``rnea`` and
``computeJointTorqueRegressor`` check :mod:`identify.dynamics`. Its joint frame of joint
``i`` sits on the joint axis (URDF child frame); armid's link frame is frame ``i`` of the
convention in use, so for standard DH the two differ by ``post_i``. Parameters differ in
that frame and in order:

- armid (Khosla): ``m, msx, msy, msz, Ixx, Ixy, Ixz, Iyy, Iyz, Izz`` about the link frame;
- Pinocchio: ``m, mcx, mcy, mcz, Ixx, Ixy, Iyy, Ixz, Iyz, Izz`` about the joint frame.
"""

from __future__ import annotations

import numpy as np

from .robot import Robot, change_link_frame, inertia_matrix, link_parameters
from .spatial import Array

KHOSLA_TO_PINOCCHIO_ORDER = np.array([0, 1, 2, 3, 4, 5, 7, 6, 8, 9])
"""``phi_pin = phi_khosla[KHOSLA_TO_PINOCCHIO_ORDER]`` for parameters in the same frame."""


def parameter_map(robot: Robot) -> Array:
    """``T`` (10N, 10N) with ``phi_pinocchio = T phi_khosla``, hence ``M = Y_pin T``.

    Block diagonal: per link the frame change (link frame -> joint frame, by ``post_i``,
    the general parallel-axis law) followed by the reordering of the inertia entries.
    """
    n = robot.n_parameters
    t = np.zeros((n, n))
    for i, joint in enumerate(robot.joints):
        rot, trans = joint.post[:3, :3], joint.post[:3, 3]
        block = np.column_stack([change_link_frame(e, rot, trans) for e in np.eye(10)])
        t[10 * i : 10 * i + 10, 10 * i : 10 * i + 10] = block[KHOSLA_TO_PINOCCHIO_ORDER]
    return t


def _joint_model(pin, axis: Array, revolute: bool):  # type: ignore[no-untyped-def]
    for k, name in enumerate("XYZ"):
        e = np.zeros(3)
        e[k] = 1.0
        if np.allclose(axis, e):
            return getattr(pin, f"JointModel{'R' if revolute else 'P'}{name}")()
    cls = pin.JointModelRevoluteUnaligned if revolute else pin.JointModelPrismaticUnaligned
    return cls(np.asarray(axis, dtype=float))


def to_pinocchio(robot: Robot, phi: Array | None = None):  # type: ignore[no-untyped-def]
    """A ``pinocchio.Model`` of the robot with Khosla parameters ``phi`` (default: modeled)."""
    import pinocchio as pin

    if phi is None:
        phi = robot.modeled_parameters()
    model = pin.Model()
    model.name = robot.name
    model.gravity = pin.Motion(np.asarray(robot.gravity, dtype=float), np.zeros(3))
    parent, parent_post = 0, np.eye(4)
    for i, joint in enumerate(robot.joints):
        placement = parent_post @ joint.pre
        jid = model.addJoint(
            parent,
            _joint_model(pin, joint.axis, joint.revolute),
            pin.SE3(placement[:3, :3], placement[:3, 3]),
            joint.name,
        )
        p = change_link_frame(np.asarray(phi[10 * i : 10 * i + 10]), joint.post[:3, :3], joint.post[:3, 3])
        mass = float(p[0])
        com = p[1:4] / mass if mass > 0 else np.zeros(3)
        i_com = inertia_matrix(p[4:10]) - mass * (com @ com * np.eye(3) - np.outer(com, com))
        model.appendBodyToJoint(jid, pin.Inertia(mass, com, i_com), pin.SE3.Identity())
        parent, parent_post = jid, joint.post
    return model


def pinocchio_parameters(robot: Robot, phi: Array | None = None) -> Array:
    """``phi`` in Pinocchio's convention (equals ``parameter_map(robot) @ phi``)."""
    if phi is None:
        phi = robot.modeled_parameters()
    return parameter_map(robot) @ phi


__all__ = ["KHOSLA_TO_PINOCCHIO_ORDER", "link_parameters", "parameter_map", "pinocchio_parameters", "to_pinocchio"]

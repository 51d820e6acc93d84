"""The physically consistent identified model as MJCF: the model MuJoCo simulates.

Written from the robot's chain as armid holds it (:mod:`identify.robot`:
``T_{i-1,i}(q) = pre_i J(axis_i, q) post_i``), not through MuJoCo's URDF importer: a robot of
DH rows, of modified DH rows or of a URDF gets the same exact kinematics, and a URDF's meshes,
its joints the robot file locks and its welded links need no importing (MuJoCo's importer
would need the mesh files, would make the locked joints move and merges welded links its own
way). Body ``i``'s frame is armid's link frame ``i``, the frame the identified parameters are
about, so its ``<inertial>`` is :func:`~armid.urdf_export.link_inertial`, as the URDF's. Body
``i`` sits at ``pre_i post_i`` in body ``i-1`` (the joints at 0); its joint passes through the
origin of ``post_i^-1`` along ``R_post^T axis``, so turning it by ``q`` gives
``pre_i J(q) post_i`` exactly (a URDF joint: ``post = E``, the joint at the body's origin).

Declared effects become joint attributes where MuJoCo has the same term: viscous friction
``fv qd`` is ``damping``, rotor inertia ``ia qdd`` is ``armature``, a spring ``ks q`` is
``stiffness`` (``springref`` 0), Coulomb friction ``fc`` is ``frictionloss``: MuJoCo's dry
friction, a soft constraint bounded by ``fc``, where armid fits ``fc sign(qd)`` or
``fc tanh(qd / v)``. A torque offset, Stribeck and load-dependent Coulomb friction, cogging
have no MuJoCo joint term and are left out; the file says so in a comment and
:func:`write_mjcf` returns the same for the command to print. Gravity is the robot file's
(``<option gravity>``); each joint with a declared torque limit gets a ``<motor>`` bounded by
it. No geometry: the bodies carry the identified inertia only.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from armid.identify.effects import LinearEffect
from armid.identify.errors import IdentificationError
from armid.identify.robot import Robot
from armid.schema import Array

from .urdf_export import child_links, link_inertial

MUJOCO_TERMS = {"viscous_friction": "damping", "coulomb_friction": "frictionloss", "rotor_inertia": "armature", "spring": "stiffness"}
"""armid's effect -> the MuJoCo joint attribute that is the same term of the dynamics."""


def _f(x: float) -> str:
    return f"{float(x) + 0.0:.17g}"  # + 0.0: no "-0"


def _v(xs: Any) -> str:
    return " ".join(_f(x) for x in xs)


def quaternion(rotation: Array) -> Array:
    """MuJoCo's ``quat`` (w, x, y, z) of a rotation matrix (Shepperd's method: the largest of the
    four squares first, so that no division is by a small number)."""
    r = np.asarray(rotation, dtype=float)
    t = np.trace(r)
    k = int(np.argmax([t, r[0, 0], r[1, 1], r[2, 2]]))
    if k == 0:
        s = 2.0 * math.sqrt(1.0 + t)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif k == 1:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(1.0 - r[0, 0] + r[1, 1] - r[2, 2])
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 - r[0, 0] - r[1, 1] + r[2, 2])
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    out = np.array(q)
    return out if out[0] >= 0 else -out


def _joints_text(joints: list[int]) -> str:
    return ("joint " if len(joints) == 1 else "joints ") + ", ".join(map(str, joints))


def joint_terms(robot: Robot, phi: Array, effects: Sequence[LinearEffect]) -> tuple[list[dict[str, str]], list[str], list[str]]:
    """Per joint the MuJoCo attributes of its declared effects (:data:`MUJOCO_TERMS`), the
    effects with no MuJoCo term (``effect on joints ...``) and where a term is MuJoCo's only
    approximately (Coulomb friction's smoothing). ``phi`` (10 N + k,): the links' parameters,
    then the effects' in the order of ``effects``."""
    terms: list[dict[str, str]] = [{} for _ in robot.joints]
    left_out: dict[str, list[int]] = {}
    smoothed: list[str] = []
    k = robot.n_parameters
    for e in effects:
        values = np.asarray(phi[k : k + len(e.parameter_names)], dtype=float)
        k += len(e.parameter_names)
        attribute = MUJOCO_TERMS.get(e.effect)
        if attribute is None:
            left_out.setdefault(e.effect.replace("_", " "), []).append(e.joint + 1)
            continue
        terms[e.joint][attribute] = _f(values[0])
        velocity = dict(e.setting).get("velocity", 0.0)
        if e.effect == "coulomb_friction" and velocity > 0:
            smoothed.append(f"{e.joint + 1} ({velocity:.3g})")
    if k != len(phi):
        raise IdentificationError(f"{len(phi)} parameters for {robot.n_joints} links and {k - robot.n_parameters} effect parameters")
    notes = [f"{name} on {_joints_text(joints)}" for name, joints in left_out.items()]
    approx = ([f"Coulomb friction as frictionloss: MuJoCo's dry friction is a soft constraint bounded by fc, where armid fits "
               f"fc tanh(qd / v) on joints (v, rad/s or m/s) {', '.join(smoothed)}"] if smoothed else [])
    return terms, notes, approx


def mjcf_tree(robot: Robot, phi: Array, effects: Sequence[LinearEffect] = ()) -> tuple[ET.ElementTree[Any], list[str]]:
    """The MJCF document (module docstring) and the effects it leaves out (no MuJoCo term)."""
    phi = np.asarray(phi, dtype=float)
    terms, left_out, approx = joint_terms(robot, phi, effects)
    names = child_links(robot) or [f"link{i + 1}" for i in range(robot.n_joints)]
    root = ET.Element("mujoco", model=robot.name)
    said = [f"armid: the physically consistent identified model of {robot.name}. Body frames are the robot file's link "
            f"frames ({', '.join(names)}), the frames the identified inertials are about; gravity is the robot file's.",
            "Joint terms: viscous friction as damping, Coulomb friction as frictionloss, rotor inertia as armature, a spring "
            "as stiffness (springref 0), where the model declares them."]
    said += approx
    said.append("No MuJoCo equivalent, left out: " + ("; ".join(left_out) if left_out else "nothing") + ".")
    said.append("No geometry: the bodies carry the identified inertia only.")
    root.append(ET.Comment(" " + "\n  ".join(said).replace("--", "- -") + " "))  # "--" ends an XML comment
    ET.SubElement(root, "compiler", angle="radian", autolimits="true")
    ET.SubElement(root, "option", gravity=_v(robot.gravity))
    parent = ET.SubElement(root, "worldbody")
    actuators = []
    for i, joint in enumerate(robot.joints):
        placement = joint.pre @ joint.post
        body = ET.SubElement(parent, "body", name=names[i], pos=_v(placement[:3, 3]), quat=_v(quaternion(placement[:3, :3])))
        inv_post = np.linalg.inv(joint.post)
        attrs = {"name": joint.name, "type": "hinge" if joint.revolute else "slide",
                 "pos": _v(inv_post[:3, 3]), "axis": _v(inv_post[:3, :3] @ np.asarray(joint.axis, dtype=float))}
        if joint.limits.position is not None:
            attrs["range"] = _v(joint.limits.position)
        ET.SubElement(body, "joint", attrib={**attrs, **terms[i]})
        inert = link_inertial(phi[10 * i : 10 * i + 10])
        xx, xy, xz, yy, yz, zz = inert.inertia_kgm2
        ET.SubElement(body, "inertial", pos=_v(inert.com_m), mass=_f(inert.mass_kg), fullinertia=_v((xx, yy, zz, xy, xz, yz)))
        if joint.limits.torque:
            actuators.append({"name": joint.name, "joint": joint.name, "ctrlrange": _v((-joint.limits.torque, joint.limits.torque))})
        parent = body
    if actuators:
        act = ET.SubElement(root, "actuator")
        for a in actuators:
            ET.SubElement(act, "motor", attrib=a)
    return ET.ElementTree(root), left_out


def write_mjcf(path: str | Path, robot: Robot, phi: Array, effects: Sequence[LinearEffect] = ()) -> tuple[Path, list[str]]:
    """Write :func:`mjcf_tree` to ``path`` once MuJoCo has compiled it; return the path and the
    effects left out. A model MuJoCo refuses (a body without mass or inertia) is an
    :class:`IdentificationError` naming MuJoCo's reason, and nothing is written."""
    import mujoco

    path = Path(path)
    tree, left_out = mjcf_tree(robot, phi, effects)
    ET.indent(tree, "  ")
    text = ET.tostring(tree.getroot(), encoding="unicode")
    try:
        mujoco.MjModel.from_xml_string(text)
    except ValueError as err:
        raise IdentificationError(f"{path}: MuJoCo does not load the identified model ({' '.join(str(err).split())})") from err
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text + "\n")
    return path, left_out

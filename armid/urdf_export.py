"""Identified inertials written back as a URDF that Pinocchio, ROS and simulators load.

Two cases:

- the robot file names a URDF: that file, with each identified link's ``<inertial>``
  replaced. armid's link frame is the URDF joint's child frame, so the identified centre
  of mass and inertia go into the child link as they are. Links fixed to a child link
  (which a URDF parser merges into its body) lose their ``<inertial>``: the identified
  values already contain them.
- DH rows (standard or modified): a URDF built from them. Joint ``i`` sits at ``pre_i`` in
  link frame ``i-1`` (a ``<link name="NAME_axis">`` without inertia), and a fixed joint
  ``post_i`` carries it to link frame ``i`` (``<link name="linkI">``), whose ``<inertial>``
  holds the identified values. For standard DH ``pre_i`` is the identity and ``post_i`` is
  ``Rz(theta) Tz(d) Tx(a) Rx(alpha)``: the DH link frame is not the URDF joint frame.

A URDF has no gravity: the model's gravity is the robot file's (set ``model.gravity``).
Declared viscous and Coulomb friction go into ``<dynamics damping friction>``; rotor
inertia has no URDF field and is left out (a comment says so).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np

from armid.identify.errors import RobotFileError
from armid.identify.robot import Inertial, Robot, inertial_from_parameters
from armid.schema import Array


def _f(x: float) -> str:
    return f"{float(x) + 0.0:.17g}"  # + 0.0: no "-0"


def rpy_of(rotation: Array) -> tuple[float, float, float]:
    """URDF roll, pitch, yaw of a rotation: ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    r = np.asarray(rotation, dtype=float)
    pitch = math.atan2(-r[2, 0], math.hypot(r[0, 0], r[1, 0]))
    if math.hypot(r[0, 0], r[1, 0]) > 1e-12:
        roll = math.atan2(r[2, 1], r[2, 2])
        yaw = math.atan2(r[1, 0], r[0, 0])
    else:  # gimbal lock: yaw taken as 0
        roll = math.atan2(-r[1, 2], r[1, 1])
        yaw = 0.0
    return roll, pitch, yaw


def _origin(parent: ET.Element, transform: Array) -> None:
    ET.SubElement(parent, "origin", xyz=" ".join(_f(x) for x in transform[:3, 3]), rpy=" ".join(_f(x) for x in rpy_of(transform[:3, :3])))


def link_inertial(phi_link: Array) -> Inertial:
    """One link's ten identified parameters (about the link frame, Khosla eq. 10) as the body a
    model file holds: mass, centre of mass ``h / m``, inertia about it with the link frame's
    axes (Steiner). A massless link (``m <= 0``: a physically consistent estimate then has
    ``h = 0``) keeps its inertia about the link frame's origin: a rotor's moment the torques
    still see. The one conversion the URDF and the MJCF both write."""
    phi_link = np.asarray(phi_link, dtype=float)
    if phi_link[0] > 0:
        return inertial_from_parameters(phi_link)
    return Inertial(0.0, (0.0, 0.0, 0.0), tuple(float(x) for x in phi_link[4:10]))  # type: ignore[arg-type]


def inertial_element(phi_link: Array) -> ET.Element:
    """``<inertial>`` of one link's ten parameters (:func:`link_inertial`)."""
    inert = link_inertial(phi_link)
    com, (xx, xy, xz, yy, yz, zz), mass = inert.com_m, inert.inertia_kgm2, inert.mass_kg
    el = ET.Element("inertial")
    ET.SubElement(el, "origin", xyz=" ".join(_f(x) for x in com), rpy="0 0 0")
    ET.SubElement(el, "mass", value=_f(mass))
    ET.SubElement(el, "inertia", ixx=_f(xx), ixy=_f(xy), ixz=_f(xz), iyy=_f(yy), iyz=_f(yz), izz=_f(zz))
    return el


def _friction(effects: dict[tuple[str, int], float], j: int) -> dict[str, str]:
    out = {}
    if ("viscous_friction", j) in effects:
        out["damping"] = _f(effects[("viscous_friction", j)])
    if ("coulomb_friction", j) in effects:
        out["friction"] = _f(effects[("coulomb_friction", j)])
    return out


def child_links(robot: Robot) -> list[str] | None:
    """Per joint, the name of its child link in the URDF the robot file names (the body the
    identified inertial belongs to); None for a robot described by DH rows."""
    source = _urdf_path(robot)
    if source is None:
        return None
    try:
        root = ET.parse(source).getroot()
    except (OSError, ET.ParseError) as err:
        raise RobotFileError(str(source), "", f"cannot read the URDF ({err})") from err
    joints = {el.get("name"): el for el in root.findall("joint")}
    missing = [j.name for j in robot.joints if j.name not in joints]
    if missing:
        raise RobotFileError(str(source), missing[0], "no such joint in the URDF")
    return [_attr(joints[j.name], "child") for j in robot.joints]


def _urdf_path(robot: Robot) -> Path | None:
    """The URDF a robot file names (``urdf:``), or None for DH rows."""
    import yaml

    if not robot.source or not Path(robot.source).exists():
        return None
    doc = yaml.safe_load(Path(robot.source).read_text())
    if isinstance(doc, dict) and "urdf" in doc:
        return Path(robot.source).parent / str(doc["urdf"])
    return None


def urdf_tree(robot: Robot, phi: Array, effects: dict[tuple[str, int], float] | None = None) -> ET.ElementTree[Any]:
    """The URDF document (see the module docstring); ``phi`` (>= 10 N,) standard parameters,
    ``effects`` maps (effect name, 1-based joint) to a value."""
    effects = effects or {}
    source = _urdf_path(robot)
    if source is not None:
        return _replace_inertials(source, robot, phi, effects)
    return _from_rows(robot, phi, effects)


def _from_rows(robot: Robot, phi: Array, effects: dict[tuple[str, int], float]) -> ET.ElementTree[Any]:
    root = ET.Element("robot", name=robot.name)
    root.append(ET.Comment(f" armid: identified inertials of {robot.name}; link frames are the robot file's "
                           f"(linkI); gravity in the robot file: {list(map(float, robot.gravity))} "))
    ET.SubElement(root, "link", name="link0")
    parent = "link0"
    for i, joint in enumerate(robot.joints):
        axis_link = f"{joint.name}_axis"
        el = ET.SubElement(root, "joint", name=joint.name, type="revolute" if joint.revolute else "prismatic")
        ET.SubElement(el, "parent", link=parent)
        ET.SubElement(el, "child", link=axis_link)
        _origin(el, joint.pre)
        ET.SubElement(el, "axis", xyz=" ".join(_f(x) for x in joint.axis))
        lim = joint.limits
        lo, hi = lim.position if lim.position else (-math.pi, math.pi)
        ET.SubElement(el, "limit", lower=_f(lo), upper=_f(hi), effort=_f(lim.torque or 0.0), velocity=_f(lim.velocity or 0.0))
        dyn = _friction(effects, i + 1)
        if dyn:
            ET.SubElement(el, "dynamics", attrib=dyn)
        ET.SubElement(root, "link", name=axis_link)
        fixed = ET.SubElement(root, "joint", name=f"{joint.name}_frame", type="fixed")
        ET.SubElement(fixed, "parent", link=axis_link)
        ET.SubElement(fixed, "child", link=f"link{i + 1}")
        _origin(fixed, joint.post)
        link = ET.SubElement(root, "link", name=f"link{i + 1}")
        link.append(inertial_element(phi[10 * i : 10 * i + 10]))
        parent = f"link{i + 1}"
    return ET.ElementTree(root)


def _replace_inertials(source: Path, robot: Robot, phi: Array, effects: dict[tuple[str, int], float]) -> ET.ElementTree[Any]:
    try:
        tree = ET.parse(source)
    except (OSError, ET.ParseError) as err:
        raise RobotFileError(str(source), "", f"cannot read the URDF ({err})") from err
    root = tree.getroot()
    if root is None:
        raise RobotFileError(str(source), "", "empty URDF")
    links = {el.get("name"): el for el in root.findall("link")}
    joints = {el.get("name"): el for el in root.findall("joint")}
    fixed_children: dict[str, list[str]] = {}
    for fixed in joints.values():
        if fixed.get("type") == "fixed":
            fixed_children.setdefault(_attr(fixed, "parent"), []).append(_attr(fixed, "child"))
    for i, joint in enumerate(robot.joints):
        found = joints.get(joint.name)
        if found is None:
            raise RobotFileError(str(source), joint.name, "no such joint in the URDF")
        el = found
        child = _attr(el, "child")
        # every link welded to the child is part of the identified body
        stack = list(fixed_children.get(child, []))
        while stack:
            name = stack.pop()
            for old in links[name].findall("inertial"):
                links[name].remove(old)
            stack += fixed_children.get(name, [])
        link = links[child]
        for old in link.findall("inertial"):
            link.remove(old)
        link.insert(0, inertial_element(phi[10 * i : 10 * i + 10]))
        dyn = _friction(effects, i + 1)
        if dyn:
            for old in el.findall("dynamics"):
                el.remove(old)
            ET.SubElement(el, "dynamics", attrib=dyn)
    root.insert(0, ET.Comment(f" armid: inertials of {', '.join(j.name for j in robot.joints)} identified "
                              f"(physically consistent); rotor inertia is not a URDF field "))
    return tree


def _attr(joint: ET.Element, tag: str) -> str:
    el = joint.find(tag)
    if el is None or el.get("link") is None:
        raise RobotFileError("<urdf>", str(joint.get("name")), f"joint without <{tag} link=...>")
    return str(el.get("link"))


def write_urdf(path: str | Path, robot: Robot, phi: Array, effects: dict[tuple[str, int], float] | None = None) -> Path:
    """Write :func:`urdf_tree` to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tree = urdf_tree(robot, np.asarray(phi, dtype=float), effects)
    ET.indent(tree, "  ")
    tree.write(path, encoding="unicode", xml_declaration=True)
    return path


def effect_values(doc: dict[str, Any]) -> dict[tuple[str, int], float]:
    """(effect, joint) -> value from a feasible JSON document's ``effects``."""
    return {(e["effect"], int(e["joint"])): float(e["value"]) for e in doc.get("effects", [])}


def _rotation_rpy(roll: float, pitch: float, yaw: float) -> Array:
    """``Rz(yaw) Ry(pitch) Rx(roll)`` (URDF ``rpy``)."""
    cr, sr, cp, sp, cy, sy = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _transform(el: ET.Element | None) -> Array:
    """4x4 of an ``<origin xyz rpy>`` (identity when absent)."""
    t = np.eye(4)
    origin = None if el is None else el.find("origin")
    if origin is not None:
        t[:3, 3] = [float(x) for x in origin.get("xyz", "0 0 0").split()]
        t[:3, :3] = _rotation_rpy(*(float(x) for x in origin.get("rpy", "0 0 0").split()))
    return t


def _shape_box(geometry: ET.Element, placement: Array) -> tuple[Array, Array] | None:
    """Axis-aligned box (in the frame ``placement`` maps into) holding one URDF primitive;
    None for a mesh (its extent is in a file this package does not read)."""
    r, c = placement[:3, :3], placement[:3, 3]
    shape = next(iter(geometry), None)
    if shape is None:
        return None
    if shape.tag == "box":
        half = np.abs(r) @ (0.5 * np.array([float(x) for x in shape.get("size", "0 0 0").split()]))
    elif shape.tag == "sphere":
        half = np.full(3, float(shape.get("radius", "0")))
    elif shape.tag == "cylinder":  # axis z of its own frame
        radius, length = float(shape.get("radius", "0")), float(shape.get("length", "0"))
        axis = r[:, 2]
        half = np.abs(axis) * 0.5 * length + radius * np.sqrt(np.maximum(1.0 - axis**2, 0.0))
    else:
        return None
    return c - half, c + half


def collision_boxes(robot: Robot) -> list[tuple[Array, Array] | None]:
    """Per link, the axis-aligned box (lower, upper corners in m, link frame) that holds the
    URDF's ``<collision>`` geometry of the joint's child link and of every link welded to it
    (``<visual>`` where a link has no collision element). None for a link with a mesh (not
    read here), without geometry, or for a robot described by DH rows (no geometry at all).
    The physically consistent fit can keep each link's mass inside its box
    (:func:`identify.feasible.box_matrices`)."""
    source = _urdf_path(robot)
    if source is None:
        return [None] * robot.n_joints
    try:
        root = ET.parse(source).getroot()
    except (OSError, ET.ParseError) as err:
        raise RobotFileError(str(source), "", f"cannot read the URDF ({err})") from err
    links = {el.get("name"): el for el in root.findall("link")}
    joints = {el.get("name"): el for el in root.findall("joint")}
    welded: dict[str, list[tuple[str, Array]]] = {}
    for j in joints.values():
        if j.get("type") == "fixed":
            welded.setdefault(_attr(j, "parent"), []).append((_attr(j, "child"), _transform(j)))
    out: list[tuple[Array, Array] | None] = []
    for joint in robot.joints:
        el = joints.get(joint.name)
        if el is None:
            raise RobotFileError(str(source), joint.name, "no such joint in the URDF")
        stack, corners, ok = [(_attr(el, "child"), np.eye(4))], [], True
        while stack and ok:
            name, placement = stack.pop()
            link = links.get(name)
            if link is None:
                continue
            shapes = link.findall("collision") or link.findall("visual")
            for shape in shapes:
                geometry = shape.find("geometry")
                box = None if geometry is None else _shape_box(geometry, placement @ _transform(shape))
                if box is None:
                    ok = False
                    break
                corners += list(box)
            stack += [(child, placement @ t) for child, t in welded.get(name, [])]
        out.append((np.min(corners, axis=0), np.max(corners, axis=0)) if ok and corners else None)
    return out

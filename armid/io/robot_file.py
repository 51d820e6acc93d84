"""Loading robot descriptions (INTERFACES.md 'Robot description') into :class:`Robot`.

Precedence for a URDF-based file: values the YAML gives for a joint (``limits``,
``inertial``, ``torque_constant``) override the URDF's; everything else comes from the URDF.
A joint's ``type`` beside ``urdf:`` may repeat what the URDF says; one that contradicts it is
refused, naming both. Continuous joints are revolute joints without position limits; the
URDF's joints the file does not list are locked at zero (Pinocchio's reduced model). Every
problem raises :class:`RobotFileError` naming the file, the field and what is wrong.

Modeled inertias must be physical: a negative mass or a negative principal moment of
inertia is refused (a URDF's own negative moment only warns: CAD exports round, and the
values are only the prior). Principal moments that break the triangle inequality
(``I1 + I2 >= I3``) give an :class:`ImplausibleDataWarning` only: published values often do
(the PUMA 560's links 1 and 3, Armstrong et al. 1986) and the torques stay well defined.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from armid.identify.effects import CATALOGUE, FIXED, LINEAR_EFFECTS, LOAD_DEPENDENT, PROFILED, SETTINGS
from armid.identify.errors import ImplausibleDataWarning, RobotFileError
from armid.identify.robot import (
    DeclaredEffect,
    Inertial,
    Joint,
    JointLimits,
    JointType,
    Robot,
    dh_joint,
    inertia_entries,
    inertia_matrix,
    mdh_joint,
)

CONVENTIONS = ("dh", "mdh")
TOP_LEVEL = {"name", "gravity", "convention", "urdf", "joints", "effects", "description", "effort"}
EFFORTS = ("torque", "current")
"""What a ROS 2 JointState's ``effort`` holds for the arm (``effort:``; torque unless said)."""
JOINT_FIELDS = {"name", "type", "a", "alpha", "d", "theta", "torque_constant", "torque_constant_std", "limits", "inertial"}
DEFAULT_TORQUE_CONSTANT_STD = 0.05
"""A torque constant the file gives (N*m per A from a datasheet) is known to about 5 %, and a
torque measured through it is off by as much; a joint without one reports its torque (a sensor)."""


def load_robot(path: str | Path) -> Robot:
    """Read and check a robot YAML file, or make a robot of a URDF (:func:`robot_from_urdf`)."""
    import yaml

    path = Path(path)
    src = str(path)
    if path.suffix.lower() == ".urdf":
        return robot_from_urdf(path)
    try:
        text = bounded_read(path, src, "").decode()
    except UnicodeDecodeError as err:
        raise RobotFileError(src, "", f"not a text file ({err.reason})") from None
    try:
        doc = yaml.safe_load(text)
    except RecursionError:
        raise RobotFileError(src, "", "nested too deeply to be a robot description") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else "YAML"
        raise RobotFileError(src, where, f"not valid YAML ({getattr(err, 'problem', err)})") from err
    return robot_from_dict(doc, src, path.parent)


ROBOT_FILE_LIMIT_BYTES = 32 * 1024 * 1024
"""The largest robot file or URDF read (meshes are files of their own): a path to a device or
a pipe (``/dev/zero``) is refused before it is read, a file larger than this is too."""


def bounded_read(path: Path, src: str, where: str) -> bytes:
    """The bytes of a robot file or a URDF: a regular file of at most :data:`ROBOT_FILE_LIMIT_BYTES`,
    else a :class:`RobotFileError` that says what the path is. ``src`` and ``where``: the file
    and field the error names (``where`` empty for the file itself)."""
    try:
        info = path.stat()
    except FileNotFoundError:
        raise RobotFileError(src, where, "no such file" if not where else f"no such file {path}") from None
    except OSError as err:
        raise RobotFileError(src, where, f"cannot read {path} ({err.strerror or type(err).__name__})") from None
    import stat

    named = f"{path} is " if where else ""
    if not stat.S_ISREG(info.st_mode):
        kind = ("a directory" if stat.S_ISDIR(info.st_mode) else "a device" if stat.S_ISCHR(info.st_mode) or stat.S_ISBLK(info.st_mode)
                else "a pipe" if stat.S_ISFIFO(info.st_mode) else "a socket" if stat.S_ISSOCK(info.st_mode) else "not a regular file")
        raise RobotFileError(src, where, f"{named}{kind}, not a regular file: a robot description is read from a file")
    if info.st_size > ROBOT_FILE_LIMIT_BYTES:
        raise RobotFileError(src, where, f"{named}{info.st_size / 2**20:.0f} MiB, larger than any robot description "
                                         f"(at most {ROBOT_FILE_LIMIT_BYTES // 2**20} MiB are read)")
    try:
        with path.open("rb") as f:
            data = f.read(ROBOT_FILE_LIMIT_BYTES + 1)
    except OSError as err:
        raise RobotFileError(src, where, f"cannot read {path} ({err.strerror or type(err).__name__})") from None
    if len(data) > ROBOT_FILE_LIMIT_BYTES:  # it grew while read
        raise RobotFileError(src, where, f"{named}more than {ROBOT_FILE_LIMIT_BYTES // 2**20} MiB: not a robot description")
    return data


def robot_from_urdf(path: Path) -> Robot:
    """A robot of a URDF alone, as a robot file ``{name, urdf, joints}`` makes it: its movable
    joints in the model's order, torque constant 1 (torques in N*m), gravity -z, no effects
    declared. A robot file around the URDF adds friction, limits and torque constants."""
    src = str(path)
    model = _urdf_model(path, src)
    movable = [str(model.names[i]) for i in range(1, model.njoints) if model.joints[i].nq > 0]
    if not movable:
        raise RobotFileError(src, "urdf", "no movable joint")
    return robot_from_dict({"name": str(model.name) or path.stem, "urdf": path.name, "joints": [{"name": n} for n in movable]}, src, path.parent)


def robot_from_dict(doc: Any, src: str = "<robot>", base_dir: Path | None = None) -> Robot:
    """Build a robot from the parsed YAML mapping (see module docstring)."""
    if not isinstance(doc, dict):
        raise RobotFileError(src, "", "the file must be a mapping with name, joints, ...")
    unknown = set(doc) - TOP_LEVEL
    if unknown:
        raise RobotFileError(src, sorted(unknown)[0], f"unknown field (allowed: {', '.join(sorted(TOP_LEVEL))})")
    name = doc.get("name")
    if not isinstance(name, str) or not name:
        raise RobotFileError(src, "name", "must be a non-empty string")
    gravity = _vector(doc.get("gravity", [0.0, 0.0, -9.81]), 3, src, "gravity")
    joints_doc = doc.get("joints")
    if not isinstance(joints_doc, list) or not joints_doc:
        raise RobotFileError(src, "joints", "must be a non-empty list of joints")
    if "urdf" in doc:
        joints = _urdf_joints(doc, joints_doc, src, base_dir or Path("."))
    else:
        convention = doc.get("convention", "dh")
        if convention not in CONVENTIONS:
            raise RobotFileError(src, "convention", f"must be one of {', '.join(CONVENTIONS)} (or give urdf:), got {convention!r}")
        joints = [_dh_joint(j, k, convention, src) for k, j in enumerate(joints_doc)]
    names = [j.name for j in joints]
    dup = sorted({x for x in names if names.count(x) > 1})
    if dup:
        raise RobotFileError(src, "joints", f"duplicate joint name {dup[0]!r}")
    effects = _effects(doc.get("effects", []) or [], len(joints), src)
    return Robot(name, gravity, tuple(joints), tuple(effects), src, _effort(doc, joints_doc, src))


def _effort(doc: dict[str, Any], joints_doc: list[Any], src: str) -> str:
    """``effort:`` (:data:`EFFORTS`): ``current`` needs every joint's own ``torque_constant``,
    the one figure that makes its current a torque (a default of 1 would pass amperes for N*m)."""
    effort = doc.get("effort", "torque")
    if effort not in EFFORTS:
        raise RobotFileError(src, "effort", f"must be one of {', '.join(EFFORTS)} (what a ROS 2 JointState's effort holds), got {effort!r}")
    if effort == "current":
        lacking = [str(j.get("name", f"joints[{k}]")) for k, j in enumerate(joints_doc) if isinstance(j, dict) and "torque_constant" not in j]
        if lacking:
            raise RobotFileError(src, "effort", f"current needs each joint's torque_constant (N*m per A); none for {', '.join(lacking)}")
    return str(effort)


def _field(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def _number(value: Any, src: str, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise RobotFileError(src, where, f"must be a number, got {value!r}")
    if not np.isfinite(value):
        raise RobotFileError(src, where, f"must be finite, got {value!r}")
    return float(value)


def _vector(value: Any, size: int, src: str, where: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != size:
        raise RobotFileError(src, where, f"must be a list of {size} numbers, got {value!r}")
    return np.array([_number(v, src, f"{where}[{k}]") for k, v in enumerate(value)])


def _joint_type(j: dict[str, Any], src: str, where: str) -> JointType:
    kind = j.get("type", "revolute")
    try:
        return JointType(kind)
    except ValueError:
        raise RobotFileError(src, _field(where, "type"), f"must be revolute or prismatic, got {kind!r}") from None


def _dh_joint(j: Any, k: int, convention: str, src: str) -> Joint:
    where = f"joints[{k}]"
    if not isinstance(j, dict):
        raise RobotFileError(src, where, "must be a mapping")
    unknown = set(j) - JOINT_FIELDS
    if unknown:
        raise RobotFileError(src, _field(where, sorted(unknown)[0]), f"unknown field (allowed: {', '.join(sorted(JOINT_FIELDS))})")
    kind = _joint_type(j, src, where)
    values = {}
    for key in ("a", "alpha", "d", "theta"):
        if key not in j:
            raise RobotFileError(src, _field(where, key), f"missing ({convention} needs a, alpha, d, theta)")
        values[key] = _number(j[key], src, _field(where, key))
    make = dh_joint if convention == "dh" else mdh_joint
    pre, axis, post = make(kind, values["a"], values["alpha"], values["d"], values["theta"])
    name = str(j.get("name", f"j{k + 1}"))
    return Joint(name, kind, pre, axis, post, *_joint_extras(j, src, where, None, None))


def _joint_extras(j: dict[str, Any], src: str, where: str, limits: JointLimits | None,
                  inertial: Inertial | None) -> tuple[float, JointLimits, Inertial | None, float]:
    kt = _number(j.get("torque_constant", 1.0), src, _field(where, "torque_constant"))
    if kt <= 0:
        raise RobotFileError(src, _field(where, "torque_constant"), f"must be positive, got {kt}")
    kt_std = _number(j.get("torque_constant_std", DEFAULT_TORQUE_CONSTANT_STD if "torque_constant" in j else 0.0), src,
                     _field(where, "torque_constant_std"))
    if not 0.0 <= kt_std < 1.0:
        raise RobotFileError(src, _field(where, "torque_constant_std"), f"must be a fraction in [0, 1) (0.05: 5 %), got {kt_std}")
    if "limits" in j:
        limits = _limits(j["limits"], src, _field(where, "limits"))
    if "inertial" in j:
        inertial = _inertial(j["inertial"], src, _field(where, "inertial"))
    return kt, limits or JointLimits(), inertial, kt_std


def _limits(doc: Any, src: str, where: str) -> JointLimits:
    if not isinstance(doc, dict):
        raise RobotFileError(src, where, "must be a mapping with position, velocity, torque")
    unknown = set(doc) - {"position", "velocity", "acceleration", "torque"}
    if unknown:
        raise RobotFileError(src, _field(where, sorted(unknown)[0]), "unknown limit (position, velocity, acceleration, torque)")
    pos = None
    if doc.get("position") is not None:
        lo, hi = _vector(doc["position"], 2, src, _field(where, "position"))
        if not lo < hi:
            raise RobotFileError(src, _field(where, "position"), f"lower {lo} must be below upper {hi}")
        pos = (float(lo), float(hi))
    scalars = {}
    for key in ("velocity", "acceleration", "torque"):
        if doc.get(key) is not None:
            v = _number(doc[key], src, _field(where, key))
            if v <= 0:
                raise RobotFileError(src, _field(where, key), f"must be positive, got {v}")
            scalars[key] = v
    return JointLimits(pos, scalars.get("velocity"), scalars.get("acceleration"), scalars.get("torque"))


def _inertial(doc: Any, src: str, where: str) -> Inertial:
    if not isinstance(doc, dict):
        raise RobotFileError(src, where, "must be a mapping with mass, com, inertia")
    unknown = set(doc) - {"mass", "com", "inertia"}
    if unknown:
        raise RobotFileError(src, _field(where, sorted(unknown)[0]), "unknown field (allowed: mass, com, inertia about the COM)")
    for key in ("mass", "com", "inertia"):
        if key not in doc:
            raise RobotFileError(src, _field(where, key), "missing")
    mass = _number(doc["mass"], src, _field(where, "mass"))
    if mass < 0:
        raise RobotFileError(src, _field(where, "mass"), f"must not be negative, got {mass}")
    com = _vector(doc["com"], 3, src, _field(where, "com"))
    inertia = _vector(doc["inertia"], 6, src, _field(where, "inertia"))
    inertial = Inertial(mass, tuple(com), tuple(inertia))  # type: ignore[arg-type]
    check_physical(inertial, src, where)
    return inertial


def check_physical(inertial: Inertial, src: str, where: str, refuse: bool = True) -> None:
    """Refuse a negative mass or principal moment; warn when the principal moments break the
    triangle inequality (no rigid body has them, but published tables do). With ``refuse``
    False (a URDF's own values, which CAD exports round), a negative moment warns too: the
    values only serve as the prior, and the physically consistent fit replaces them there."""
    if inertial.mass_kg < 0:
        raise RobotFileError(src, _field(where, "mass"), f"must not be negative, got {inertial.mass_kg}")
    moments = np.linalg.eigvalsh(inertia_matrix(np.asarray(inertial.inertia_kgm2, float)))
    tol = 1e-9 * max(float(np.abs(moments).max()), 1e-12)
    shown = ", ".join(f"{m:.6g}" for m in moments)
    if moments[0] < -tol:
        problem = f"not positive semi-definite (principal moments {shown}): no body has a negative moment of inertia"
        if refuse:
            raise RobotFileError(src, _field(where, "inertia"), problem)
        warnings.warn(f"{src}: {_field(where, 'inertia')}: {problem}; used as the prior all the same (--feasible replaces it there)",
                      ImplausibleDataWarning, stacklevel=2)
        return
    if moments[0] + moments[1] < moments[2] - tol:
        warnings.warn(f"{src}: {_field(where, 'inertia')}: principal moments {shown} break the triangle inequality "
                      f"({moments[0]:.6g} + {moments[1]:.6g} < {moments[2]:.6g}): not a physical rigid body",
                      ImplausibleDataWarning, stacklevel=2)


def _effects(doc: Any, n_joints: int, src: str) -> list[DeclaredEffect]:
    if not isinstance(doc, list):
        raise RobotFileError(src, "effects", "must be a list like [{effect: coulomb_friction, joint: 2}]")
    out = []
    for k, e in enumerate(doc):
        where = f"effects[{k}]"
        if not isinstance(e, dict) or "effect" not in e:
            raise RobotFileError(src, where, "must be a mapping with an 'effect' name")
        name = e["effect"]
        if name not in CATALOGUE:
            raise RobotFileError(src, _field(where, "effect"), f"unknown effect {name!r} (catalogue: {', '.join(CATALOGUE)})")
        declarable = [*LINEAR_EFFECTS, *SETTINGS, *FIXED, *PROFILED, *LOAD_DEPENDENT]
        if name not in declarable:
            raise RobotFileError(src, _field(where, "effect"), f"{name} cannot be declared yet (declarable: {', '.join(declarable)})")
        if name in FIXED:
            key = FIXED[name]
            value = e.get(key)
            if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
                raise RobotFileError(src, _field(where, key), f"{name} needs {key}: a period > 0 in the joint's position (rad, or m), got {value!r}")
        if (name in SETTINGS or name in LOAD_DEPENDENT) and "velocity" in e and (isinstance(e["velocity"], bool) or not isinstance(e["velocity"], int | float) or e["velocity"] < 0):
            raise RobotFileError(src, _field(where, "velocity"), f"must be a velocity >= 0 (rad/s or m/s), got {e['velocity']!r}")
        joint = e.get("joint")
        if joint is not None and (isinstance(joint, bool) or not isinstance(joint, int) or not 1 <= joint <= n_joints):
            raise RobotFileError(src, _field(where, "joint"), f"must be a joint number 1..{n_joints} or null (all joints), got {joint!r}")
        if "modeled" in e:
            _modeled_effect(e["modeled"], name, n_joints if joint is None else 1, src, _field(where, "modeled"))
        out.append(DeclaredEffect(name, joint, {k2: v for k2, v in e.items() if k2 not in ("effect", "joint")}))
    gains = {j for e in out if e.effect in PROFILED for j in (range(1, n_joints + 1) if e.joint is None else [e.joint])}
    if n_joints > 0 and len(gains) == n_joints:
        k = next(k for k, e in enumerate(out) if e.effect in PROFILED)
        raise RobotFileError(src, f"effects[{k}]", "torque_gain on every joint: one overall scale of the torque is not identifiable from "
                             "motion alone (every torque and every parameter scaled alike fit equally); declare it on at most "
                             f"{n_joints - 1} joints (the others' torque constants set the scale), or use a torque reference")
    return out


MODELED_EFFECTS = {"viscous_friction": True, "coulomb_friction": True, "rotor_inertia": True, "torque_offset": False, "spring": False}
"""Effects that may carry a modeled value (one parameter each: a datasheet's reflected rotor
inertia, a known friction), and whether it must be >= 0. The single-link sequence takes it
for what an experiment cannot separate (identify.single_link.held_motion_torque)."""


def _modeled_effect(value: Any, name: str, count: int, src: str, where: str) -> None:
    """An effect's modeled value: one number (one joint), or one per joint for ``joint: null``."""
    if name not in MODELED_EFFECTS:
        raise RobotFileError(src, where, f"{name} takes no modeled value (one is read for: {', '.join(MODELED_EFFECTS)})")
    values = value if isinstance(value, list) else [value]
    if len(values) != count:
        raise RobotFileError(src, where, f"needs {'one number' if count == 1 else f'a number per joint ({count})'}, got {value!r}")
    for v in values:
        if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v):
            raise RobotFileError(src, where, f"must be finite numbers, got {v!r}")
        if MODELED_EFFECTS[name] and v < 0:
            raise RobotFileError(src, where, f"must be >= 0 (no friction or inertia is negative), got {v!r}")


def _joint_axis(jm: Any, revolute: bool) -> np.ndarray:
    """The joint's unit axis in its own frame, from its motion subspace (any aligned, unaligned or continuous joint)."""
    jd = jm.createData()
    q = np.zeros(jm.nq)
    if jm.nq == 2:  # continuous joint: q = (cos, sin)
        q[0] = 1.0
    jm.calc(jd, q)
    s = np.asarray(jd.S, dtype=float).reshape(6)
    axis = s[3:] if revolute else s[:3]
    return axis / np.linalg.norm(axis)


def _lock_unlisted(model: Any, joints_doc: list[Any], src: str, urdf: Path) -> Any:
    """The URDF's model with the joints the robot file does not list locked at zero, their
    links merged into their parents' (a gripper's fingers into the hand, an unrecorded torso
    into the base), as a recording of the listed joints sees them. A locked joint between the
    base and the last listed one is warned about: if it moves, the model is wrong."""
    import pinocchio as pin

    for k, j in enumerate(joints_doc):
        if not isinstance(j, dict) or "name" not in j:
            raise RobotFileError(src, f"joints[{k}]", "must be a mapping with the URDF joint's name")
        if not model.existJointName(str(j["name"])):
            movable = [model.names[i] for i in range(1, model.njoints)]
            raise RobotFileError(src, f"joints[{k}].name", f"no joint {j['name']!r} in {urdf.name} (movable joints: {', '.join(movable)})")
    listed = [model.getJointId(str(j["name"])) for j in joints_doc]
    unlisted = [i for i in range(1, model.njoints) if i not in listed]
    if not unlisted:
        return model
    upstream = set()
    for jid in listed:  # every joint on the way from the base to a listed one
        while jid > 0:
            upstream.add(jid)
            jid = model.parents[jid]
    skipped = [model.names[i] for i in unlisted if i in upstream]
    if skipped:
        warnings.warn(f"{src}: joints: not listed, yet between the base and the listed joints of {urdf.name}: {', '.join(skipped)}; "
                      "held at zero (list each that moves)", ImplausibleDataWarning, stacklevel=3)
    return pin.buildReducedModel(model, unlisted, pin.neutral(model))


@contextlib.contextmanager
def _stderr_of_c_code() -> Iterator[Callable[[], list[str]]]:
    """Hold what C++ code (urdfdom) writes to file descriptor 2 while parsing: a bad URDF then
    ends in armid's one error line, which quotes the parser's first line of complaint."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as held:
        os.dup2(held.fileno(), 2)
        lines: list[str] = []
        try:
            yield lambda: lines
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            held.seek(0)
            lines += [" ".join(x.split()) for x in held.read().decode(errors="replace").splitlines() if x.strip()]


def _urdf_model(urdf: Path, src: str) -> Any:
    """The URDF loaded through Pinocchio, or a :class:`RobotFileError` that names what is wrong."""
    import pinocchio as pin

    bounded_read(urdf, src, "urdf")  # a regular file of a robot's size: the parser reads without a bound
    with _stderr_of_c_code() as parser_said:
        try:
            model = pin.buildModelFromUrdf(str(urdf))
            err = None
        except Exception as caught:  # Pinocchio raises ValueError/RuntimeError on a bad URDF
            err = caught
    if err is not None:
        hint = " (a xacro file: expand it first, `xacro robot.urdf.xacro > robot.urdf`)" if urdf.name.endswith(".xacro") else ""
        said = " ".join(parser_said()[:1])
        raise RobotFileError(src, "urdf", f"{urdf}: not a loadable URDF{hint} ({said or err})") from err
    dropped = [line for line in parser_said() if line.startswith("Error:")]
    if dropped:  # urdfdom leaves out what it cannot parse (a link's inertial with a nan in it) and goes on
        raise RobotFileError(src, "urdf", f"{urdf}: the URDF parser left part of it out ({'; '.join(dropped[:2])})")
    return model


def _urdf_joints(doc: dict[str, Any], joints_doc: list[Any], src: str, base_dir: Path) -> list[Joint]:
    """Joints matched by name in a URDF loaded through Pinocchio (link frame = child frame)."""
    urdf = base_dir / str(doc["urdf"])
    model = _lock_unlisted(_urdf_model(urdf, src), joints_doc, src, urdf)
    joints = []
    previous = 0
    for k, j in enumerate(joints_doc):
        where = f"joints[{k}]"
        extra = set(j) - {"name", "type", "torque_constant", "torque_constant_std", "limits", "inertial"}
        if extra:
            raise RobotFileError(src, _field(where, sorted(extra)[0]), "not allowed with urdf (kinematics come from the URDF)")
        name = str(j["name"])
        jid = model.getJointId(name)
        if model.parents[jid] != previous:
            raise RobotFileError(src, _field(where, "name"), f"{name!r} does not follow the previous joint in the chain of {urdf.name}")
        jm = model.joints[jid]
        short = jm.shortname()
        revolute, prismatic = short.startswith("JointModelR"), short.startswith("JointModelP")
        if jm.nv != 1 or not (revolute or prismatic):
            raise RobotFileError(src, _field(where, "name"), f"{name!r} is a {short}; only revolute (bounded or continuous) and prismatic joints are supported")
        axis = _joint_axis(jm, revolute)
        placement = model.jointPlacements[jid].homogeneous
        inert = model.inertias[jid]
        inertial = Inertial(float(inert.mass), tuple(float(x) for x in inert.lever), tuple(float(x) for x in inertia_entries(inert.inertia)))  # type: ignore[arg-type]
        iq, iv = model.idx_qs[jid], model.idx_vs[jid]
        # a continuous joint (nq 2: cos, sin) has no position limits
        lo, hi = (float(model.lowerPositionLimit[iq]), float(model.upperPositionLimit[iq])) if jm.nq == 1 else (np.nan, np.nan)
        vel, eff = float(model.velocityLimit[iv]), float(model.effortLimit[iv])
        limits = JointLimits(
            (lo, hi) if np.isfinite(lo) and np.isfinite(hi) and lo < hi else None,
            vel if np.isfinite(vel) and vel > 0 else None,
            None,
            eff if np.isfinite(eff) and eff > 0 else None,
        )
        kind = JointType.REVOLUTE if revolute else JointType.PRISMATIC
        if "type" in j:
            said = _joint_type(j, src, where)
            if said is not kind:
                raise RobotFileError(src, _field(where, "type"), f"{said.value} here, but {urdf.name} makes {name!r} {kind.value}")
        if "inertial" not in j:  # the file's own inertial replaces the URDF's, and is checked as read
            check_physical(inertial, src, f"{where} ({urdf.name})", refuse=False)
        joints.append(Joint(name, kind, placement, axis, np.eye(4), *_joint_extras(j, src, where, limits, inertial)))
        previous = jid
    return joints

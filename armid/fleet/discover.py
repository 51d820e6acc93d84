"""A fleet's folder: one sub-folder per arm, each with its robot file and its recordings.

``ROOT/<arm>/robot.yaml`` describes the arm (its kinematics, modeled inertials, declared
effects); every ``*.csv``, ``*.mcap``, ``*.npz`` and ``*.db3`` below ``ROOT/<arm>/``, in any
sub-folder, is one of its recordings, and so is every rosbag2 bag's folder (its ``metadata.yaml``
beside its storage files, which are not read on their own). Hidden files and folders, and the output folder when it lies
inside ROOT, are not read. A folder without a robot file is not an arm: it is said, and
left alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from armid.io.ros2_bag import is_bag_folder
from armid.schema.errors import InputFileError

from .task import RECORDING_SUFFIXES, Job

ROBOT_FILE = "robot.yaml"


@dataclass(frozen=True)
class ArmFolder:
    """An arm: its folder's name, its robot file, its recordings relative to ROOT (by name)."""

    name: str
    robot_file: Path
    recordings: tuple[str, ...]


def _visible(path: Path, base: Path) -> bool:
    return not any(part.startswith(".") for part in path.relative_to(base).parts)


def find_arms(root: Path, skip: Path | None = None) -> tuple[list[ArmFolder], list[str]]:
    """The arms under ``root`` and notes on what was left out. Raises :class:`InputFileError`
    when ``root`` is not a folder or holds no arm."""
    if not root.is_dir():
        raise InputFileError(str(root), "", "no such folder (the fleet's root: ROOT/<arm>/robot.yaml and each arm's recordings)")
    skip = skip.resolve() if skip is not None else None
    arms, notes = [], []
    for folder in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        if skip is not None and folder.resolve() == skip:
            continue
        robot = folder / ROBOT_FILE
        if not robot.is_file():
            notes.append(f"{folder.name}/: no {ROBOT_FILE}, not an arm: left out")
            continue
        bags = [p for p in folder.rglob("*") if is_bag_folder(p)]
        found = sorted(p for p in folder.rglob("*") if (is_bag_folder(p) or (p.is_file() and p.suffix.lower() in RECORDING_SUFFIXES))
                       and _visible(p, folder) and not any(b in p.parents for b in bags)
                       and (skip is None or skip not in p.resolve().parents))
        if not found:
            notes.append(f"{folder.name}/: no recording (*.csv, *.mcap, *.npz, *.db3, a rosbag2 bag's folder)")
        arms.append(ArmFolder(folder.name, robot, tuple(p.relative_to(root).as_posix() for p in found)))
    loose = [p.name for p in root.iterdir() if p.is_file() and p.suffix.lower() in RECORDING_SUFFIXES]
    if loose:
        notes.append(f"{len(loose)} recording(s) directly in ROOT belong to no arm: left out ({', '.join(sorted(loose)[:3])}"
                     + (", ..." if len(loose) > 3 else "") + ")")
    if not arms:
        raise InputFileError(str(root), "", f"no arm in it: an arm is a folder with a {ROBOT_FILE} and its recordings")
    return arms, notes


def jobs_of(arms: list[ArmFolder], root: Path, topic: str | None = None) -> list[Job]:
    """One job per recording, arm by arm (``topic``: the JointState topic of the rosbag2 bags)."""
    return [Job(arm.name, str(root), rec, str(arm.robot_file), topic) for arm in arms for rec in arm.recordings]

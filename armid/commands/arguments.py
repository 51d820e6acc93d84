"""What the options' values mean: argparse types that refuse a bad value in one line, and
``--robot`` (a robot file, a URDF, or the name of a shipped robot)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from armid.schema.errors import RobotFileError

ROBOT_HELP = "robot file (YAML), a URDF, or the name of a shipped robot (puma560, kuka_lwr4, ...)"
RECORDINGS = "CSV, NPZ, MCAP, or a rosbag2 bag: its folder or its .db3/.mcap file"
"""What a command that reads recordings takes (``armid.io.recordings.recording_kind``)."""


def finite_number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    return value


def positive_number(text: str) -> float:
    """A finite number above zero (durations, frequencies, limits)."""
    value = finite_number(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return value


def gap_factor(text: str) -> float:
    """A step this many median steps long splits a log: below 2 every jitter would split it."""
    value = finite_number(text)
    if value < 2:
        raise argparse.ArgumentTypeError(f"must be at least 2 (median steps), got {text}")
    return value


def whole_count(text: str) -> int:
    """A whole number of at least 1 (periods)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text}")
    return value


def seed_number(text: str) -> int:
    """NumPy seeds are whole numbers from 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {text}")
    return value


LOWPASS_WORDS = ("off", "auto")


def lowpass_setting(text: str) -> float | str:
    """A cutoff in Hz (checked against each recording's Nyquist frequency once it is read),
    or one of the words ``off`` and ``auto``, passed through as given."""
    if text.strip().lower() in LOWPASS_WORDS:
        return text.strip().lower()
    value = finite_number(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive cutoff in Hz, 'off' or 'auto', got {text}")
    return value


def load_robot_argument(value: str) -> Any:
    """``--robot``: a robot file's path, a URDF's path (a robot of the URDF alone), or the name
    of a shipped robot (``puma560``, ``kuka_lwr4``, ...: ``config/robots/NAME.yaml``)."""
    from armid.io.robot_file import load_robot
    from armid.resources import config_file

    path = Path(value)
    if not path.exists() and "/" not in value and not path.suffix:
        shipped = config_file(f"robots/{value}.yaml")
        if shipped.is_file():
            return load_robot(shipped)
        names = sorted(p.stem for p in config_file("robots").glob("*.yaml"))
        raise RobotFileError(value, "", f"no such file, nor a shipped robot (shipped: {', '.join(names)})")
    return load_robot(path)


def ros2_topic(text: str) -> str:
    """A ROS 2 topic name, fully qualified as a bag stores it (``joint_states``: ``/joint_states``)."""
    name = text.strip()
    if not name or any(c.isspace() for c in name):
        raise argparse.ArgumentTypeError(f"{text!r} is not a ROS 2 topic name")
    return name if name.startswith("/") else "/" + name


def add_topic_argument(p: argparse.ArgumentParser) -> None:
    """``--topic``: which topic of a rosbag2 bag holds the arm's ``sensor_msgs/msg/JointState``."""
    p.add_argument("--topic", type=ros2_topic, default=None, metavar="TOPIC",
                   help="the sensor_msgs/msg/JointState topic read from a rosbag2 bag (default /joint_states; other recordings "
                        "have no topic)")

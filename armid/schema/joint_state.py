"""The joint-state record: one cycle of every joint, its units, and its one binary codec.

Units are SI at the joint, everywhere after the driver: position in rad (m for a prismatic
joint), velocity in rad/s (m/s), current in A, torque in N*m (N). The driver applies each
joint's torque constant to the measured current, ``torque = measured_current * torque_constant``,
and the torque travels beside the currents: a reader takes it as recorded. Where a recording
carries currents only (a CSV's ``i1..in``), the reader applies
the robot file's torque constant instead (``armid.io.recordings``); a torque command is divided
by it into a current. Each record is scaled once.

Binary codec (the Zenoh stream): the schema's name and version travel in the Zenoh
encoding (``application/octet-stream;armid.JointState/2``), so a subscriber knows what it
holds before it decodes a byte. Layout, little-endian: a 32-byte header (sequence u64,
cycle u64, time f64, joint count u16, flags u16, reserved u32), then 44 bytes per joint
(valid u8, velocity fresh u8, statusword u16, position, velocity, commanded current,
measured current, torque f64); a payload holds one such record or several back to back.
``sequence`` counts records without gaps, so that a subscriber can see what it missed. The
codec is :class:`~armid.schema.joint_states.JointStates`' (the record as columns).

Recordings (MCAP) carry the same record as ROS 2 messages: ``sensor_msgs/msg/JointState``
on ``/joint_states`` (position, velocity, effort = torque) and the rest in
``armid_msgs/msg/JointStateExtra`` on ``/armid/joint_state_extra`` (:data:`ROS2_MSGDEFS`; their CDR
codec is :mod:`armid.io.ros2_cdr`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .errors import RecordFormatError

Array = NDArray[np.float64]

SCHEMA = "armid.JointState"
VERSION = 2
ENCODING = f"application/octet-stream;{SCHEMA}/{VERSION}"


@dataclass
class Sample:
    """One cycle of every joint, keyed by the cycle counter (not by arrival time), SI units.

    ``valid[j]`` is False when joint j's frames for this cycle did not arrive by the
    deadline; its values are then the last known ones. ``velocity_fresh[j]`` is False when
    the plan did not carry velocity this cycle (the value is the last reported one).
    ``commanded_current`` is what was in force during the period that ends at this cycle.
    ``torque`` is ``measured_current`` times each joint's torque constant (N*m or N), set by
    the driver; ``None`` only for a sample built by hand without one.
    """

    cycle: int
    time_s: float
    valid: Array
    position: Array
    velocity: Array
    velocity_fresh: Array
    commanded_current: Array
    measured_current: Array
    status: Array  # statusword per joint (0 when unknown)
    torque: Array | None = None

    @staticmethod
    def empty(cycle: int, time_s: float, n: int) -> Sample:
        z = np.zeros(n)
        return Sample(cycle, time_s, np.zeros(n, bool), z.copy(), z.copy(), np.zeros(n, bool), z.copy(), z.copy(), np.zeros(n, np.int64),
                      z.copy())

    def joint_torque(self) -> Array:
        """``torque``; a sample built without one has NaN (never a silent zero)."""
        return self.torque if self.torque is not None else np.full(self.measured_current.shape, np.nan)


@dataclass
class JointStateRecord:
    """One numbered sample: a cycle of :class:`~armid.schema.joint_states.JointStates` as the ROS 2
    writer takes it (:meth:`JointStates.record <armid.schema.joint_states.JointStates.record>`)."""

    sequence: int
    sample: Sample


def check_encoding(encoding: str) -> None:
    """Refuse a record whose schema or version this code does not read."""
    if not encoding.endswith(f";{SCHEMA}/{VERSION}"):
        raise RecordFormatError(f"encoding {encoding!r} is not {ENCODING!r}")


# --- the same record as ROS 2 messages (MCAP recordings) ---
JOINT_STATES_TOPIC = "/joint_states"
EXTRA_TOPIC = "/armid/joint_state_extra"
JOINT_STATE_TYPE = "sensor_msgs/msg/JointState"
EXTRA_TYPE = "armid_msgs/msg/JointStateExtra"

_HEADER_DEFS = """================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec"""

ROS2_MSGDEFS = {
    JOINT_STATE_TYPE: "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\nfloat64[] effort\n" + _HEADER_DEFS,
    EXTRA_TYPE: ("# armid's part of a joint-state record; header.stamp equals the /joint_states message's\n"
                 "std_msgs/Header header\nuint64 sequence\nuint64 cycle\nbool[] valid\nbool[] velocity_fresh\n"
                 "float64[] commanded_current\nfloat64[] measured_current\nuint16[] statusword\n" + _HEADER_DEFS),
}
"""``ros2msg`` schema text of each message type, as rosbag2 writes it (dependencies after ``MSG:`` lines)."""


ROS2_SECONDS = (-(2.0**31), 2.0**31)
"""The stamps ``builtin_interfaces/Time`` can hold (``sec`` is an int32)."""

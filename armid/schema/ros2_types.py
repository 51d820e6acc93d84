"""The ROS 2 message types armid publishes live (beside the recording's, :data:`~armid.schema.joint_state.ROS2_MSGDEFS`).

``ros2msg`` text as rosbag2 stores it (dependencies after ``MSG:`` lines), the ROS 2 definitions
field for field (their comments left out: a type's hash, REP-2016, does not read them):
``geometry_msgs/msg/InertiaStamped`` (a payload's or a link's mass, centre of mass and inertia
about the centre of mass, in ``header.frame_id``'s axes) and ``diagnostic_msgs/msg/DiagnosticArray``
(findings and drive faults). Their CDR is :mod:`armid.io.ros2_cdr`'s, their rmw_zenoh key
expressions and type hashes :mod:`armid.io.rmw_zenoh`'s.
"""

from __future__ import annotations

from .joint_state import JOINT_STATE_TYPE

INERTIA_STAMPED_TYPE = "geometry_msgs/msg/InertiaStamped"
DIAGNOSTIC_ARRAY_TYPE = "diagnostic_msgs/msg/DiagnosticArray"

_SEPARATOR = "=" * 80
_HEADER = f"""{_SEPARATOR}
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
{_SEPARATOR}
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec"""

LIVE_MSGDEFS = {
    INERTIA_STAMPED_TYPE: f"""std_msgs/Header header
geometry_msgs/Inertia inertia
{_SEPARATOR}
MSG: geometry_msgs/Inertia
float64 m
geometry_msgs/Vector3 com
float64 ixx
float64 ixy
float64 ixz
float64 iyy
float64 iyz
float64 izz
{_SEPARATOR}
MSG: geometry_msgs/Vector3
float64 x
float64 y
float64 z
{_HEADER}""",
    DIAGNOSTIC_ARRAY_TYPE: f"""std_msgs/Header header
diagnostic_msgs/DiagnosticStatus[] status
{_SEPARATOR}
MSG: diagnostic_msgs/DiagnosticStatus
byte OK=0
byte WARN=1
byte ERROR=2
byte STALE=3
byte level
string name
string message
string hardware_id
diagnostic_msgs/KeyValue[] values
{_SEPARATOR}
MSG: diagnostic_msgs/KeyValue
string key
string value
{_HEADER}""",
}
"""``ros2msg`` schema text of each live message type."""

LIVE_TYPES = (JOINT_STATE_TYPE, INERTIA_STAMPED_TYPE, DIAGNOSTIC_ARRAY_TYPE)
"""What armid publishes over rmw_zenoh."""

DIAGNOSTIC_LEVELS = {"ok": 0, "warn": 1, "error": 2, "stale": 3}
"""``diagnostic_msgs/msg/DiagnosticStatus`` levels (its ``byte`` constants)."""

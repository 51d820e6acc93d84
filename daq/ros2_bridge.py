"""armid's live keys as ROS 2 topics: the one place armid publishes to ROS 2 (``--ros2``).

Whatever a command puts on armid's own keys (``armid/<robot>/joint_state``, ``events``,
``estimate/parameters``, ``estimate/payload``: docs/reference/zenoh.md) this bridge hears on
the same session and publishes again over rmw_zenoh (:mod:`armid.io.rmw_zenoh`), as a node
``armid_<robot>``:

| topic | type | from |
|---|---|---|
| ``/armid/<robot>/joint_states`` | ``sensor_msgs/msg/JointState`` | each record: the robot file's joint names, position, velocity, effort = joint torque, header stamp = the record's time |
| ``/armid/<robot>/payload`` | ``geometry_msgs/msg/InertiaStamped`` | each payload estimate with a mass, centre of mass and inertia (frame ``link<N>``, the last link) |
| ``/armid/<robot>/inertia/link<i>`` | ``geometry_msgs/msg/InertiaStamped`` | each parameters document: every link of which the newest whole-arm fit identifies a parameter (:func:`link_inertials`) |
| ``/armid/<robot>/diagnostics`` | ``diagnostic_msgs/msg/DiagnosticArray`` | drive faults (ERROR) and events (WARN), a run that stopped (WARN), each experiment's outcome (OK, or WARN with the reason it was not identified) |

Zenoh's callbacks only queue bytes; one thread of the bridge converts and publishes, so the
thread that acquires never waits on it, and a queue of ``capacity`` messages drops its oldest
when the bridge falls behind (``dropped`` counts them). ROS 2 publishers drop rather than block
(:class:`~armid.io.rmw_zenoh.Ros2Publisher`).
"""

from __future__ import annotations

import json
import threading
from collections import deque
from collections.abc import Sequence
from typing import Any

import numpy as np

from armid.identify.robot import LINK_PARAMETER_NAMES, inertial_from_parameters
from armid.io.rmw_zenoh import Ros2Node, Ros2Publisher, ros_name
from armid.io.ros2_cdr import diagnostic_array_cdr, inertia_stamped_cdr, joint_state_cdr
from armid.schema.joint_state import JOINT_STATE_TYPE
from armid.schema.joint_states import JointStates
from armid.schema.ros2_types import DIAGNOSTIC_ARRAY_TYPE, DIAGNOSTIC_LEVELS, INERTIA_STAMPED_TYPE

from .stream import key

LEAVES = ("joint_state", "events", "estimate/parameters", "estimate/payload")


def stamp_ns(t: Any) -> Any:
    """Seconds (f64) as whole nanoseconds, the whole seconds apart: ``round(t * 1e9)`` alone
    rounds to 256 ns at today's epoch."""
    t = np.asarray(t, float)
    whole = np.floor(t)
    return whole.astype(np.int64) * 1_000_000_000 + np.round((t - whole) * 1e9).astype(np.int64)


def topic_prefix(robot: str) -> str:
    return f"/armid/{ros_name(robot)}"


def link_inertials(doc: dict[str, Any]) -> dict[int, tuple[float, tuple[float, ...], tuple[float, ...], int]]:
    """Each link (1-based) of which the newest whole-arm fit of an ``estimate/parameters``
    document identifies at least one parameter, as (mass, centre of mass, inertia about it,
    how many of its ten parameters are identified): the estimate where the data identify the
    parameter, the robot file's modeled value elsewhere (a whole-arm fit identifies combinations,
    rarely a whole link); a link whose values are not a body with mass is left out."""
    source = str(doc.get("source") or "")
    whole = (doc.get("whole_arm") or {}).get(source.removeprefix("whole_arm ")) if source.startswith("whole_arm ") else None
    out: dict[int, tuple[float, tuple[float, ...], tuple[float, ...], int]] = {}
    if not whole:
        return out
    by_link: dict[int, list[dict[str, Any]]] = {}
    for p in whole.get("parameters") or []:
        by_link.setdefault(int(p["link"]), []).append(p)
    for link, params in sorted(by_link.items()):
        rows = params[: len(LINK_PARAMETER_NAMES)]
        identified = sum(bool(p.get("identified")) and p.get("value") is not None for p in rows)
        if len(rows) < len(LINK_PARAMETER_NAMES) or not identified:
            continue
        phi = np.array([float(p["value"]) if p.get("identified") and p.get("value") is not None
                        else float(p["modeled"]) if p.get("modeled") is not None else np.nan for p in rows])
        if not (np.all(np.isfinite(phi)) and phi[0] > 0):
            continue
        inertial = inertial_from_parameters(phi)
        out[link] = (inertial.mass_kg, tuple(inertial.com_m), tuple(inertial.inertia_kgm2), identified)
    return out


class Ros2Bridge:
    """Republish one robot's live keys on ``session`` as ROS 2 topics of ``node``."""

    def __init__(self, session: Any, node: Ros2Node, robot: str, joint_names: Sequence[str], listen: Sequence[str] = LEAVES,
                 capacity: int = 5000) -> None:
        self.robot = robot
        self.names = list(joint_names)
        self.node = node
        self.prefix = topic_prefix(robot)
        self.published = 0
        self.dropped = 0
        self.errors: list[str] = []
        self._inbox: deque[tuple[str, bytes]] = deque()
        self._capacity = capacity
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._publishers: dict[str, Ros2Publisher] = {}
        self._lock = threading.Lock()
        if "joint_state" in listen:
            self._publisher("joint_states", JOINT_STATE_TYPE)
        if "estimate/payload" in listen:
            self._publisher("payload", INERTIA_STAMPED_TYPE)
        self._publisher("diagnostics", DIAGNOSTIC_ARRAY_TYPE)
        self._subs = [session.declare_subscriber(key(robot, leaf), self._queue(leaf)) for leaf in listen]
        self._thread = threading.Thread(target=self._run, name="armid-ros2-bridge", daemon=True)
        self._thread.start()

    def _publisher(self, leaf: str, kind: str) -> Ros2Publisher:
        with self._lock:
            pub = self._publishers.get(leaf)
            if pub is None:
                pub = self._publishers[leaf] = self.node.publisher(f"{self.prefix}/{leaf}", kind)
            return pub

    def _queue(self, leaf: str) -> Any:
        def on_sample(sample: Any) -> None:
            try:
                if len(self._inbox) >= self._capacity:
                    self._inbox.popleft()
                    self.dropped += 1
                self._inbox.append((leaf, sample.payload.to_bytes()))
                self._wake.set()
            except Exception as err:  # a callback never kills the receive thread
                self._error(err)

        return on_sample

    def _error(self, err: BaseException) -> None:
        if len(self.errors) < 100:
            self.errors.append(f"{type(err).__name__}: {err}")

    def _run(self) -> None:
        while not self._stop.is_set() or self._inbox:
            self._wake.wait(0.05)
            self._wake.clear()
            while self._inbox:
                leaf, data = self._inbox.popleft()
                try:
                    self._forward(leaf, data)
                except Exception as err:  # one bad message costs itself only
                    self._error(err)
            if self._stop.is_set():
                return

    def _forward(self, leaf: str, data: bytes) -> None:
        if leaf == "joint_state":
            self.joint_states(JointStates.unpack(data))
            return
        doc = json.loads(data)
        if leaf == "events":
            self.event(doc)
        elif leaf == "estimate/payload":
            self.payload(doc)
        elif leaf == "estimate/parameters":
            self.parameters(doc)

    def joint_states(self, states: JointStates) -> None:
        """Each record as a ``sensor_msgs/msg/JointState`` (effort: the joint torque)."""
        pub = self._publishers["joint_states"]
        ns = stamp_ns(states.time)
        for k in range(len(states)):
            pub.put(joint_state_cdr(self.names, int(ns[k]), states.position[k], states.velocity[k], states.torque[k]))
        self.published += len(states)

    def payload(self, doc: dict[str, Any]) -> None:
        """A payload estimate that has a mass, centre of mass and inertia, in the last link's frame."""
        if doc.get("mass") is None or doc.get("com") is None or doc.get("inertia") is None:
            return
        stamp = int(stamp_ns(doc["time"]))
        frame = f"link{len(self.names)}"
        self._publisher("payload", INERTIA_STAMPED_TYPE).put(inertia_stamped_cdr(stamp, frame, doc["mass"], doc["com"], doc["inertia"]))
        self.published += 1

    def parameters(self, doc: dict[str, Any]) -> None:
        """Each identified link's inertial, and the experiment's outcome as a diagnostic."""
        stamp = int(stamp_ns(doc.get("time") or 0.0))
        e = doc.get("experiment") or {}
        v = doc.get("validation") or {}
        values = {"run": e.get("run"), "kind": e.get("kind"), "base_parameters": len(doc.get("base_parameters") or [])}
        for link, (mass, com, inertia, identified) in link_inertials(doc).items():
            name = f"link{link}"
            self._publisher(f"inertia/{name}", INERTIA_STAMPED_TYPE).put(inertia_stamped_cdr(stamp, name, mass, com, inertia))
            self.published += 1
            values[f"{name}_identified"] = f"{identified} of {len(LINK_PARAMETER_NAMES)}"
        if v.get("relative_error") is not None:
            values["validation_error_percent"] = f"{100 * float(v['relative_error']):.4g}"
        self._diagnostic(stamp, [{"level": DIAGNOSTIC_LEVELS["warn" if e.get("note") else "ok"], "name": f"armid/{self.robot}/identification",
                                  "message": e.get("note") or f"{e.get('run')}: identified", "values": values}])

    def event(self, doc: dict[str, Any]) -> None:
        """A drive fault (ERROR), a drive's event (WARN) or a run that stopped short (WARN)."""
        kind = doc.get("event")
        stamp = int(stamp_ns(doc.get("time") or 0.0))
        joint = doc.get("joint")
        name = f"armid/{self.robot}" + (f"/joint{joint}" if joint is not None else "")
        if kind == "fault":
            status = {"level": DIAGNOSTIC_LEVELS["error"], "name": name, "message": str(doc.get("meaning") or "drive fault"),
                      "hardware_id": f"node {doc.get('node')}", "values": {"code": doc.get("code")}}
        elif kind == "drive_event":
            status = {"level": DIAGNOSTIC_LEVELS["warn"], "name": name, "message": str(doc.get("message")), "values": {"type": doc.get("type")}}
        elif kind == "stop" and doc.get("completed") is False:
            status = {"level": DIAGNOSTIC_LEVELS["warn"], "name": name, "message": f"{doc.get('run')} stopped: {doc.get('reason')}"}
        else:
            return
        self._diagnostic(stamp, [status])

    def _diagnostic(self, stamp: int, statuses: list[dict[str, Any]]) -> None:
        self._publishers["diagnostics"].put(diagnostic_array_cdr(stamp, statuses))
        self.published += 1

    def close(self, wait_s: float = 2.0) -> None:
        """Publish what is queued (up to ``wait_s``), then undeclare (safe twice)."""
        for sub in self._subs:
            try:
                sub.undeclare()
            except Exception:  # already gone with the session
                pass
        self._subs = []
        self._stop.set()
        self._wake.set()
        self._thread.join(wait_s)
        self.node.close()

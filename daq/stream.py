"""Zenoh: the live stream, events, liveliness and status of a running component.

Keys (docs/reference/zenoh.md): ``armid/<robot>/joint_state`` (:class:`~armid.schema.joint_states.JointStates`
packed, a cycle per put, schema and version in the encoding), ``armid/<robot>/events`` (JSON: faults,
start, stop), ``armid/<robot>/status`` (a queryable answering JSON), and a liveliness
token ``armid/<robot>/alive/<component>``. Sessions are peers. ``session_config`` makes
the explicit-endpoint, no-multicast configuration tests use; a lab passes its own file
(``config/zenoh/lab.json5``).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from typing import Any

from armid.schema.joint_state import ENCODING
from armid.schema.joint_states import JointStates


def session_config(listen: list[str] | None = None, connect: list[str] | None = None, config_file: str | None = None):  # type: ignore[no-untyped-def]
    """A peer-mode ``zenoh.Config``: explicit endpoints, multicast scouting off. A configuration
    file that asks for client mode keeps it: a station of a lab's router (config/zenoh/arm.json5),
    whose every message then passes the router's access control."""
    import zenoh

    config = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    if json.loads(config.get_json("mode")) != "client":
        config.insert_json5("mode", '"peer"')
    config.insert_json5("scouting/multicast/enabled", "false")
    if listen is not None:
        config.insert_json5("listen/endpoints", json.dumps(listen))
    if connect is not None:
        config.insert_json5("connect/endpoints", json.dumps(connect))
    return config


LOCAL_ENDPOINT = "tcp/127.0.0.1:7447"
"""Where armid processes on one machine meet when no endpoint is given (``ARMID_ZENOH_LOCAL``
overrides it): the first to start listens there, every one connects there, and Zenoh's gossip
then links them all to each other, so that any of them may stop first."""


def local_endpoint() -> str:
    import os

    return os.environ.get("ARMID_ZENOH_LOCAL") or LOCAL_ENDPOINT


def open_local_session() -> Any:
    """A peer session that finds every other armid process on this machine with no flags.

    It listens on :data:`LOCAL_ENDPOINT` when that is free (else on a port of the loopback
    the system picks) and connects to it; peers learn each other's endpoints by gossip and
    connect directly. Zenoh retries a connect endpoint that is not there yet, so processes
    may start in any order, and when the one holding the endpoint stops, the next to start
    takes it over and the others reconnect to it. Multicast scouting stays off: on a lab
    network, a configuration file says how peers find each other (multicast scouting or a
    router), as ``config/zenoh/lab.json5`` does."""
    import zenoh

    hub = local_endpoint()
    try:
        return zenoh.open(session_config([hub], [hub]))
    except Exception:  # the endpoint is taken: another armid process holds it
        host = hub.split("/", 1)[1].rsplit(":", 1)[0] if "/" in hub else "127.0.0.1"
        return zenoh.open(session_config([f"tcp/{host}:0"], [hub]))


def key(robot: str, leaf: str) -> str:
    return f"armid/{robot}/{leaf}"


class Stream:
    """Publishes records and events of one component on an open session."""

    def __init__(self, session: Any, robot: str, component: str, status: Callable[[], dict[str, Any]]) -> None:
        import zenoh

        self.session = session
        self.robot = robot
        self._pub = session.declare_publisher(key(robot, "joint_state"), encoding=zenoh.Encoding(ENCODING),
                                              congestion_control=zenoh.CongestionControl.BLOCK)
        # an experiment's start and stop are what a subscriber files its records by: never
        # dropped (a publisher's default drops a message its queue has no room for), and
        # queued ahead of the records
        self._events = session.declare_publisher(key(robot, "events"), encoding=zenoh.Encoding.APPLICATION_JSON,
                                                 congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.INTERACTIVE_HIGH)
        self._token = session.liveliness().declare_token(key(robot, f"alive/{component}"))
        self._status = status
        self.component = component
        self._queryable = session.declare_queryable(key(robot, "status"), self._on_query)
        self.published = 0

    def _on_query(self, query: Any) -> None:
        query.reply(key(self.robot, "status"), json.dumps({"component": self.component, **self._status()}))

    def publish(self, states: JointStates) -> None:
        """Put ``states`` (one cycle, or several in one payload)."""
        self._pub.put(states.pack())
        self.published += len(states)

    def event(self, kind: str, **fields: Any) -> None:
        self._events.put(json.dumps({"time": time.time(), "event": kind, **fields}))

    def close(self) -> None:
        for entity in (self._queryable, self._token, self._events, self._pub):
            try:
                entity.undeclare()
            except Exception:  # already gone with the session
                pass


def drops_line(counts: dict[str, Any]) -> str:
    """What a payload estimator's stream did not use, in words, from the counts its documents
    and status carry (``skipped``, ``lost``, ``invalid``, ``time_faults``, ``dropped``,
    ``last_drop``: :meth:`daq.payload_service.EstimateStream.counts`); empty when nothing."""
    parts = [f"{counts[k]} {k.replace('_', ' ')}" for k in ("skipped", "lost", "invalid", "time_faults") if counts.get(k)]
    dropped = counts.get("dropped") or {}
    if dropped:
        parts.append("dropped " + ", ".join(f"{v} {k}" for k, v in dropped.items()) + f" (last: {counts.get('last_drop')})")
    return "; ".join(parts)

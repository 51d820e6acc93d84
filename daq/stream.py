"""Zenoh: the live stream, events, liveliness and status of a running component.

Keys (INTERFACES.md): ``armid/<robot>/joint_state`` (one :mod:`daq.record_format` record
per cycle, schema and version in the encoding), ``armid/<robot>/events`` (JSON: faults,
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

from armid.schema.joint_state import ENCODING, JointStateRecord


def session_config(listen: list[str] | None = None, connect: list[str] | None = None, config_file: str | None = None):  # type: ignore[no-untyped-def]
    """A peer-mode ``zenoh.Config``: explicit endpoints, multicast scouting off."""
    import zenoh

    config = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("scouting/multicast/enabled", "false")
    if listen is not None:
        config.insert_json5("listen/endpoints", json.dumps(listen))
    if connect is not None:
        config.insert_json5("connect/endpoints", json.dumps(connect))
    return config


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
        self._events = session.declare_publisher(key(robot, "events"), encoding=zenoh.Encoding.APPLICATION_JSON)
        self._token = session.liveliness().declare_token(key(robot, f"alive/{component}"))
        self._status = status
        self._queryable = session.declare_queryable(key(robot, "status"), self._on_query)
        self.published = 0

    def _on_query(self, query: Any) -> None:
        query.reply(key(self.robot, "status"), json.dumps(self._status()))

    def publish(self, record: JointStateRecord) -> None:
        self._pub.put(record.pack())
        self.published += 1

    def event(self, kind: str, **fields: Any) -> None:
        self._events.put(json.dumps({"time": time.time(), "event": kind, **fields}))

    def close(self) -> None:
        for entity in (self._queryable, self._token, self._events, self._pub):
            try:
                entity.undeclare()
            except Exception:  # already gone with the session
                pass

"""``armid watch``: the live stream in a terminal, refreshed a few times a second.

What an operator glances at: per joint the position, velocity, measured and commanded
current, drive state and validity; the record rate, sequence gaps (records lost between
the stream and this viewer), late records; the latest events (faults, start, stop); the
payload estimate when an estimator runs; which components are alive.
"""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from typing import Any

from armid.daq.stream import key
from armid.schema.joint_state import check_encoding
from armid.schema.joint_states import JointStates


class WatchState:
    """What the view shows, updated from Zenoh callbacks (thread-safe enough: one writer each)."""

    def __init__(self) -> None:
        self.last: JointStates | None = None  # the newest record
        self.received = 0
        self.gaps = 0
        self.missing = 0
        self.bad = 0
        self.arrivals: deque[float] = deque(maxlen=2000)
        self.events: deque[str] = deque(maxlen=6)
        self.payload: dict[str, Any] | None = None
        self.alive: set[str] = set()
        self.seen: set[str] = set()  # every component that was alive at some point
        self._last_seq: int | None = None
        self.lock = threading.Lock()

    def on_record(self, data: bytes, encoding: str) -> None:
        try:
            check_encoding(encoding)
            records = JointStates.unpack(data)
        except ValueError as err:
            self.bad += 1
            self.events.append(f"bad record: {err}")
            return
        with self.lock:
            first = int(records.sequence[0])
            if self._last_seq is not None and first != self._last_seq + 1:
                self.gaps += 1
                self.missing += max(0, first - self._last_seq - 1)
            self._last_seq = int(records.sequence[-1])
            self.last = records[len(records) - 1 :]
            self.received += len(records)
            now = time.monotonic()
            self.arrivals.extend([now] * len(records))

    def rate_hz(self) -> float:
        a = list(self.arrivals)
        now = time.monotonic()
        recent = [x for x in a if now - x <= 1.0]
        return float(len(recent))


def render(state: WatchState, robot: str) -> Any:
    from rich.console import Group
    from rich.table import Table
    from rich.text import Text

    rec = state.last
    head = Text(f"armid/{robot}  records {state.received}  rate {state.rate_hz():.0f} Hz  gaps {state.gaps} "
                f"({state.missing} records missing)  bad {state.bad}  alive: {', '.join(sorted(state.alive)) or 'nothing'}")
    table = Table(expand=False)
    for col in ("joint", "valid", "position rad", "velocity rad/s", "current A", "commanded A", "statusword"):
        table.add_column(col, justify="right")
    if rec is not None:
        for j in range(rec.n_joints):
            table.add_row(str(j + 1), "yes" if rec.valid[0, j] else "[red]NO[/]", f"{rec.position[0, j]:+.4f}", f"{rec.velocity[0, j]:+.3f}",
                          f"{rec.measured_current[0, j]:+.3f}", f"{rec.commanded_current[0, j]:+.3f}", f"0x{int(rec.status[0, j]):04X}")
        head.append(f"\ncycle {int(rec.cycle[0])}  sequence {int(rec.sequence[0])}  t {float(rec.time[0]):.3f}")
    parts: list[Any] = [head, table]
    if state.payload:
        p = state.payload
        com = p.get("com") or [float("nan")] * 3
        mass = "not excited" if p.get("mass") is None else f"{p['mass']:.3f} +- {p['mass_std']:.3f} kg"  # null: not determined yet
        parts.append(Text(f"payload: {mass}, centre of mass "
                          f"[{', '.join('-' if c is None else f'{100 * c:.1f}' for c in com)}] cm, {p.get('status') or ('converged' if p.get('converged') else 'settling')}"))
    if state.events:
        parts.append(Text("events:\n" + "\n".join(state.events)))
    return Group(*parts)


def watch(session: Any, robot: str, duration_s: float | None = None, refresh_hz: float = 4.0, console: Any = None,
          stop: Any = None) -> WatchState:
    """Subscribe and render until ``duration_s`` passes, ``stop`` (a ``threading.Event``) is set, or Ctrl-C."""
    from rich.live import Live

    state = WatchState()
    subs = [
        session.declare_subscriber(key(robot, "joint_state"), lambda s: state.on_record(s.payload.to_bytes(), str(s.encoding))),
        session.declare_subscriber(key(robot, "events"), lambda s: state.events.append(_event_line(s.payload.to_bytes()))),
        session.declare_subscriber(key(robot, "estimate/payload"), lambda s: setattr(state, "payload", json.loads(s.payload.to_bytes()))),
    ]
    token_sub = session.liveliness().declare_subscriber(key(robot, "alive/**"), history=True,
                                                        handler=lambda s: _alive(state, str(s.key_expr), str(s.kind)))
    deadline = None if duration_s is None else time.monotonic() + duration_s
    try:
        with Live(render(state, robot), console=console, refresh_per_second=refresh_hz, transient=False) as live:
            while (deadline is None or time.monotonic() < deadline) and not (stop is not None and stop.is_set()):
                time.sleep(1.0 / refresh_hz)
                live.update(render(state, robot))
    except KeyboardInterrupt:
        pass
    finally:
        for s in subs:
            s.undeclare()
        token_sub.undeclare()
    return state


def _alive(state: WatchState, key_expr: str, kind: str) -> None:
    name = key_expr.rsplit("/", 1)[-1]
    if "DELETE" in kind.upper():
        state.alive.discard(name)
    else:
        state.alive.add(name)
        state.seen.add(name)


def _event_line(data: bytes) -> str:
    try:
        doc = json.loads(data)
    except ValueError:
        return f"(unreadable event: {data[:40]!r})"
    when = time.strftime("%H:%M:%S", time.localtime(doc.pop("time", time.time())))
    kind = doc.pop("event", "?")
    return f"{when} {kind} " + " ".join(f"{k}={v}" for k, v in doc.items())




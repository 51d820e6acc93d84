"""``armid watch``: the live stream in a terminal, refreshed a few times a second.

What an operator glances at: per joint the position, velocity, measured and commanded
current, drive state and validity; the record rate, sequence gaps (records lost between
the stream and this viewer); the arm's parameters as the estimator service publishes them
(``estimate/parameters``: each base parameter's value +- std, and which experiment gave
them), every parameter set published since the view started, the payload with its band and
whether it has converged (``estimate/payload``), what the service found (a run refused, not
identified) and the drives' faults, in words; which components are alive. The events'
documents themselves (trajectory coefficients, drive settings) only with ``raw``.
"""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from typing import Any

from armid.daq.stream import drops_line, key
from armid.schema.joint_state import check_encoding
from armid.schema.joint_states import JointStates


class WatchState:
    """What the view shows, updated from Zenoh callbacks (thread-safe enough: one writer each).
    ``raw``: the events' documents as they came, instead of their lines in words."""

    def __init__(self, raw: bool = False) -> None:
        self.raw = raw
        self.last: JointStates | None = None  # the newest record
        self.received = 0
        self.gaps = 0
        self.missing = 0
        self.bad = 0
        self.arrivals: deque[float] = deque(maxlen=2000)
        self.events: deque[str] = deque(maxlen=6)
        self.findings: deque[str] = deque(maxlen=4)  # what the service found of a run, the drives' faults
        self.payload: dict[str, Any] | None = None
        self.payloads = 0
        self.parameters: dict[str, Any] | None = None  # the newest estimate/parameters document
        self.parameter_sets: deque[str] = deque(maxlen=8)  # one line per document published
        self.published = 0
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

    def on_event(self, data: bytes) -> None:
        """An event's line (in words, or as it came with ``raw``); a fault is a finding too."""
        doc = _json_object(data)
        if doc is None:
            self.events.append(f"(unreadable event: {data[:40]!r})")
            return
        line = raw_event_line(doc) if self.raw else event_line(doc)
        self.events.append(line)
        if doc.get("event") == "fault" and not self.raw:
            self.findings.append(line)

    def on_parameters(self, data: bytes) -> None:
        """A parameter set the service published: kept, and a line of it in the list of sets."""
        doc = _json_object(data)
        if doc is None:
            self.events.append(f"(unreadable estimate/parameters: {data[:40]!r})")
            return
        self.published += 1
        self.parameter_sets.append(f"#{self.published} {_clock(doc.get('time'))} {parameter_set_line(doc)}")
        note = (doc.get("experiment") or {}).get("note")
        if note:
            self.findings.append(f"{_clock(doc.get('time'))} run {_run(doc)}: {note}")
        if doc.get("base_parameters") or self.parameters is None:
            self.parameters = doc

    def on_payload(self, data: bytes) -> None:
        doc = _json_object(data)
        if doc is None:
            self.events.append(f"(unreadable estimate/payload: {data[:40]!r})")
            return
        self.payload = doc
        self.payloads += 1

    def rate_hz(self) -> float:
        a = list(self.arrivals)
        now = time.monotonic()
        recent = [x for x in a if now - x <= 1.0]
        return float(len(recent))


def _json_object(data: bytes) -> dict[str, Any] | None:
    try:
        doc = json.loads(data)
    except (ValueError, RecursionError):
        return None
    return doc if isinstance(doc, dict) else None


def _clock(stamp: Any) -> str:
    return time.strftime("%H:%M:%S", time.localtime(stamp if isinstance(stamp, int | float) else time.time()))


def _run(doc: dict[str, Any]) -> str:
    return repr((doc.get("experiment") or {}).get("run") or "?")


def _number(x: Any) -> str:
    return "-" if not isinstance(x, int | float) or isinstance(x, bool) else f"{x:.4g}"


def raw_event_line(doc: dict[str, Any]) -> str:
    """An event's document as it came (``--raw``): its time, its kind, every field."""
    doc = dict(doc)
    when = _clock(doc.pop("time", None))
    kind = doc.pop("event", "?")
    return f"{when} {kind} " + " ".join(f"{k}={v}" for k, v in doc.items())


def event_line(doc: dict[str, Any]) -> str:
    """An event in words: an experiment's start or stop, a drive's fault or event; another kind
    by its name and its plain fields (never a list or a mapping: a trajectory's coefficients)."""
    when, kind = _clock(doc.get("time")), doc.get("event")
    run = doc.get("run") or "?"
    exp: dict[str, Any] = doc["experiment"] if isinstance(doc.get("experiment"), dict) else {}
    if kind == "start":
        what = exp.get("kind") or "recording"
        link = f" of link {exp['link']}" if exp.get("link") is not None else ""
        lasting = f", {doc['duration_s']:.1f} s" if isinstance(doc.get("duration_s"), int | float) else ""
        return f"{when} started run {run!r}: {what.replace('_', '-')}{link}{lasting}"
    if kind == "stop":
        records = f", {doc['records']} records" if isinstance(doc.get("records"), int) else ""
        if doc.get("completed", True):
            return f"{when} run {run!r} completed{records}"
        return f"{when} run {run!r} STOPPED: {doc.get('reason') or 'no reason given'}{records}"
    if kind == "fault":
        node = f" (node {doc['node']})" if doc.get("node") is not None else ""
        code = f" [{doc['code']:#06x}]" if isinstance(doc.get("code"), int) and doc["code"] else ""
        return f"{when} FAULT joint {doc.get('joint', '?')}{node}: {doc.get('meaning') or doc.get('type') or 'drive fault'}{code}"
    if kind == "drive_event":
        joint = f"joint {doc['joint']}: " if doc.get("joint") is not None else ""
        return f"{when} drive: {joint}{doc.get('message') or doc.get('type') or '?'}"
    plain = [f"{k}={v}" for k, v in doc.items() if k not in ("time", "event") and not isinstance(v, dict | list)]
    return f"{when} {kind or '?'} " + " ".join(plain)


def parameter_set_line(doc: dict[str, Any]) -> str:
    """One published parameter set in a line: which experiment, what it gave."""
    exp = doc.get("experiment") or {}
    head = f"run {_run(doc)} ({str(exp.get('kind') or '?').replace('_', '-')}, {exp.get('records', '?')} records)"
    base = doc.get("base_parameters") or []
    if exp.get("note"):
        return f"{head}: {exp['note']}" + (f"; the parameters stay those of {doc['source']}" if doc.get("source") else "")
    return f"{head}: {len(base)} base parameters from {_source(doc)}"


def _source(doc: dict[str, Any]) -> str:
    """Which experiment(s) gave the document's parameters."""
    source = doc.get("source")
    if source == "single_link":
        steps = (doc.get("single_link") or {}).get("steps") or []
        runs = [f"link {s.get('link')} {s.get('run')!r}" for s in steps if isinstance(s, dict)]
        return "the single-link runs " + ", ".join(runs) if runs else "the single-link runs"
    if isinstance(source, str) and source.startswith("whole_arm "):
        return f"whole-arm run {source.split(' ', 1)[1]!r}"
    return "nothing yet"


def _fit_line(doc: dict[str, Any]) -> str:
    """The fit and validation errors of the newest whole-arm fit, where there is one."""
    source = doc.get("source") or ""
    fit = ((doc.get("whole_arm") or {}).get(source.split(" ", 1)[-1]) or {}) if source.startswith("whole_arm ") else {}
    parts = []
    for name, value in (("fit", fit.get("fit")), ("validation", doc.get("validation"))):
        error = value.get("relative_error") if isinstance(value, dict) else None
        if isinstance(error, int | float):
            parts.append(f"{name} error {100 * error:.2f} %")
    return ("; " + ", ".join(parts)) if parts else ""


def payload_line(p: dict[str, Any]) -> str:
    """The payload estimate with its band (1 sigma, the data's and the torque constants' parts)
    and whether it has converged."""
    status = p.get("status") or ("converged" if p.get("converged") else "converging")
    if p.get("mass") is None:
        return f"payload: mass not determined yet (the motion does not excite it), {status}"
    band = f"{p['mass']:.3f} +- {_number(p.get('mass_std'))} kg"
    parts = [f"data {_number(p.get('mass_std_data'))}", f"torque constants {_number(p.get('mass_std_torque_constants'))}"]
    com, com_std = p.get("com"), p.get("com_std")
    where = ""
    if isinstance(com, list):
        cm = ", ".join("-" if c is None else f"{100 * c:.1f}" for c in com)
        spread = (" +- [" + ", ".join("-" if s is None else f"{100 * s:.1f}" for s in com_std) + "]") if isinstance(com_std, list) else ""
        where = f", centre of mass [{cm}]{spread} cm"
    verdict = "CONVERGED" if p.get("converged") else status
    return f"payload: {band} (1 sigma: {', '.join(parts)}){where}: {verdict}"


def render(state: WatchState, robot: str) -> Any:
    from rich.columns import Columns
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
    doc = state.parameters
    if doc is not None and doc.get("base_parameters"):
        parts.append(Text(f"parameters from {_source(doc)} (set {state.published}){_fit_line(doc)}:", style="bold"))
        cells = [Text(f"{b.get('expression', '?')} = {_number(b.get('value'))} +- {_number(b.get('std'))}"
                      + (f" (link {b['link']})" if b.get("link") is not None else ""))  # a single-link table's row: its link's run
                 for b in doc["base_parameters"] if isinstance(b, dict)]
        parts.append(Columns(cells, padding=(0, 3)))
    else:
        parts.append(Text("parameters: none published yet (armid serve publishes them after each experiment)"))
    if state.parameter_sets:
        parts.append(Text("parameter sets published:\n" + "\n".join(state.parameter_sets)))
    if state.payload:
        parts.append(Text(payload_line(state.payload)))
        unused = drops_line(state.payload)
        if unused:
            parts.append(Text(f"the payload estimator did not use: {unused}"))
    if state.findings:
        parts.append(Text("findings:\n" + "\n".join(state.findings), style="yellow"))
    if state.events:
        parts.append(Text("events:\n" + "\n".join(state.events)))
    return Group(*parts)


def watch(session: Any, robot: str, duration_s: float | None = None, refresh_hz: float = 4.0, console: Any = None,
          stop: Any = None, raw: bool = False) -> WatchState:
    """Subscribe and render until ``duration_s`` passes, ``stop`` (a ``threading.Event``) is set, or Ctrl-C."""
    from rich.live import Live

    state = WatchState(raw)
    subs = [
        session.declare_subscriber(key(robot, "joint_state"), lambda s: state.on_record(s.payload.to_bytes(), str(s.encoding))),
        session.declare_subscriber(key(robot, "events"), lambda s: state.on_event(s.payload.to_bytes())),
        session.declare_subscriber(key(robot, "estimate/payload"), lambda s: state.on_payload(s.payload.to_bytes())),
        session.declare_subscriber(key(robot, "estimate/parameters"), lambda s: state.on_parameters(s.payload.to_bytes())),
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

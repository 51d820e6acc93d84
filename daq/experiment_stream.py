"""Experiments on the stream: what ``armid excite`` says about each run, and how a subscriber
cuts the run's records back out of ``armid/<robot>/joint_state``.

``armid excite`` (and ``armid record``) publish on ``armid/<robot>/events`` a ``start`` event
before each experiment and a ``stop`` event after it. Both carry ``experiment`` (see
:func:`experiment_description`: the kind, which joints move and which hold, the trajectory,
the plan's timing and the run's metadata); the ``stop`` event adds what the recording holds:
``first_sequence`` .. ``last_sequence`` (the gap-free record numbers of the stream),
``first_cycle`` and ``window_s`` (where the excitation lies in the plan's time), ``completed``
and the stop reason.

:class:`ExperimentCollector` is the subscriber's side, with no I/O: records and events
in (any interleaving: records and events travel on different keys, so a ``stop`` may arrive
before the run's last records), completed experiments out, each with exactly the records of
the recording that it received, and what it did not receive.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from typing import Any

from armid.schema.joint_states import JointStates

IDLE_KEEP = 2000
"""Records kept while no experiment is open (4 s at 2 ms): a ``start`` event may arrive after
the run's first records."""
MOST_KEPT = 400_000
"""At most this many records are held (about 100 MB at six joints): 13 minutes at 2 ms."""


def experiment_description(name: str, plan: Any, n_joints: int, metadata: dict[str, Any]) -> dict[str, Any]:
    """What an experiment is, for the ``start`` and ``stop`` events: ``kind`` (``single_link``,
    ``whole_arm``, ``partial`` or ``recording``), ``link`` (1-based, single-link only),
    ``moving`` and ``held`` joints (1-based), the trajectory, the plan's timing and the metadata."""
    meta = dict(metadata)
    excitation = dict(meta.pop("excitation", None) or {}) if isinstance(meta.get("excitation"), dict) else {}
    design = excitation.pop("design", None) or {}
    moving = design.get("moving_joints")
    link = None
    if moving is None:
        kind, moving = "recording", None
    elif len(moving) == 1:
        kind, link = "single_link", moving[0]
    elif len(moving) == n_joints:
        kind = "whole_arm"
    else:
        kind = "partial"
    doc: dict[str, Any] = {
        "name": name, "kind": kind, "link": link,
        "moving": moving, "held": None if moving is None else [j for j in range(1, n_joints + 1) if j not in moving],
        "trajectory": design.get("fourier"), "design": {k: v for k, v in design.items() if k != "fourier"} or None,
        "metadata": meta,
    }
    if plan is not None:
        doc["plan"] = {"lead_in_s": plan.lead_in_s, "periods": plan.periods, "settle_s": plan.settle_s,
                       "window_s": list(plan.excitation_window), "duration_s": plan.duration_s}
        if moving is not None:
            import numpy as np

            doc["pose_at_start"] = [float(x) for x in plan.trajectory.evaluate(np.zeros(1))[0][0]]
    return doc


@dataclass
class CollectedExperiment:
    """One experiment as a subscriber received it: ``records`` (in sequence order) of the
    recording's ``first_sequence`` .. ``last_sequence``; ``missing`` of them never arrived or
    were skipped; ``kept`` gives the sequence ranges received, ``[[first, last], ...]``."""

    name: str
    start: dict[str, Any] | None
    stop: dict[str, Any]
    records: JointStates
    missing: int
    kept: list[list[int]]
    timed_out: bool = False

    @property
    def sequences(self) -> list[int]:
        return [int(k) for k in self.records.sequence]

    @property
    def description(self) -> dict[str, Any]:
        return (self.stop.get("experiment") or (self.start or {}).get("experiment") or {})


@dataclass
class ExperimentCollector:
    """Records and events in, :class:`CollectedExperiment` out (see the module docstring).

    ``stop_wait_s``: how long after a ``stop`` event the run's last records may still arrive;
    past it the experiment is completed with what was received."""

    stop_wait_s: float = 5.0
    buffer: dict[int, JointStates] = field(default_factory=dict)
    started: dict[str, dict[str, Any]] = field(default_factory=dict)
    stopping: list[tuple[dict[str, Any], float]] = field(default_factory=list)
    newest: int = -1
    dropped_idle: int = 0

    def record(self, states: JointStates) -> None:
        """File ``states`` (one record or several) by their sequence numbers."""
        for k, sequence in enumerate(states.sequence.tolist()):
            self.buffer[sequence] = states[k : k + 1]
        self.newest = max(self.newest, int(states.sequence.max(initial=-1)))
        limit = MOST_KEPT if (self.started or self.stopping) else IDLE_KEEP
        if len(self.buffer) > limit:
            for seq in sorted(self.buffer)[: len(self.buffer) - limit]:
                del self.buffer[seq]
                self.dropped_idle += 1

    def event(self, doc: dict[str, Any], now: float | None = None) -> None:
        run = doc.get("run")
        if not isinstance(run, str):
            return
        if doc.get("event") == "start":
            self.started[run] = doc
        elif doc.get("event") == "stop" and isinstance(doc.get("last_sequence"), int) and isinstance(doc.get("first_sequence"), int):
            self.stopping.append((doc, time.monotonic() if now is None else now))

    def completed(self, now: float | None = None) -> list[CollectedExperiment]:
        """Experiments whose records are all in (or whose wait ran out), oldest first."""
        now = time.monotonic() if now is None else now
        out = []
        for doc, when in list(self.stopping):
            first, last = int(doc["first_sequence"]), int(doc["last_sequence"])
            timed_out = self.newest < last and now - when > self.stop_wait_s
            if self.newest < last and not timed_out:
                continue
            self.stopping.remove((doc, when))
            seqs = sorted(s for s in self.buffer if first <= s <= last)
            kept: list[list[int]] = []
            for s in seqs:
                if kept and s == kept[-1][1] + 1:
                    kept[-1][1] = s
                else:
                    kept.append([s, s])
            records = JointStates.concat([self.buffer[s] for s in seqs]) if seqs else JointStates.empty(0)
            out.append(CollectedExperiment(doc["run"], self.started.pop(doc["run"], None), doc, records,
                                           (last - first + 1) - len(seqs), kept, timed_out))
            if not self.stopping:
                for s in [s for s in self.buffer if s <= last]:
                    del self.buffer[s]
        return out


def event_of(data: bytes) -> dict[str, Any] | None:
    try:
        doc = json.loads(data)
    except (ValueError, RecursionError):
        return None
    return doc if isinstance(doc, dict) else None

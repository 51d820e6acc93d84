"""What the drives said while a run went on, said to the operator.

A driver raises each drive fault once (:class:`~armid.drivers.interface.DriveFault`: an
EMCY, a lost heartbeat, a drive stopped or reset by NMT) and keeps what did not stop the arm
as events (a frame of the wrong length, error frames, a node the rig does not have). Before
this, ``armid record`` kept both to itself: 2,000 over-current EMCYs, a drive stopped by NMT
and frames of the wrong length all ended in exit 0 with nothing said. :class:`Supervision`
says each kind once per drive as it happens (repeats counted, not repeated: a storm of
frames must not flood the terminal), sends each to the run's Zenoh events typed, sums up at
the end, and says whether the run lost a drive.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from armid.drivers.interface import DriveFault, Event, HeartbeatLost
from armid.schema.errors import NotOperational

# the driver makes an event of every fault as well: said once, from the fault
_FAULT_EVENTS = {"emcy", "heartbeat_lost", "nmt"}


@dataclass
class _Seen:
    first: str
    count: int = 1


class Supervision:
    """Faults and events of one run: ``say`` prints a line, ``stream`` (optional) has
    ``event(kind, **fields)``; :attr:`lost` holds the 0-based joints that were lost."""

    def __init__(self, say: Callable[[str], None], stream: Any = None) -> None:
        self.say, self.stream = say, stream
        self._seen: dict[tuple[str, int | None, int], _Seen] = {}
        self.lost: set[int] = set()
        self.faulted: set[int] = set()

    def fault(self, fault: DriveFault) -> None:
        kind = "lost" if isinstance(fault, HeartbeatLost | NotOperational) else "fault"
        (self.lost if kind == "lost" else self.faulted).add(fault.joint)
        if self.stream is not None:
            self.stream.event("fault", joint=fault.joint + 1, node=fault.node_id, code=fault.code, meaning=fault.meaning,
                              type=type(fault).__name__)
        self._note(kind, fault.joint, fault.code, str(fault))

    def events(self, events: list[Event]) -> None:
        for e in events:
            if e.kind in _FAULT_EVENTS:
                continue
            if self.stream is not None:
                self.stream.event("drive_event", type=e.kind, joint=None if e.joint is None else e.joint + 1, message=e.message)
            self._note(e.kind, e.joint, 0, e.message)

    def _note(self, kind: str, joint: int | None, code: int, text: str) -> None:
        key = (kind, joint, code)
        seen = self._seen.get(key)
        if seen is not None:
            seen.count += 1
            return
        self._seen[key] = _Seen(text)
        self.say(text)

    def summary(self) -> list[str]:
        """One line per kind and drive that came more than once: how often."""
        return [f"{s.first} ({s.count:,} times)" for s in self._seen.values() if s.count > 1]

    @property
    def failed(self) -> bool:
        """A drive was lost or faulted: the run's records of it are not what was asked for."""
        return bool(self.lost or self.faulted)

    def verdict(self) -> str:
        joints = ", ".join(str(j + 1) for j in sorted(self.lost | self.faulted))
        what = "lost" if self.lost and not self.faulted else "faulted" if not self.lost else "lost or faulted"
        return f"the run {what} joint{'s' if len(self.lost | self.faulted) > 1 else ''} {joints}: their records after that are marked invalid"

"""The live line of ``armid record`` and ``armid excite``: records, rate, lost cycles, faults.

Refreshed four times a second with rich, on standard output, and only when standard output
is a terminal: a log, a pipe or a test sees nothing of it.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np


class RateLine:
    """``records N  rate R Hz  lost cycles L  invalid I  faults F`` from counters read now."""

    def __init__(self) -> None:
        self._last: tuple[float, int] | None = None
        self.rate_hz = 0.0

    def __call__(self, records: int, lost_cycles: int, invalid: int, faults: int, dropped: int = 0) -> str:
        now = time.monotonic()
        if self._last is not None and now - self._last[0] >= 0.2:
            self.rate_hz = (records - self._last[1]) / (now - self._last[0])
            self._last = (now, records)
        elif self._last is None:
            self._last = (now, records)
        text = (f"records {records:,}  rate {self.rate_hz:6.1f} Hz  lost cycles {lost_cycles}  invalid {invalid}  "
                f"faults {faults}")
        return text + (f"  dropped by the stream {dropped}" if dropped else "")


def acquisition_counts(acq: Any, driver: Any) -> tuple[int, int, int]:
    """(records, lost cycles summed over the joints, invalid joint-cycles) of a running acquisition."""
    lost = getattr(driver, "lost_cycles", None)
    return int(acq.sequence), int(np.sum(lost)) if lost is not None else 0, int(np.sum(acq.invalid))


def acquisition_line(acq: Any, driver: Any, faults: int, period_s: float, _line: RateLine | None = None) -> str:
    line = _LINES.setdefault(id(acq), _line or RateLine())
    records, lost, invalid = acquisition_counts(acq, driver)
    dropped = sum(s.dropped for s in getattr(acq, "sinks", []))
    return line(records, lost, invalid, faults, dropped)


_LINES: dict[int, RateLine] = {}


def enabled() -> bool:
    try:
        return sys.stdout.isatty()
    except (AttributeError, ValueError):
        return False


class LiveLine:
    """A rich live line on standard output while in a ``with`` block (nothing when it is not a terminal)."""

    def __init__(self, text: Callable[[], str], refresh_hz: float = 4.0) -> None:
        self.text = text
        self.refresh_hz = refresh_hz
        self._live: Any = None
        self._thread: Any = None
        self._stop: Any = None

    def __enter__(self) -> LiveLine:
        if not enabled():
            return self
        import threading

        from rich.console import Console
        from rich.live import Live
        from rich.text import Text

        self._live = Live(Text(self.text()), console=Console(), refresh_per_second=self.refresh_hz, transient=False)
        self._live.__enter__()
        self._stop = threading.Event()

        def run() -> None:
            while not self._stop.wait(1.0 / self.refresh_hz):
                try:
                    self._live.update(Text(self.text()))
                except Exception:  # the line must never stop what it shows
                    pass

        self._thread = threading.Thread(target=run, name="armid-live-line", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._live is None:
            return
        from rich.text import Text

        self._stop.set()
        self._thread.join(2.0)
        try:
            self._live.update(Text(self.text()))
        finally:
            self._live.__exit__(None, None, None)

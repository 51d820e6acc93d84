"""Processes that each keep a core busy beside a measurement (a lab PC's load: ROS, a browser,
an IDE), started before it and killed by id after it."""

from __future__ import annotations

import contextlib
import subprocess
import sys
from collections.abc import Iterator


@contextlib.contextmanager
def busy_loops(n: int) -> Iterator[None]:
    loads = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield
    finally:
        for p in loads:
            p.kill()
            p.wait()

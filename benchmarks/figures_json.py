"""Where a benchmark's figures go: ``benchmarks/results/<name>.json``, holding what the benchmark
printed, the command that produced it, the machine it ran on (CPU model, cores, load average
before and after, Python and numpy versions) and the date. ``scripts/gen_figures.py`` renders
``docs/figures.md`` from these files, so a figure on that page is always one a benchmark wrote.

A benchmark wraps its run::

    with recorded("identify"):
        main()

Everything the run prints to stdout is shown as usual and kept line by line; the file is
written only when the run finishes without an exception (a failed run leaves the previous
figures in place). ``ARMID_RESULTS_DIR`` puts the files elsewhere (a trial run).
"""

from __future__ import annotations

import contextlib
import datetime
import io
import json
import os
import platform
import shlex
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).resolve().parent / "results"


def cpu_model() -> str:
    """The CPU's model name as the kernel reports it (``/proc/cpuinfo``), else the platform's."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def load_average() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def command_line() -> str:
    """The command as typed from the repository's root: ``python benchmarks/NAME.py ARGS``."""
    script = Path(sys.argv[0]).resolve()
    shown = script.relative_to(ROOT) if script.is_relative_to(ROOT) else script
    return shlex.join(["python", str(shown), *sys.argv[1:]])


class _Tee(io.TextIOBase):
    """stdout that still prints, and keeps what was printed."""

    def __init__(self, through: io.TextIOBase) -> None:
        self.through = through
        self.kept = io.StringIO()

    def write(self, text: str) -> int:
        self.kept.write(text)
        return self.through.write(text)

    def flush(self) -> None:
        self.through.flush()


@contextlib.contextmanager
def recorded(name: str) -> Iterator[None]:
    """Run the block with stdout kept, then write ``results/<name>.json`` (module docstring)."""
    started = time.monotonic()
    load_before = load_average()
    date = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    tee = _Tee(sys.stdout)  # type: ignore[arg-type]
    with contextlib.redirect_stdout(tee):  # type: ignore[type-var]
        yield
    output = [line.rstrip() for line in tee.kept.getvalue().splitlines() if line.strip()]
    doc = {
        "name": name,
        "command": command_line(),
        "date": date,
        "seconds": round(time.monotonic() - started, 1),
        "machine": {
            "cpu": cpu_model(),
            "cores": os.cpu_count(),
            "load_average_before": load_before,
            "load_average_after": load_average(),
            "system": f"{platform.system()} {platform.release()}",
            "python": platform.python_version(),
            "numpy": np.__version__,
        },
        "output": output,
    }
    where = Path(os.environ.get("ARMID_RESULTS_DIR") or RESULTS)
    where.mkdir(parents=True, exist_ok=True)
    path = where / f"{name}.json"
    path.write_text(json.dumps(doc, indent=1, ensure_ascii=False) + "\n")
    print(f"figures written to {path}", file=sys.stderr)

"""armid's command line run in the test's own process, for the tests that read what it says:
one way to run a command and one way to record while something is done to the bus."""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from armid.cli import main

ROOT = Path(__file__).resolve().parent.parent
SIM_RIG = ROOT / "config" / "rigs" / "sim.yaml"


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """``armid ARGV`` in this process: (exit code, stderr)."""
    try:
        code = main(argv)
    except SystemExit as stop:  # argparse's own exit
        code = int(stop.code or 0)
    return code, capsys.readouterr().err


def record_with(inject: Callable[[Any], None], tmp_path: Path, capsys: pytest.CaptureFixture[str],
                duration_s: float = 3.0) -> tuple[int, str, dict[str, Any]]:
    """``armid record`` of the simulated arm for ``duration_s`` of its time on a virtual bus of
    its own; ``inject`` runs once the recording has started, on a bus handle of its own.
    Returns (exit code, stderr, the recording's arrays)."""
    import can

    from armid.io.recordings import read_mcap_arrays

    channel, out, box = f"armid-rec-{uuid.uuid4().hex[:8]}", tmp_path / "run", {}
    thread = threading.Thread(target=lambda: box.setdefault("code", main(
        ["record", "--rig", str(SIM_RIG), "--channel", channel, "--out", str(out), "--duration", str(duration_s), "--no-zenoh"])))
    thread.start()
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        for _ in range(400):  # the recorder writes its file once the drives are up
            if (out / "run.mcap").exists() and (out / "run.mcap").stat().st_size > 0:
                break
            time.sleep(0.05)
        time.sleep(0.3)
        inject(bus)
    finally:
        thread.join(300)
        bus.shutdown()
    assert not thread.is_alive(), "armid record did not end"
    arrays, _, _ = read_mcap_arrays(out / "run.mcap")
    return box["code"], capsys.readouterr().err, arrays

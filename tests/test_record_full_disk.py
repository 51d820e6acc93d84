"""``armid record`` onto a disk that fills: the run stops with one line naming the file and the
cause and a non-zero exit, and every record handed to the disk before it reads back.

The disk is a real one that fills: a 1 MiB tmpfs mounted for the test. (The tests run as root,
for whom a folder made read-only with chmod still takes writes, so chmod cannot make a write
fail; a tmpfs of a fixed size fails it with ENOSPC for root too. A file-size limit, RLIMIT_FSIZE,
would also do, but it is the process's, not the disk's.) Skipped where mounting is not allowed.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import uuid
from pathlib import Path

import numpy as np
import pytest

from armid.io.recordings import read_mcap_arrays, read_recording
from armid.io.robot_file import load_robot

ROOT = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


@pytest.fixture
def small_disk(tmp_path: Path):  # type: ignore[no-untyped-def]
    disk = tmp_path / "disk"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(disk)], capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.strip()}")
    try:
        yield disk
    finally:
        subprocess.run(["umount", str(disk)], check=False)


@pytest.mark.realtime  # a simulated arm on a bus
def test_record_onto_a_disk_that_fills_stops_naming_the_file_and_keeps_what_was_written(small_disk: Path, tmp_path: Path) -> None:
    out = small_disk / "run"
    cmd = [sys.executable, "-m", "armid.cli", "record", "--rig", str(ROOT / "config/rigs/sim.yaml"), "--channel",
           f"armid-full-{uuid.uuid4().hex[:6]}", "--out", str(out), "--duration", "600", "--no-zenoh"]
    done = subprocess.run(cmd, cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=600)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1, done.stderr[-2000:]
    assert "Traceback" not in done.stderr, done.stderr[-2000:]
    last = lines[-1]
    assert re.match(r"armid record: error: .*(run\.mcap|can\.log): cannot write \(No space left on device\); the run stopped after \d+ records",
                    last), last
    # every record the recording took before the disk filled reads back, in order, none missing between
    copy = tmp_path / "run.mcap"  # read outside the full disk: the reader needs no room, but the check should not depend on it
    copy.write_bytes((out / "run.mcap").read_bytes())
    arrays, _, notes = read_mcap_arrays(copy)
    seq = arrays["sequence"]
    assert seq.size >= 250, (seq.size, notes)  # half a second at 2 ms at least reached the disk before it filled
    assert seq[0] == 0 and np.all(np.diff(seq) == 1), notes
    rec = read_recording(copy, load_robot(ROOT / "config" / "robots" / "puma560.yaml"))
    assert rec.t.size == seq.size and np.isfinite(rec.tau).all()

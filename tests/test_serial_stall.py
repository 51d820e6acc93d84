"""Issue 66: the serial chain waits through a stall of the machine, as the CAN arm does.

``armid excite --whole`` on the simulated Dynamixel rig, its process and the chain's stopped
together for 20 ms (a host that deschedules both, SIGSTOP), the excitation's process let go first: its
reads find the chain still silent. A read waits for a simulated chain that has not yet served
it (drivers.line_progress), and cycles lost beyond that are waited through, up to the rig's
``bus.silent_cycles``; either is said; a chain silent while the driver's process ran on
time still stops the arm at three cycles (tests/test_excitation_dynamixel.py)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from armid.resources import config_file

pytestmark = [pytest.mark.realtime, pytest.mark.slow, pytest.mark.alone]  # a stall it makes itself, on cores of its own


def _chain_of(parent: int) -> int:
    """The pid of ``parent``'s child running ``armid.chain_process``."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ")
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == parent and b"armid.chain_process" in cmdline:
            return int(entry.name)
    raise AssertionError(f"no chain process under {parent}")


def test_a_stall_of_the_machine_is_waited_through_and_said(tmp_path: Path) -> None:
    rig = config_file("rigs/sim_dynamixel.yaml")
    excite = subprocess.Popen([sys.executable, "-c", "from armid.cli import run; run()", "excite", "--rig", str(rig), "--whole",
                               "--out", str(tmp_path / "runs")], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        recording = tmp_path / "runs" / "whole" / "run.mcap"
        deadline = time.monotonic() + 120.0
        while not recording.exists() and excite.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert recording.exists(), "the whole-arm run did not start"
        time.sleep(3.0)  # the arm moving, the drives enabled
        chain = _chain_of(excite.pid)
        os.kill(chain, signal.SIGSTOP)
        os.kill(excite.pid, signal.SIGSTOP)
        time.sleep(0.02)
        os.kill(excite.pid, signal.SIGCONT)  # the excitation runs again; the chain only 60 ms later: its reads
        time.sleep(0.06)  # wait for the chain that has not served them (drivers.line_progress), or a gap is waited through
        os.kill(chain, signal.SIGCONT)
        out, _ = excite.communicate(timeout=120)
    finally:
        if excite.poll() is None:
            excite.kill()
            excite.wait()
    assert excite.returncode == 0, out
    said = " ".join(out.split())  # the console folds its lines
    assert "whole: completed" in said, out
    assert "in the frames while this process was not scheduled" in said or "given again: the simulated chain" in said, out


def _cycles(driver: object, n: int) -> None:
    for _ in range(n):
        driver.read(1.0)  # type: ignore[attr-defined]


@pytest.mark.parametrize("witness", [True, False])
def test_a_stall_of_the_chain_alone_is_waited_through_and_a_silent_servo_still_counts(witness: bool) -> None:
    """The cause of the replies `armid record` dropped beside one busy loop: the host stops one CPU
    of this machine for up to 8 ms (a real-time process pinned to it sees the gap, as /proc/stat's
    steal grows), and a chain (or the pty's kernel worker) on that CPU answers after the master's
    8 ms window, while the master on the other CPU ran on time. Stopped alone for 15 ms (SIGSTOP),
    the chain is waited through where it says how far it has got (drivers.line_progress), and a
    cycle is lost where it does not (the control: this test can fail); a servo that does not
    answer, the chain running, still counts at once."""
    from armid.io.rig_file import load_rig
    from armid.simulated import simulated_driver

    rig = load_rig(config_file("rigs/sim_dynamixel.yaml"))
    driver, sim = simulated_driver(rig, **({} if witness else {"progress": None}))
    try:
        driver.start()
        _cycles(driver, 250)
        lost_before = driver.lost_cycles.copy()  # type: ignore[attr-defined]
        os.kill(sim.peer.pid, signal.SIGSTOP)
        time.sleep(0.015)  # longer than a reply window (8 ms), shorter than four
        os.kill(sim.peer.pid, signal.SIGCONT)
        _cycles(driver, 100)
        lost = driver.lost_cycles - lost_before  # type: ignore[attr-defined]
        if witness:
            assert driver.far_end_waits >= 1 and not lost.any(), (lost, driver.far_end_waits)  # type: ignore[attr-defined]
        else:
            assert lost.min() >= 1, lost
        waits = driver.far_end_waits  # type: ignore[attr-defined]
        sim.peer.inject("drop", rig.drives[0].node_id, 2)  # servo 1 silent: a Fast Sync Read has no block after it
        _cycles(driver, 50)
        assert (driver.lost_cycles - lost_before - lost).tolist() == [2] * rig.n_joints  # type: ignore[attr-defined]
        assert driver.far_end_waits == waits  # type: ignore[attr-defined]
    finally:
        driver.close()
        sim.close()

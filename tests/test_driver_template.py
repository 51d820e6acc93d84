"""The driver template (drivers.interface.Driver): start, close safe twice, a driver never
closed warns, timeouts are TimeoutErrors, command checks; and pacing as the rig's setting.
On real python-can virtual buses with the simulated arm, and a real pty chain."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import uuid
from pathlib import Path

import can
import numpy as np
import pytest
import yaml

from armid.drivers.canopen_driver import CanopenDriver
from armid.drivers.dynamixel_driver import DynamixelDriver
from armid.io.rig_file import load_rig, rig_from_dict
from armid.schema.errors import DriverError, DriverTimeout, RigFileError
from armid.sim_bus.arm import SimulatedArm
from armid.sim_bus.servo_chain import SimulatedServoChain
from armid.simulated import simulated_driver

ROOT = Path(__file__).resolve().parent.parent
SIM_RIG = ROOT / "config" / "rigs" / "sim.yaml"
SERIAL_RIG = ROOT / "config" / "rigs" / "sim_dynamixel.yaml"


def _channel() -> str:
    return f"armid-test-{uuid.uuid4().hex[:8]}"


def test_close_is_safe_twice_and_a_closed_driver_does_not_start_again() -> None:
    channel = _channel()
    rig = load_rig(SIM_RIG).with_bus(channel=channel)
    buses = [can.Bus(interface="virtual", channel=channel) for _ in range(2)]
    arm = SimulatedArm(rig, bus=buses[0])
    driver = CanopenDriver(rig, bus=buses[1])
    driver.pacing = "consumer"
    try:
        driver.start()
        s = driver.read(1.0)
        driver.acknowledge(s.cycle)
        driver.close()
        driver.close()
        with pytest.raises(DriverError, match="closed; open a new driver"):
            driver.start()
    finally:
        driver.close()
        arm.close()
        for bus in buses:
            bus.shutdown()


def test_a_start_that_fails_closes_what_it_opened() -> None:
    """No drive answers on this bus: the start fails naming the SDO, and the driver is closed
    (its notifier stopped; a second close is a no-op), not left half open."""
    channel = _channel()
    rig = load_rig(SIM_RIG).with_bus(channel=channel)
    bus = can.Bus(interface="virtual", channel=channel)
    driver = CanopenDriver(rig, bus=bus)
    try:
        with pytest.raises(DriverError, match=r"joint 1 \(node 1\): no SDO answer"):
            driver.start()
        assert driver.network is None
        with pytest.raises(DriverError, match="closed"):
            driver.start()
    finally:
        driver.close()
        bus.shutdown()


def test_a_read_that_times_out_is_a_timeout_error() -> None:
    driver = CanopenDriver(load_rig(SIM_RIG).with_bus(channel=_channel()))
    with pytest.raises(TimeoutError, match=r"no cycle within 0.01 s"):
        driver.read(0.01)
    with pytest.raises(DriverTimeout):  # and a driver error, which the command line prints on one line
        driver.read(0.01)
    driver.close()


@pytest.mark.parametrize("value", [[np.nan] * 6, [0.0] * 5])
def test_commands_are_checked_once_for_every_driver(value: list[float]) -> None:
    chain_rig = load_rig(SERIAL_RIG)
    chain = SimulatedServoChain(chain_rig)
    drivers = [CanopenDriver(load_rig(SIM_RIG).with_bus(channel=_channel())), DynamixelDriver(chain_rig, port=chain.port)]
    try:
        for driver in drivers:
            for command in (driver.command_torque, driver.command_position, driver.command_current):
                with pytest.raises(ValueError, match=r"command must be 6 finite values"):
                    command(np.asarray(value))
    finally:
        for driver in drivers:
            driver.close()
        chain.close()


def _run(script: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-W", "always::ResourceWarning", "-c", textwrap.dedent(script)],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)


UNCLOSED = """
    import uuid, can
    from armid.drivers.canopen_driver import CanopenDriver
    from armid.io.rig_file import load_rig
    from armid.sim_bus.arm import SimulatedArm
    channel = f"armid-test-{uuid.uuid4().hex[:8]}"
    rig = load_rig("config/rigs/sim.yaml").with_bus(channel=channel)
    arm = SimulatedArm(rig, bus=can.Bus(interface="virtual", channel=channel))
    driver = CanopenDriver(rig, bus=can.Bus(interface="virtual", channel=channel))
    driver.pacing = "consumer"
    driver.start()
    driver.read(2.0)
    CLOSE
    print("ran")
"""


@pytest.mark.parametrize("close", [False, True])
def test_a_driver_started_and_never_closed_warns(close: bool) -> None:
    """As python-can's bus never shut down: a ResourceWarning (at the interpreter's exit here:
    the cycle's thread keeps a running driver alive), none once closed."""
    done = _run(UNCLOSED.replace("CLOSE", "driver.close(); arm.close()" if close else "pass"))
    assert "ran" in done.stdout, done.stderr[-2000:]
    warned = "ResourceWarning: CanopenDriver was started and never closed" in done.stderr
    assert warned != close, done.stderr[-2000:]


def test_pacing_is_the_rigs_setting() -> None:
    """The simulated rig asks its driver to pace by the drives' answers; an arm simulated in the
    consumer's process paces by the consumer; a rig that says nothing keeps the clock; a wrong
    value is refused naming the field."""
    rig = load_rig(SIM_RIG)
    assert rig.pacing == "drives"
    assert load_rig(ROOT / "config" / "rigs" / "bench_template.yaml").pacing == "clock"
    doc = yaml.safe_load(SIM_RIG.read_text())
    del doc["pacing"]
    assert rig_from_dict(doc, "<test>", SIM_RIG.parent).pacing == "clock"
    with pytest.raises(RigFileError, match=r"<test>: pacing: must be one of clock, drives, consumer, got 'sometimes'"):
        rig_from_dict({**doc, "pacing": "sometimes"}, "<test>", SIM_RIG.parent)
    driver, sim = simulated_driver(rig.with_bus(channel=_channel()))
    try:
        assert driver.pacing == "consumer" and driver.paced
    finally:
        driver.close()
        sim.close()

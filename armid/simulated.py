"""The simulated hardware as a peer on the bus, started here (the top layer) or by a test.

:func:`simulated_driver` starts the rig's simulator (the CiA 402 arm on a CAN bus, or the
Dynamixel chain in a process of its own on a pseudo-terminal) and opens the rig's driver
(the registry, :func:`armid.drivers.open_driver`) on it. Nothing below this layer knows
whether the hardware is real.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from armid.drivers import open_driver
from armid.drivers.interface import Driver
from armid.drivers.rig import Pacing, Rig, open_bus


class Simulator:
    """A running simulator: ``peer`` is the :class:`~armid.sim_bus.arm.SimulatedArm` or the
    :class:`~armid.chain_process.ServoChainProcess`; :meth:`close` stops it (safe twice)."""

    def __init__(self, rig: Rig, in_process_chain: bool = False) -> None:
        self.rig = rig
        self._buses: list[Any] = []
        self.driver_kwargs: dict[str, Any] = {}
        self.peer: Any
        self.pacing: Pacing  # what the driver of this simulated hardware waits for (drivers.rig.Pacing)
        if rig.serial is not None:
            if in_process_chain or rig.source.startswith("<"):
                from armid.sim_bus.servo_chain import SimulatedServoChain

                self.peer = SimulatedServoChain(rig)
            else:
                from .chain_process import ServoChainProcess

                self.peer = ServoChainProcess(rig.source)  # its own process: the driver's cannot stall it
            self.driver_kwargs["port"] = self.peer.port
            self.driver_kwargs["progress"] = self.peer.progress  # how far the chain has got: its own stalls are no servo's silence
            self.pacing = rig.pacing  # the chain keeps its own time: the rig's setting stands
        else:
            from armid.sim_bus.arm import SimulatedArm

            bus = open_bus(**rig.bus.kwargs())
            self._buses.append(bus)
            try:
                self.peer = SimulatedArm(rig, bus=bus)
            except BaseException:
                bus.shutdown()
                raise
            self.pacing = "consumer"  # an arm in this process never runs ahead of its control loop
        self._closed = False

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self.peer.close()
        finally:
            for bus in self._buses:
                bus.shutdown()


def simulated_driver(rig: Rig, **driver_kwargs: Any) -> tuple[Driver, Simulator]:
    """The rig's simulator and its driver (not started); close the driver, then the simulator."""
    sim = Simulator(rig)
    try:
        driver = open_driver(replace(rig, pacing=sim.pacing), **{**sim.driver_kwargs, **driver_kwargs})
    except BaseException:
        sim.close()
        raise
    return driver, sim


def excitation_session(rig: Rig, simulate: bool = True, **kwargs: Any) -> Any:
    """An :class:`~armid.daq.excite.ExcitationSession` on the rig's driver; with ``simulate``
    on the simulated hardware, which the session closes with itself. ``kwargs`` go to the session."""
    from armid.daq.excite import ExcitationSession

    if not simulate:
        return ExcitationSession(rig, **kwargs)
    bus = kwargs.pop("bus", None)
    driver, sim = simulated_driver(rig, **({"bus": bus} if bus is not None else {}))
    return ExcitationSession(rig, driver, simulator=sim, **kwargs)

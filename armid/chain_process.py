"""A simulated Dynamixel chain (:class:`~armid.sim_bus.servo_chain.SimulatedServoChain`) in a
process of its own, as a real chain is: the driver's process cannot stall it.

This is the top layer's: the child reads the rig file (``armid.io``) and starts the simulated
hardware on the parsed rig, so that ``sim_bus`` parses no file. Requests (``inject``,
``status``, ``collector``, ``table``) go as JSON lines over the child's stdin and stdout.
"""

from __future__ import annotations

import select
from typing import Any

from armid.drivers.line_progress import LineProgress
from armid.drivers.rig import Rig
from armid.schema.errors import SimulationError
from armid.sim_bus.servo_chain import SimulatedServoChain


class ServoChainProcess:
    """A :class:`SimulatedServoChain` in a process of its own, like a real chain: the
    driver's process cannot stall it. Requests (``inject``, ``status``, ``collector``, ``table``) go as
    JSON lines over the child's stdin and stdout."""

    def __init__(self, rig_file: str, seed: int | None = None, start_timeout: float = 60.0) -> None:
        import subprocess
        import sys

        args = [sys.executable, "-m", "armid.chain_process", str(rig_file)] + ([] if seed is None else ["--seed", str(seed)])
        self._process = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1)
        hello = self._reply(start_timeout)
        self.port: str = hello["port"]
        # the chain's counters of the line, for its master (drivers.line_progress); the file goes now, the mapping stays
        self.progress = LineProgress(hello["progress"])
        self.progress.unlink()

    @property
    def pid(self) -> int:
        """The chain's process (a test stops it to stand for a host that stopped its CPU)."""
        return self._process.pid

    def _reply(self, timeout: float) -> Any:
        import json

        assert self._process.stdout is not None
        ready, _, _ = select.select([self._process.stdout], [], [], timeout)
        line = self._process.stdout.readline() if ready else ""
        if not line:
            self._process.kill()
            raise SimulationError(f"the simulated servo chain did not answer within {timeout} s (exit code {self._process.poll()})")
        doc = json.loads(line)
        if "error" in doc:
            raise SimulationError(f"the simulated servo chain: {doc['error']}")
        return doc

    def _ask(self, *message: Any) -> Any:
        import json

        assert self._process.stdin is not None
        self._process.stdin.write(json.dumps(message) + "\n")
        self._process.stdin.flush()
        return self._reply(10.0)["value"]

    def inject(self, kind: str, servo_id: int, count: int = 1, bits: int = 0x20) -> None:
        self._ask("inject", kind, servo_id, count, bits)

    def status(self) -> dict[str, Any]:
        return self._ask("status")  # type: ignore[no-any-return]

    def collector(self) -> dict[str, int]:
        """The chain process's garbage collector: objects frozen at start-up, objects a full collection walks."""
        return self._ask("collector")  # type: ignore[no-any-return]

    def table(self, servo_id: int, address: int, length: int) -> bytes:
        return bytes(self._ask("table", servo_id, address, length))

    def close(self) -> None:
        if self._process.poll() is None:
            try:
                assert self._process.stdin is not None
                self._process.stdin.close()  # end of input ends the chain
                self._process.wait(5.0)
            except Exception:
                self._process.kill()
        if self._process.stdout is not None:
            self._process.stdout.close()

    def __enter__(self) -> ServoChainProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def chain_as_hardware(rig: Rig, seed: int | None = None, progress: LineProgress | None = None) -> SimulatedServoChain:
    """A chain standing in for servos in this process, which it then has to itself until the
    process ends: hardware answers in hardware time, so its threads run at real-time priority
    where allowed, above a master's (:data:`~drivers.realtime.HARDWARE_ABOVE`), and what exists
    once it is built is frozen (a full collection of this process took 30-34 ms, and every
    reply waited that long)."""
    from armid.drivers.interface import ProcessSettings

    settings = ProcessSettings()
    settings.realtime(hardware=True)
    chain = SimulatedServoChain(rig, seed=seed, progress=progress)
    settings.freeze()
    return chain


def serve(rig_file: str, seed: int | None = None) -> None:
    """Run a chain and answer JSON-line requests on stdin until it closes (ServoChainProcess).
    The rig file is read here, in the top layer: the simulated hardware takes a parsed rig."""
    import gc
    import json
    import sys

    from armid.io.rig_file import load_rig
    def say(doc: dict[str, Any]) -> None:
        sys.stdout.write(json.dumps(doc) + "\n")
        sys.stdout.flush()

    # the line's thread takes the interpreter from the physics' within half a millisecond
    # of a request (the default 5 ms switch interval would hold the reply that long)
    sys.setswitchinterval(0.0001)
    progress = LineProgress.create()  # in a file the master maps (and removes once it has)
    try:
        chain = chain_as_hardware(load_rig(rig_file), seed, progress)
    except Exception as err:
        progress.unlink()
        say({"error": f"{type(err).__name__}: {err}"})
        return
    say({"port": chain.port, "progress": chain.progress.path})
    try:
        for line in sys.stdin:
            what, *args = json.loads(line)
            try:
                if what == "inject":
                    chain.inject(*args)
                    say({"value": None})
                elif what == "status":
                    say({"value": chain.status()})
                elif what == "collector":  # what a full collection walks, against what start-up froze
                    say({"value": {"frozen": gc.get_freeze_count(), "walked": len(gc.get_objects())}})
                elif what == "table":
                    servo_id, address, length = args
                    with chain._lock:
                        say({"value": list(chain._by_id[servo_id].table[address:address + length])})
                else:
                    say({"error": f"unknown request {what!r}"})
            except Exception as err:
                say({"error": f"{type(err).__name__}: {err}"})
    finally:
        chain.close()
        progress.unlink()  # a master that never took it


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description="a simulated Dynamixel chain on a pty, answering JSON lines on stdin")
    parser.add_argument("rig")
    parser.add_argument("--seed", type=int)
    a = parser.parse_args()
    serve(a.rig, a.seed)

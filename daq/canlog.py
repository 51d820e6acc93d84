"""The raw CAN frames of a run, and replay of them into a virtual bus.

:class:`BusLog` writes every frame on the bus, the master's own SYNC, commands and
heartbeats included, in python-can's log format (``can.log``: candump's text, readable by
``can.LogReader``, ``python -m can.player`` and the can-utils).

:func:`replay_log` plays such a log into a virtual bus, in order and with its time stamps,
to a :class:`~drivers.canopen_driver.CanopenDriver` that only listens, and returns the
samples it decodes: the same records as the run's, cycle by cycle. That holds because the
frames the records come from (SYNCs and TPDOs) are written by the driver itself, under its
decoding lock, in the order it used them and with each SYNC stamped at its cycle's time: a
frame that arrives while the next SYNC goes out is in the log on the side of that SYNC the
driver saw it on. A log starts when the driver is up, so the run's first records (queued
while it started) can precede it, and its first few cycles can be partial: frames that
answer a SYNC from before the log are taken for the next one until the deadline logic
catches up.
"""

from __future__ import annotations

import threading
import time
import uuid
from pathlib import Path
from typing import Any

import can

from armid.drivers.interface import Sample


class BusLog:
    """Log every frame on a driver's bus to ``path`` until :meth:`stop`. SYNCs and TPDOs
    come from the driver (``decoded_frames``), in its decoding order; everything else
    from what its bus receives (through its notifier) and what it sends (a tap on its
    ``send``, which its commands and periodic heartbeat go through). A second bus instance
    would see every frame too, but receives and unpacks each again (on this machine that
    cost more CPU than the rest of the logging), and could not know which side of a SYNC
    the driver saw a frame on.

    A write that fails (a full disk) closes the log, never the driver's path that called it:
    ``failure`` says why, for the command to stop the run on."""

    def __init__(self, driver: Any, path: str | Path) -> None:
        self.path = Path(path)
        self.failure: str | None = None
        self.logger = can.Logger(str(path))
        self.driver = driver
        self.bus = driver.bus
        self._send = self.bus.send
        self._lock = threading.Lock()  # the SYNC thread, senders and the notifier all write
        self._closed = False
        self._decoded = driver.decoded_cob_ids
        send = self._send

        def tapped(msg: can.Message, timeout: float | None = None) -> None:
            if msg.arbitration_id not in self._decoded:
                # logged before it goes out: the answers it provokes must follow it in the log
                self._write(can.Message(timestamp=time.time(), arbitration_id=msg.arbitration_id, is_extended_id=msg.is_extended_id,
                                        is_remote_frame=msg.is_remote_frame, dlc=msg.dlc, data=msg.data, is_rx=False, channel=msg.channel))
            send(msg, timeout)

        self.bus.send = tapped  # instance attribute: every sender of this bus goes through it
        self._listener = _Received(self._write, self._decoded)
        driver.network.notifier.add_listener(self._listener)
        driver.decoded_frames = self._write

    def _write(self, msg: can.Message) -> None:
        with self._lock:
            if not self._closed:
                try:
                    self.logger.on_message_received(msg)
                except OSError as err:
                    self._failed(err)

    def _failed(self, err: OSError) -> None:
        self._closed = True
        if self.failure is None:
            self.failure = f"{self.path}: cannot write ({err.strerror or err})"

    def stop(self) -> None:
        self.driver.decoded_frames = None
        self.bus.send = self._send
        self.driver.network.notifier.remove_listener(self._listener)
        with self._lock:
            self._closed = True
            try:
                self.logger.stop()
            except OSError as err:  # the last buffer did not fit
                self._failed(err)


class _Received(can.Listener):
    def __init__(self, write: Any, skip: set[int]) -> None:
        self.write = write
        self.skip = skip  # the driver writes these itself

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.arbitration_id not in self.skip:
            self.write(msg)


END_OF_LOG_COB_ID = 0x7FF  # no CANopen service uses it; with a payload of its own besides


def replay_log(path: str | Path, rig: Any, timeout_s: float = 30.0) -> list[Sample]:
    """Decode ``path`` as the rig's driver would have: one sample per SYNC in the log.

    The player sends faster than the driver's notifier decodes, so the end of the log is
    marked by one more frame, and the cycles still open are closed only once the notifier
    has reached it (closing them when the sending ended cut a cycle in the middle of the
    stream in two whenever the notifier lagged, as it does under load)."""
    from armid.drivers.canopen_driver import SYNC_COB_ID, CanopenDriver

    channel = f"armid-replay-{uuid.uuid4().hex[:8]}"
    listen_bus = can.Bus(interface="virtual", channel=channel)
    player = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    driver = CanopenDriver(rig.with_bus(interface="virtual", channel=channel), bus=listen_bus)
    driver.frame_time = lambda stamp: stamp  # the log's stamps are its bus time
    samples: list[Sample] = []
    marker = uuid.uuid4().bytes[:8]
    reached = threading.Event()
    try:
        driver.listen()
        assert driver.network is not None  # listening opened it
        driver.network.subscribe(END_OF_LOG_COB_ID, lambda can_id, data, timestamp: reached.set() if bytes(data) == marker else None)
        stop = threading.Event()
        reader = threading.Thread(target=lambda: _drain(driver, samples, stop), daemon=True)
        reader.start()
        syncs, last = 0, 0.0
        for msg in can.LogReader(str(path)):
            if msg.is_error_frame:
                continue
            player.send(msg)
            syncs += msg.arbitration_id == SYNC_COB_ID
            last = msg.timestamp
        player.send(can.Message(timestamp=last, arbitration_id=END_OF_LOG_COB_ID, data=marker, is_extended_id=False))
        if not reached.wait(timeout_s):
            raise TimeoutError(f"{path}: the replay did not decode the whole log within {timeout_s:g} s")
        driver.flush()
        deadline = time.monotonic() + timeout_s
        while len(samples) < syncs and time.monotonic() < deadline:
            time.sleep(0.01)
        stop.set()
        reader.join(2.0)
        driver.close()
    finally:
        player.shutdown()
        listen_bus.shutdown()
    return samples


def _drain(driver: Any, samples: list[Sample], stop: threading.Event) -> None:
    """Every sample the driver gives, until ``stop`` is set and none is left (never longer)."""
    from armid.schema.errors import DriveFault, DriverError

    while True:
        try:
            samples.append(driver.read(timeout=0.1))
        except DriveFault:
            return
        except DriverError:  # none within 0.1 s
            if stop.is_set():
                return
        except Exception:
            return

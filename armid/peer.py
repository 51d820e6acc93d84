"""An armid command in a process of its own, beside the real-time process (STYLE.md, "Real time
in Python"): the process that owns the bus acquires, controls and records; ``armid serve`` and
``armid estimate live``, which compute, run as :class:`Peer` processes that meet it on a
loopback Zenoh endpoint, as they would on a lab's other machine.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any


class Peer:
    """An armid command in a process of its own (``armid serve``, ``armid estimate live``),
    meeting the demo on a loopback Zenoh endpoint: a lab's analysis beside its real-time
    process. The real-time process acquires, controls and records; whatever computes runs
    here, where a stall cannot reach the drives (STYLE.md, "Real time in Python")."""

    def __init__(self, args: list[str], endpoint: str, log: Path) -> None:
        import subprocess
        import sys

        log.parent.mkdir(parents=True, exist_ok=True)
        self.log_path = log
        self._log = open(log, "w")  # noqa: SIM115 - closed by stop()
        self.command = "armid " + " ".join(args[:2])
        self.proc = subprocess.Popen([sys.executable, "-m", "armid.cli", *args, "--zenoh-connect", endpoint, "--zenoh-listen"],
                                     stdin=subprocess.DEVNULL, stdout=self._log, stderr=subprocess.STDOUT)

    def wait_alive(self, session: Any, token: str, timeout_s: float = 120.0) -> None:
        """Until the peer's liveliness token is seen (it is subscribed and ready)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"{self.command} ended with exit {self.proc.returncode} before it was ready: {self.tail()}")
            if any(r.ok is not None for r in session.liveliness().get(token, timeout=1.0)):
                return
            time.sleep(0.1)
        raise RuntimeError(f"{self.command} was not ready within {timeout_s:.0f} s: {self.tail()}")

    def tail(self) -> str:
        self._log.flush()
        lines = self.log_path.read_text().strip().splitlines()
        return " | ".join(lines[-3:]) or "(no output)"

    def stop(self, timeout_s: float = 30.0) -> int:
        """SIGINT, as Ctrl-C: the peer closes what it writes and exits (safe to call twice)."""
        import signal
        import subprocess

        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()
        return int(self.proc.returncode)


def loopback_endpoint() -> str:
    """A free TCP port of the loopback, as a Zenoh endpoint: the demo's processes meet there."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def collect(session: Any, key_expr: str, into: list[dict[str, Any]]) -> Any:
    """Append every JSON document published on ``key_expr`` (the callback only parses)."""
    import json

    return session.declare_subscriber(key_expr, lambda sample: into.append(json.loads(sample.payload.to_string())))


class Meeting:
    """A Zenoh session listening on a free loopback endpoint (127.0.0.1 only), where the demo
    meets its peers; a viewer joins it there too (:meth:`watch_command`)."""

    def __init__(self) -> None:
        import zenoh

        from armid.daq.stream import session_config

        self.endpoint = loopback_endpoint()
        self.session = zenoh.open(session_config(listen=[self.endpoint], connect=[]))

    def watch_command(self, robot: str) -> str:
        """The ``armid watch`` command that joins this meeting from another terminal."""
        return f"armid watch --robot {robot} --zenoh-connect {self.endpoint}"

    def close(self) -> None:
        if not self.session.is_closed():
            self.session.close()


class PeerLink:
    """The demo's side of a :class:`Peer`: a Zenoh session listening on a loopback endpoint,
    the peer connected to it and ready (its liveliness ``token`` seen), every JSON document it
    publishes on ``publishes`` collected in :attr:`docs`, and a :class:`~daq.stream.Stream` that
    carries the records to it. :meth:`close` ends them in order (safe to call twice)."""

    def __init__(self, robot: str, args: list[str], log: Path, publishes: str, token: str, component: str = "demo",
                 wait: bool = True, meeting: Meeting | None = None) -> None:
        """``wait=False``: the peer starts (its imports take seconds) while the caller does
        something else; :meth:`ready` waits for it. ``meeting``: the caller's session and
        endpoint, shared with its other peers and left open by :meth:`close` (default: a
        session of this link's own on an endpoint of its own)."""
        from armid.daq.stream import key

        self.docs: list[dict[str, Any]] = []
        self._robot, self._token, self._component = robot, key(robot, token), component
        self._meeting = meeting if meeting is not None else Meeting()
        self._own = meeting is None
        self.session = self._meeting.session
        self.peer = Peer(args, self._meeting.endpoint, log)
        self._subscriber: Any = None
        self.stream: Any = None
        self._alive = False
        try:
            self._subscriber = collect(self.session, key(robot, publishes), self.docs)
            if wait:
                self.ready()
        except BaseException:
            self.close()
            raise

    def open_stream(self) -> Any:
        """The stream that feeds the peer, opened now (what it carries before the peer is ready
        does not reach it: :meth:`ready` before what it must see)."""
        from armid.daq.stream import Stream

        if self.stream is None:
            self.stream = Stream(self.session, self._robot, self._component, lambda: {"component": self._component})
        return self.stream

    def ready(self) -> None:
        """Until the peer is ready (its liveliness token seen); the stream that feeds it open."""
        if not self._alive:
            self.peer.wait_alive(self.session, self._token)
            self._alive = True
        self.open_stream()

    def wait(self, done: Any, timeout_s: float) -> None:
        """Until ``done()`` holds, the peer ends, or ``timeout_s`` passes."""
        deadline = time.monotonic() + timeout_s
        while not done() and time.monotonic() < deadline and self.peer.proc.poll() is None:
            time.sleep(0.05)

    def close(self) -> None:
        if self.stream is not None:
            self.stream.close()
            self.stream = None
        if self._subscriber is not None:
            self._subscriber.undeclare()
            self._subscriber = None
        self.peer.stop()
        if self._own:
            self._meeting.close()

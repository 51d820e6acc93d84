"""How far the far end of a simulated serial line has got, shared between its two processes.

A real servo chain answers in hardware time. A simulated one is a process on the same
machine, and a machine under a hypervisor stops one of its CPUs for up to 8 ms at a time
(steal time: a real-time thread pinned to the CPU sees the gap, and nothing inside the
machine can preempt the host); a pseudo-terminal also carries every byte through a kernel
worker of ordinary priority. A chain whose CPU (or whose line) stopped while the master's
ran answers after the master's reply window shut: a stall of the simulation, not a silent
servo. The chain counts, in shared memory, the request bytes it has served and the reply
bytes it has put on the line; the master compares them with what it wrote and read
(:meth:`LineProgress.behind`) and gives a window the far end has not yet had its chance
in again, as it does for a stall of its own process. Real hardware has no such counters:
there every missing reply counts.
"""

from __future__ import annotations

import ctypes
import mmap
import os
import tempfile

SIZE = 16  # two unsigned 64-bit counters: request bytes served, reply bytes sent


class LineProgress:
    """The far end's two counters, in a shared mapping (``path``, or anonymous for one process).

    The chain's line thread is the only writer; each counter is one aligned 8-byte store."""

    def __init__(self, path: str | None = None) -> None:
        if path is None:
            self._map = mmap.mmap(-1, SIZE)
        else:
            fd = os.open(path, os.O_RDWR)
            try:
                self._map = mmap.mmap(fd, SIZE)
            finally:
                os.close(fd)
        self.path = path
        self._served = ctypes.c_uint64.from_buffer(self._map, 0)
        self._sent = ctypes.c_uint64.from_buffer(self._map, 8)
        self._base = (0, 0)

    @classmethod
    def create(cls) -> LineProgress:
        """A new pair of counters in a file another process can map (:attr:`path`)."""
        folder = "/dev/shm" if os.path.isdir("/dev/shm") else None
        fd, path = tempfile.mkstemp(prefix="armid-line-", dir=folder)
        try:
            os.write(fd, bytes(SIZE))
        finally:
            os.close(fd)
        return cls(path)

    def unlink(self) -> None:
        """Remove the file (both mappings stay valid)."""
        if self.path is not None:
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass

    # --- the far end (the simulated chain) ---
    def record(self, served: int, sent: int) -> None:
        """Request bytes served so far (answered, or found needing no answer), reply bytes sent so far."""
        self._sent.value = sent
        self._served.value = served

    # --- the master ---
    def start(self) -> None:
        """What the far end had served and sent before this master opened the line: not its."""
        self._base = (self._served.value, self._sent.value)

    def behind(self, written: int, read: int) -> bool:
        """Whether the far end has not yet served the ``written`` request bytes of this master,
        or has sent reply bytes this master has not yet ``read`` (the line still holds them)."""
        served = self._served.value - self._base[0]  # read first: the far end writes it last
        sent = self._sent.value - self._base[1]
        return served < written or sent > read

    def close(self) -> None:
        del self._served, self._sent
        self._map.close()

"""Real-time scheduling for the process that owns the bus (STYLE.md, "Real time in Python").

A 2 ms cycle kept by Python threads at normal priority waits behind whatever else the machine
runs: with two busy processes on a 2-core machine, the scheduler hands the cycle's threads
the CPU tens of milliseconds late, and the drives see SYNC late. Where the system allows it
(root, or ``CAP_SYS_NICE`` and an ``RLIMIT_RTPRIO``), every Python thread of the process runs
at ``SCHED_FIFO``: they share one interpreter lock, so a loop thread at real-time priority
waiting for the lock held by a normal-priority thread that the scheduler preempted would
wait all the same (priority inversion). Threads that compute (:data:`ORDINARY_THREADS`) stay
ordinary: analysis belongs in another process, and where a test keeps it in this one it must
not take the cores from the cycle; so is the thread that opened an excitation session,
between its runs (:func:`calling_thread_at`). Threads started later by these threads inherit the
policy (``pthread_create``'s default). Memory is locked as it is touched
(``mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT)``), so no page of the loop is swapped out.

``ARMID_REALTIME`` chooses: a priority 1-99 (default 50, below the kernel's threaded
interrupts of a PREEMPT_RT kernel, which the bus itself needs), or ``off``. A simulated arm or
servo chain in a process of its own stands in for drives, which have processors of their own:
it runs :data:`HARDWARE_ABOVE` higher, so that on a machine it shares with the master it is
never the one waiting (a simulator and a master at one priority on two cores lost cycles over
``udp_multicast`` when both were busy, issue 31).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

DEFAULT_PRIORITY = 50
HARDWARE_ABOVE = 10  # a simulated drive's priority over its master's
ORDINARY_THREADS = ("armid-serve-", "armid-payload", "armid-regressor")
"""Threads that compute, left at the ordinary policy when they share the process (a test's
in-process service, the regressor's pool): arithmetic must not take the cores from the cycle."""
MCL_CURRENT, MCL_FUTURE, MCL_ONFAULT = 1, 2, 4


@dataclass(frozen=True)
class Timing:
    """What scheduling the cycle's threads got, and why: said once at start-up."""

    policy: str  # "SCHED_FIFO" | "normal"
    priority: int
    memory_locked: bool
    why: str

    @property
    def realtime(self) -> bool:
        return self.policy == "SCHED_FIFO"

    def sentence(self, what: str = "cycle threads") -> str:
        if self.realtime:
            return f"{what} at SCHED_FIFO {self.priority}" + ("" if self.memory_locked else f" (memory not locked: {self.why})")
        return f"{what} at normal priority: {self.why}; expect jitter under load"


def requested_priority(hardware: bool = False) -> tuple[int, str]:
    """(priority, why) from ``ARMID_REALTIME``, :data:`HARDWARE_ABOVE` higher for simulated
    ``hardware``; priority 0 means off."""
    text = os.environ.get("ARMID_REALTIME", "").strip().lower()
    above = HARDWARE_ABOVE if hardware else 0
    if not text:
        return DEFAULT_PRIORITY + above, ""
    if text in ("off", "0", "no", "false"):
        return 0, "ARMID_REALTIME=off"
    try:
        value = int(text)
    except ValueError:
        return DEFAULT_PRIORITY + above, f"ARMID_REALTIME={text!r} is not a priority (1-99 or off): using {DEFAULT_PRIORITY + above}"
    return max(1, min(99, value + above)), ""


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    return ctypes.CDLL(name, use_errno=True) if name else None


class RealtimeScheduling:
    """Holds ``SCHED_FIFO`` for the process's Python threads; :meth:`release` puts back the
    policy each had (threads started meanwhile go back to normal)."""

    def __init__(self, hardware: bool = False) -> None:
        self.hardware = hardware  # a simulated drive in a process of its own: above its master
        self._before: dict[int, tuple[int, int]] = {}  # every thread's policy and priority before acquire()
        self._locked = False
        self.timing: Timing | None = None

    def acquire(self) -> Timing:
        priority, why = requested_priority(self.hardware)
        if not hasattr(os, "sched_setscheduler"):
            self.timing = Timing("normal", 0, False, "this system has no sched_setscheduler")
            return self.timing
        if priority == 0:
            self.timing = Timing("normal", 0, False, why)
            return self.timing
        self._before = {tid: policy for tid in _task_ids() if (policy := _policy(tid)) is not None}
        param = os.sched_param(priority)
        try:
            for tid in _python_thread_ids():
                try:
                    os.sched_setscheduler(tid, os.SCHED_FIFO, param)
                except ProcessLookupError:  # the thread ended meanwhile
                    pass
        except PermissionError:
            self.release()
            self.timing = Timing("normal", 0, False, "no permission for SCHED_FIFO (run as root, or give CAP_SYS_NICE and an rtprio limit)")
            return self.timing
        except OSError as err:
            self.release()
            self.timing = Timing("normal", 0, False, f"SCHED_FIFO refused ({err.strerror or err})")
            return self.timing
        locked, lock_why = self._lock_memory()
        self.timing = Timing("SCHED_FIFO", priority, locked, why or lock_why)
        return self.timing

    def _lock_memory(self) -> tuple[bool, str]:
        libc = _libc()
        if libc is None:
            return False, "no C library found for mlockall"
        if libc.mlockall(MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT) != 0:
            return False, f"mlockall: {os.strerror(ctypes.get_errno())}"
        self._locked = True
        return True, ""

    def release(self) -> None:
        """Every thread back to the policy it had; a thread started meanwhile (it inherited the
        real-time policy: ours, a library's, a child process's starter) back to normal."""
        for tid in _task_ids():
            policy, priority = self._before.get(tid, (os.SCHED_OTHER, 0))
            try:
                if tid in self._before or os.sched_getscheduler(tid) == os.SCHED_FIFO:
                    os.sched_setscheduler(tid, policy, os.sched_param(priority))
            except OSError:  # the thread ended meanwhile
                pass
        self._before = {}
        if self._locked:
            libc = _libc()
            if libc is not None:
                libc.munlockall()
            self._locked = False


def one_cpu() -> int | None:
    """Keep this process on one CPU, the last it may use; returns it (None where the system
    cannot). For a simulated device: the kernel queues a datagram looped back on this host on
    the CPU that sent it, so a sender that moves between CPUs can have its frames delivered out
    of order, one held behind a busy CPU while the next goes through, which a CAN bus never
    does (on a 2-core machine with busy processes, one joint's TPDO came after its cycle's
    deadline while the joints sent after it were on time; kept on one CPU, none did)."""
    if not hasattr(os, "sched_setaffinity"):
        return None
    try:
        cpu = max(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
    except OSError:
        return None
    return cpu


def realtime_allowed() -> bool:
    """Whether this process may take ``SCHED_FIFO`` (tried on the calling thread, put back)."""
    if not hasattr(os, "sched_setscheduler"):
        return False
    before = _policy(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except OSError:
        return False
    if before is not None:
        os.sched_setscheduler(0, before[0], os.sched_param(before[1]))
    return True


def ordinary_priority() -> None:
    """This process's threads at the ordinary policy: a process that computes (``armid serve``,
    ``armid estimate``) started from a real-time thread inherited its policy, and must not keep it."""
    for tid in _task_ids():
        try:
            if os.sched_getscheduler(tid) != os.SCHED_OTHER:
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
        except (OSError, AttributeError):
            pass


Policy = tuple[int, int]
"""A thread's scheduling policy and priority, as ``os.sched_getscheduler``/``sched_getparam`` say."""


def calling_thread_policy() -> Policy | None:
    """The calling thread's policy and priority; None where the system cannot say."""
    return _policy(threading.get_native_id()) if hasattr(os, "sched_getscheduler") else None


def set_calling_thread(policy: Policy) -> bool:
    """The calling thread at ``policy``; False where the system refuses (it stays as it was)."""
    try:
        os.sched_setscheduler(threading.get_native_id(), policy[0], os.sched_param(policy[1]))
    except (OSError, AttributeError):
        return False
    return True


def ordinary_policy() -> Policy:
    return (os.SCHED_OTHER, 0)


@contextmanager
def calling_thread_at(policy: Policy | None) -> Iterator[None]:
    """The calling thread at ``policy`` for the block, then as it was before.

    The thread that runs a plan is real-time while it runs it, and ordinary between runs,
    where a script designs the next trajectory: a thread that computes at ``SCHED_FIFO``
    keeps a core for seconds, and the kernel then serves the ordinary tasks that core
    starved by pausing every real-time thread on it for up to 50 ms (RT throttling,
    ``sched_rt_runtime_us``): the simulated drives' threads among them, which then answer
    no SYNC or request for cycles."""
    before = calling_thread_policy()
    changed = policy is not None and before is not None and policy != before and set_calling_thread(policy)
    try:
        yield
    finally:
        if changed and before is not None:
            set_calling_thread(before)


def stall_sentence(seconds: float) -> str:
    """A fault that came from this process not being scheduled, said with the figures."""
    try:
        load = f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    except OSError:
        load = f"{os.cpu_count()} cores"
    return f"this process was not scheduled for {seconds:.2f} s ({load})"


def silent_for(last_sent: float, last_stall: tuple[float, float], wait: float, began: float, sent: int, least_period_s: float) -> float:
    """How long a cycle thread did not run, where that explains a wait of ``wait`` begun at
    ``began`` that saw no cycle (0 where it ran): fewer cycles ``sent`` meanwhile than even a
    paced thread sends (one per ``least_period_s``), silent still since ``last_sent``, or back
    from a stall it measured (``last_stall``: when, how long). A demo beside two busy loops stopped
    on "no cycle within 1.0 s" after 1.7-1.8 s in which no thread of its process ran."""
    now = time.monotonic()
    when, stall = last_stall
    waited = now - began
    longest = max(now - last_sent, stall if now - when < wait + 0.5 else 0.0,
                  waited - sent * least_period_s if sent < 0.5 * waited / least_period_s else 0.0)
    return longest if longest > 0.5 * wait else 0.0


def _task_ids() -> list[int]:
    """Every thread of this process, the libraries' (BLAS, Zenoh's runtime) included."""
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return _python_thread_ids()


def _policy(tid: int) -> tuple[int, int] | None:
    try:
        return os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority
    except OSError:
        return None


def _python_thread_ids() -> list[int]:
    """The Python threads of the cycle's role (all but :data:`ORDINARY_THREADS`)."""
    return [t.native_id for t in threading.enumerate()
            if t.native_id is not None and t.is_alive() and not t.name.startswith(ORDINARY_THREADS)]

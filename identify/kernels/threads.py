"""The threads that share a large computation's independent parts.

Identify's regressor shares its chunks of samples (:mod:`identify.kernels.regressor_lanes`), the
diagnosis's scoring its joints and candidates (:func:`identify.diagnosis_scoring.round_moments`). The compiled
kernels and numpy's large operations release the interpreter's lock, so on a machine's cores
these parts run side by side. Each use has its own pool: a joint's task may compute a
regressor, and waits for the regressor's pool then, which a shared pool (all of its threads
busy with joints) would never serve.
"""

from __future__ import annotations

import itertools
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numba

THREADS = max(1, int(getattr(numba.config, "NUMBA_NUM_THREADS", 1)))
"""Threads that share a large call (numba's thread count: the CPUs, or ``NUMBA_NUM_THREADS``)."""

_POOLS: dict[str, ThreadPoolExecutor] = {}
_MADE = threading.Lock()


def pool(name: str) -> ThreadPoolExecutor:
    """The process's pool ``armid-<name>``, ``THREADS - 1`` threads (the caller is the other
    one), made on first use and kept for the process's life."""
    with _MADE:
        if name not in _POOLS:
            _POOLS[name] = ThreadPoolExecutor(max(1, THREADS - 1), thread_name_prefix=f"armid-{name}")
        return _POOLS[name]


def each_shared(task: Callable[[int], None], count: int, name: str) -> None:
    """``task(k)`` for k in ``range(count)``, shared between this thread and pool ``name``'s
    (in this thread alone on one core): each thread takes the next task not yet taken, so
    that tasks of unequal size (a joint with all 119 cogging periods, one with a few) keep
    every thread busy; put the largest first. The tasks must be independent. An exception ends
    its thread's share and is raised here once every thread has stopped: no task outlives the
    call."""
    threads = min(THREADS, count)
    if threads <= 1:
        for k in range(count):
            task(k)
        return
    taken = itertools.count()  # next() is atomic under the interpreter's lock

    def share() -> None:
        while (k := next(taken)) < count:
            task(k)

    others = [pool(name).submit(share) for _ in range(1, threads)]
    try:
        share()
    finally:
        for f in others:
            f.exception()  # waits
    for f in others:
        f.result()

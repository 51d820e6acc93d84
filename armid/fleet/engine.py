"""Where the recordings are identified: Ray tasks (a local cluster or a real one), or this process.

Ray is an optional extra (``pip install "armid[fleet]"``). Each recording is one task
(:func:`armid.fleet.task.identify_recording`); at most ``workers`` are in flight, and each
result is handed to ``on_result`` as soon as its task finishes (``ray.wait``), whatever the
order they were started in. On a real cluster (``address``) every node must see ROOT at the
same path (a shared file system) and have armid installed. The local engine runs the same
function in a loop in this process, for tests and small labs.
"""

from __future__ import annotations

import logging
import os
from collections import deque
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from armid.extras import EXTRAS, install_command
from armid.schema.errors import MissingExtraError, OptionError, UsageError

if TYPE_CHECKING:
    from .task import Job, Result

ENGINES = ("ray", "local")

ONE_THREAD = {"env_vars": {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}}
"""Each worker computes on one thread (Ray runs one task per CPU): the regressor's threads and
BLAS's would otherwise share out the cores twice over."""
EXTRA = install_command("fleet")


def import_ray() -> Any:
    """The ``ray`` module, or one clear error naming the extra that installs it."""
    try:
        import ray
    except ImportError as err:
        raise MissingExtraError(f"--engine ray needs the {EXTRAS['fleet'].purpose}, not installed ({err.msg}): {EXTRA}, "
                                "or run with --engine local --workers 1") from None
    return ray


def run_local(jobs: Sequence[Job], on_result: Callable[[Result], None]) -> str:
    """Every job in this process, one after the other."""
    from .task import identify_recording

    for job in jobs:
        on_result(identify_recording(job))
    return "this process (--engine local)"


def _start(ray: Any, workers: int | None, address: str | None) -> bool:
    """Join ``address``, or start a local cluster of ``workers`` CPUs; False when Ray was
    already running in this process (a caller's own cluster, left as it is)."""
    if ray.is_initialized():
        return False
    quiet = {"logging_level": logging.ERROR, "log_to_driver": False}
    if address:
        ray.init(address=address, **quiet)
    else:
        ray.init(num_cpus=workers or os.cpu_count() or 1, include_dashboard=False, **quiet)
    return True


def run_ray(jobs: Sequence[Job], on_result: Callable[[Result], None], workers: int | None = None, address: str | None = None) -> str:
    """Every job as a Ray task, at most ``workers`` at once (default: the cluster's CPUs); a
    task that dies (its worker lost) is a failed result too. Returns what ran them."""
    from .task import Job, Result, identify_recording, one_line

    ray = import_ray()
    started = _start(ray, workers, address)
    try:
        cpus = int(ray.cluster_resources().get("CPU", 1))
        limit = max(1, workers or cpus)
        task = ray.remote(num_cpus=1, runtime_env=ONE_THREAD)(identify_recording)
        queue, pending = deque(jobs), dict[Any, Job]()
        while queue or pending:
            while queue and len(pending) < limit:
                job = queue.popleft()
                pending[task.remote(job)] = job
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                job = pending.pop(ref)
                try:
                    result = ray.get(ref)
                except Exception as err:  # the worker died or the object was lost: that recording's row says so
                    result = Result(job.arm, job.recording, error=one_line(f"the Ray task failed: {type(err).__name__}: {err}"))
                on_result(result)
        where = address or "a local Ray cluster"
        return f"{where} ({cpus} CPUs, at most {limit} task(s) at once)"
    finally:
        if started:
            ray.shutdown()


def check(engine: str, workers: int | None, address: str | None) -> None:
    """The options fit the engine: the local engine takes one worker and no address; Ray must
    be installed for the Ray engine. One clear error before anything starts."""
    if engine == "local" and ((workers or 1) != 1 or address):
        raise UsageError("--engine local runs in this process, one recording at a time: --workers 1 and no --address "
                         f"(more workers run on Ray: --engine ray; {EXTRA})")
    if engine == "ray":
        import_ray()
        if address:
            _reachable(address)


def _reachable(address: str, timeout_s: float = 5.0) -> None:
    """A ``host:port`` (or ``ray://host:port``) address must accept a connection: Ray itself
    retries an absent cluster for minutes before it gives up."""
    import socket

    hostport = address.split("://", 1)[-1]
    host, _, port = hostport.rpartition(":")
    if not host or not port.isdigit():
        return  # "auto" and the like: Ray finds the cluster itself
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            pass
    except OSError as err:
        raise OptionError("--address", f"no Ray cluster answers at {address} ({err.strerror or err})") from None


def run(engine: str, jobs: Sequence[Job], on_result: Callable[[Result], None], workers: int | None, address: str | None) -> str:
    """Run ``jobs`` on ``engine`` (:data:`ENGINES`) after :func:`check`; what ran them."""
    check(engine, workers, address)
    return run_local(jobs, on_result) if engine == "local" else run_ray(jobs, on_result, workers, address)

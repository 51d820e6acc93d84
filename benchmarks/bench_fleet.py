"""``armid fleet`` on Ray: the same generated fleet on 2 workers against 1, and the same results.

The fleet is ``tests/fleetgen.py``'s (6 arms x 10 recordings of 20 s at 200 Hz, a friction
step, a gain drift and a 1 kg tool in it; made by code that shares nothing with armid). For
each worker count a local Ray cluster of that many CPUs is started in this process, each
worker is warmed up (its first recording pays for imports and compiled kernels), and then
every recording is identified through :func:`armid.fleet.engine.run_ray` (what ``armid fleet
--engine ray`` runs). The runs alternate (1, 2, 1, 2, ...) so that a load that comes and goes
on a shared machine falls on both; the figure is the ratio of the medians, with the load
average before and after. The results of every run must be the same (values, stds, errors,
changes), or the script exits 1.

    python benchmarks/bench_fleet.py [repeats] [fleet_dir]
"""

from __future__ import annotations

import logging
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from figures_json import recorded  # noqa: E402

from armid.fleet.discover import find_arms, jobs_of  # noqa: E402
from armid.fleet.engine import ONE_THREAD, import_ray, run_ray  # noqa: E402
from armid.fleet.outputs import detect, in_order  # noqa: E402
from armid.fleet.task import Result, identify_recording  # noqa: E402


def fingerprint(results: list[Result]) -> tuple[list[tuple[object, ...]], list[tuple[object, ...]]]:
    """Every recording's quantities (or error) in order, and the changes found."""
    ordered = in_order(results)
    rows = [(r.recording, r.error, tuple((q.parameter, q.joint, q.value, q.std) for q in r.quantities), r.fit_error, r.cv_error)
            for rs in ordered.values() for r in rs]
    changes = [(c.arm, c.recording, c.parameter, c.joint, c.kind) for c in detect(ordered).changes]
    return rows, changes


def timed_run(ray: object, jobs: list, workers: int) -> tuple[float, list[Result]]:
    """Seconds to identify every job on a fresh local cluster of ``workers`` CPUs, warmed up."""
    ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)  # type: ignore[attr-defined]
    try:
        warm = ray.remote(num_cpus=1, runtime_env=ONE_THREAD)(identify_recording)  # type: ignore[attr-defined]
        ray.get([warm.remote(jobs[k]) for k in range(workers)])  # type: ignore[attr-defined]
        out: list[Result] = []
        start = time.perf_counter()
        run_ray(jobs, out.append, workers)
        return time.perf_counter() - start, out
    finally:
        ray.shutdown()  # type: ignore[attr-defined]


def main(repeats: int = 2, fleet_dir: str | None = None) -> int:
    import fleetgen

    ray = import_ray()
    with tempfile.TemporaryDirectory() as scratch:
        root = Path(fleet_dir or scratch) / "fleet"
        if not root.is_dir():
            fleetgen.make_fleet(root)
        arms, _ = find_arms(root)
        jobs = jobs_of(arms, root)
        load_before = os.getloadavg()
        seconds: dict[int, list[float]] = {1: [], 2: []}
        reference = None
        for _ in range(repeats):
            for workers in (1, 2):
                took, results = timed_run(ray, jobs, workers)
                seconds[workers].append(took)
                cpu = sum(r.cpu_seconds for r in results)
                print(f"{workers} worker(s): {len(results)} recordings in {took:.1f} s; the tasks' CPU time {cpu:.1f} s, "
                      f"so the run had {cpu / took:.2f} cores (load average {os.getloadavg()[0]:.2f} now)")
                got = fingerprint(results)
                if reference is None:
                    reference = got
                elif got != reference:
                    print("the results differ between runs", file=sys.stderr)
                    return 1
        load_after = os.getloadavg()
    one, two = statistics.median(seconds[1]), statistics.median(seconds[2])
    assert reference is not None
    print(f"fleet of {len(arms)} arms, {len(jobs)} recordings; {len(reference[1])} changes found, the same on every run")
    pairs = ", ".join(f"{a / b:.2f}x" for a, b in zip(seconds[1], seconds[2]))
    print(f"each pair run back to back: {pairs}")
    print(f"1 worker {one:.1f} s, 2 workers {two:.1f} s (medians of {repeats}): {one / two:.2f}x faster (target 1.6x); "
          f"load average (1, 5, 15 min) before {', '.join(f'{x:.2f}' for x in load_before)}, "
          f"after {', '.join(f'{x:.2f}' for x in load_after)} on {os.cpu_count()} CPUs")
    return 0


if __name__ == "__main__":
    argv = sys.argv[1:]
    with recorded("fleet"):
        code = main(int(argv[0]) if argv else 2, argv[1] if len(argv) > 1 else None)
        if code:
            raise SystemExit(code)

"""``armid identify`` on 100,000 samples x 6 joints (a CSV) against the plain script
(``plain_identify.py``: a per-sample Pinocchio regressor and ``numpy.linalg.lstsq``) on the same
file, as whole processes, what a user waits for (target: at most 1.0x; beyond it 0.5x).

    python benchmarks/bench_identify_process.py [repeats] [n_samples]

The file is made here with Pinocchio alone (no armid code): the UR5 that armid ships
(``config/robots/ur5.urdf``, whose robot file declares viscous and Coulomb friction) on a
Fourier trajectory of five harmonics per joint at 500 Hz, its torque Pinocchio's RNEA plus
viscous and Coulomb friction plus noise. The two processes run interleaved (armid, plain, armid,
...) so that a load that comes and goes falls on both; each is given as its best and its median,
wall-clock and CPU seconds (steadier on a shared machine), with the load average at the start and the end.
"""

from __future__ import annotations

import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pinocchio as pin
from figures_json import load_average, recorded

ROOT = Path(__file__).resolve().parent.parent
URDF = ROOT / "config" / "robots" / "ur5.urdf"
ROBOT = ROOT / "config" / "robots" / "ur5.yaml"
RATE_HZ = 500.0


def make_csv(path: Path, n: int, seed: int = 0) -> None:
    """``n`` samples of the UR5 on a random Fourier trajectory (module docstring), as t, q, qd, tau."""
    rng = np.random.default_rng(seed)
    model = pin.buildModelFromUrdf(str(URDF))
    data = model.createData()
    nj = model.nv
    t = np.arange(n) / RATE_HZ
    w = 2 * np.pi * 0.1 * np.arange(1, 6)  # 0.1-0.5 Hz
    a, b = rng.normal(scale=0.3, size=(2, nj, 5)) / np.arange(1, 6)
    s, c = np.sin(np.outer(t, w)), np.cos(np.outer(t, w))
    q = s @ (a / w).T - c @ (b / w).T
    qd = c @ a.T + s @ b.T
    qdd = -s @ (a * w).T + c @ (b * w).T
    tau = np.array([pin.rnea(model, data, q[k], qd[k], qdd[k]) for k in range(n)])
    viscous, coulomb = rng.uniform(0.5, 3.0, nj), rng.uniform(0.5, 4.0, nj)
    tau += viscous * qd + coulomb * np.sign(qd) + rng.normal(scale=0.05 * tau.std(axis=0), size=tau.shape)
    header = ",".join(["t"] + [f"{k}{j + 1}" for k in ("q", "qd", "tau") for j in range(nj)])
    np.savetxt(path, np.column_stack([t, q, qd, tau]), delimiter=",", header=header, comments="", fmt="%.10g")


def wall_seconds(argv: list[str]) -> tuple[float, float, str]:
    """One whole process, start to exit: its wall-clock and CPU seconds (user and system,
    all its threads) and its last line; a failed run is no figure."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True)
    took = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} exited {done.returncode}: {done.stderr[-1000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return took, cpu, (done.stdout.strip().splitlines() or [""])[-1]


def interleaved(commands: dict[str, list[str]], repeats: int) -> tuple[dict[str, list[float]], dict[str, list[float]], dict[str, str], list[float]]:
    """Each command run once untimed (numba's cache and the files in the page cache, as a
    user's second run), then ``repeats`` rounds of every command in turn: wall-clock and CPU
    seconds per command, each one's last line, and the load average at the start."""
    for argv in commands.values():
        wall_seconds(argv)
    load_start = load_average()
    times: dict[str, list[float]] = {name: [] for name in commands}
    cpus: dict[str, list[float]] = {name: [] for name in commands}
    last: dict[str, str] = {}
    for _ in range(repeats):
        for name, argv in commands.items():
            took, cpu, last[name] = wall_seconds(argv)
            times[name].append(took)
            cpus[name].append(cpu)
    return times, cpus, last, load_start


def print_against(times: dict[str, list[float]], cpus: dict[str, list[float]], last: dict[str, str], ours: str, reference: str) -> None:
    """Each command's best and median, wall and CPU, then ``ours`` against ``reference`` as ratios."""
    for name, secs in times.items():
        print(f"{name}: best {min(secs):.2f} s, median {statistics.median(secs):.2f} s; CPU best {min(cpus[name]):.2f} s, "
              f"median {statistics.median(cpus[name]):.2f} s ({last[name]})")
    a, p = times[ours], times[reference]
    ca, cp = cpus[ours], cpus[reference]
    print(f"{ours} / {reference}: {min(a) / min(p):.2f}x (best), {statistics.median(a) / statistics.median(p):.2f}x (median); "
          f"CPU seconds {min(ca) / min(cp):.2f}x (best), {statistics.median(ca) / statistics.median(cp):.2f}x (median)")


def main(repeats: int = 5, n: int = 100_000) -> None:
    armid = str(Path(sys.executable).parent / "armid")
    with tempfile.TemporaryDirectory() as tmp:
        csv = Path(tmp) / "ur5_run.csv"
        make_csv(csv, n)
        commands = {
            "armid identify": [armid, "identify", str(csv), "--robot", str(ROBOT), "--json", str(Path(tmp) / "identify.json")],
            "plain script": [sys.executable, str(ROOT / "benchmarks" / "plain_identify.py"), str(csv), str(URDF)],
        }
        times, cpus, last, load_start = interleaved(commands, repeats)
    print(f"{n} samples x 6 joints (UR5, {RATE_HZ:g} Hz, CSV), {repeats} interleaved runs each, {os.cpu_count()} cores, "
          f"load average {load_start} at the start, {load_average()} at the end")
    print_against(times, cpus, last, "armid identify", "plain script")


if __name__ == "__main__":
    args = [int(x) for x in sys.argv[1:]]
    with recorded("identify_process"):
        main(*args)

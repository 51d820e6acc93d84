"""Reading a rosbag2 bag against reading the CSV of the same data.

A UR5's JointState at 500 Hz (joints alphabetical, as its driver publishes them), written by
``rosbags`` as a bag in sqlite3 and in MCAP storage, a bag with a gripper's JointState
interleaved on the same topic (one message in three), and a CSV of the same numbers (written
here, shortest round-trip text). Each is read by ``armid.io.recordings.read_recording`` in a
process of its own (import, robot file, read), three times; the median, and the ratio to the
CSV's in the same run. The arrays read must be equal to the CSV's, bit for bit.

    python benchmarks/bench_bags.py [--seconds 600]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from figures_json import recorded

from armid.io.recordings import read_recording
from armid.io.robot_file import load_robot
from armid.resources import config_file

RATE_HZ = 500.0
READ = ("import sys, time; from armid.io.recordings import read_recording; from armid.io.robot_file import load_robot; "
        "r = load_robot(sys.argv[2]); t = time.perf_counter(); read_recording(sys.argv[1], r); print(time.perf_counter() - t)")


def joint_states(seconds: float, names: list[str], seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Stamps (ns) and positions, velocities, efforts (samples, joints) of a smooth random motion."""
    rng = np.random.default_rng(seed)
    t_ns = 1_700_000_000 * 10**9 + np.arange(int(seconds * RATE_HZ), dtype=np.int64) * int(1e9 / RATE_HZ)
    t = (t_ns - t_ns[0]) * 1e-9
    w = 2 * np.pi * rng.uniform(0.05, 0.3, len(names))
    q = 0.5 * np.sin(np.outer(t, w))
    qd = 0.5 * w * np.cos(np.outer(t, w))
    effort = 10 * np.sin(np.outer(t, w) + 0.3) + rng.normal(0, 0.05, q.shape)
    return t_ns, q, qd, effort


def write_bag(out: Path, storage: str, t_ns: np.ndarray, names: list[str], q: np.ndarray, qd: np.ndarray, effort: np.ndarray,
              gripper: bool = False) -> None:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    kind = "sensor_msgs/msg/JointState"
    msg, header, stamp = store.types[kind], store.types["std_msgs/msg/Header"], store.types["builtin_interfaces/msg/Time"]
    order = sorted(range(len(names)), key=lambda j: names[j])
    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    with Writer(out, version=9, storage_plugin=plugin) as writer:
        connection = writer.add_connection("/joint_states", kind, typestore=store)
        for k, ns in enumerate(int(x) for x in t_ns):
            h = header(stamp=stamp(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="base_link")
            m = msg(header=h, name=[names[j] for j in order], position=q[k, order], velocity=qd[k, order], effort=effort[k, order])
            writer.write(connection, ns, store.serialize_cdr(m, kind))
            if gripper and k % 3 == 0:
                g = msg(header=header(stamp=stamp(sec=ns // 10**9, nanosec=ns % 10**9 + 1000), frame_id=""), name=["finger_joint"],
                        position=np.array([0.01]), velocity=np.array([0.0]), effort=np.array([0.5]))
                writer.write(connection, ns + 1000, store.serialize_cdr(g, kind))


def write_csv(path: Path, t_ns: np.ndarray, q: np.ndarray, qd: np.ndarray, effort: np.ndarray) -> None:
    t = (t_ns // 10**9).astype(float) + 1e-9 * (t_ns % 10**9).astype(float)
    n = q.shape[1]
    header = ["t"] + [f"{p}{j + 1}" for p in ("q", "qd", "tau") for j in range(n)]
    with path.open("w") as f:
        f.write(",".join(header) + "\n")
        f.writelines(",".join(repr(float(v)) for v in row) + "\n" for row in np.column_stack([t, q, qd, effort]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=600.0, help="the recording's length at 500 Hz (default 600: 300,000 messages)")
    args = parser.parse_args()
    robot_file = config_file("robots/ur5.yaml")
    robot = load_robot(robot_file)
    names = [j.name for j in robot.joints]
    t_ns, q, qd, effort = joint_states(args.seconds, names)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        paths = {"CSV": folder / "run.csv", "bag, sqlite3": folder / "sqlite3", "bag, MCAP": folder / "mcap",
                 "bag, MCAP, a gripper's JointState interleaved": folder / "mixed"}
        start = time.perf_counter()
        write_csv(paths["CSV"], t_ns, q, qd, effort)
        write_bag(paths["bag, sqlite3"], "sqlite3", t_ns, names, q, qd, effort)
        write_bag(paths["bag, MCAP"], "mcap", t_ns, names, q, qd, effort)
        write_bag(paths["bag, MCAP, a gripper's JointState interleaved"], "mcap", t_ns, names, q, qd, effort, gripper=True)
        print(f"{t_ns.size} JointState messages of 6 joints at {RATE_HZ:g} Hz ({args.seconds:g} s), written in {time.perf_counter() - start:.1f} s")
        reference = read_recording(paths["CSV"], robot)
        for name, path in paths.items():
            rec = read_recording(path, robot)
            same = all(np.array_equal(getattr(rec, a), getattr(reference, a)) for a in ("t", "q", "qd", "tau"))
            if not same:
                raise SystemExit(f"{name}: the arrays read differ from the CSV's")
        runs: dict[str, list[float]] = {name: [] for name in paths}
        for _ in range(3):
            for name, path in paths.items():
                t0 = time.perf_counter()
                done = subprocess.run([sys.executable, "-c", READ, str(path), str(robot_file)], check=True, capture_output=True, text=True)
                runs[name].append(time.perf_counter() - t0)
                runs[name + " (read only)"] = [*runs.get(name + " (read only)", []), float(done.stdout)]
        csv, csv_read = statistics.median(runs["CSV"]), statistics.median(runs["CSV (read only)"])
        print("every file read to the CSV's arrays, bit for bit; each read in a process of its own, median of 3:")
        for name in paths:
            whole, read = statistics.median(runs[name]), statistics.median(runs[name + " (read only)"])
            size = sum(p.stat().st_size for p in (paths[name].iterdir() if paths[name].is_dir() else [paths[name]]))
            print(f"  {name}: {size / 1e6:.1f} MB, read {read:.2f} s ({read / csv_read:.2f}x the CSV's), whole process {whole:.2f} s "
                  f"({whole / csv:.2f}x)")


if __name__ == "__main__":
    with recorded("bags"):
        main()

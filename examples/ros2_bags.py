"""Write rosbag2 bags of ``sensor_msgs/msg/JointState`` with ``rosbags`` (not armid), to try
``armid identify BAG`` without an arm running ROS 2 (docs/guides/ros2.md):

    python examples/ros2_bags.py kuka ../shared/data/kuka_lwr4/measurements_1.npz kuka_bag
    python examples/ros2_bags.py ur5 ur5_bag --storage sqlite3

``kuka``: a KUKA LWR4+ recording (NPZ: ``times``, ``positions``, ``velocities``, ``torques``) as
its joint torque sensors would publish it, effort = joint torque (as a Franka publishes it).
``ur5``: a simulated UR5 (Pinocchio's RNEA on ``config/robots/ur5.urdf``, viscous and Coulomb
friction, a 5-harmonic trajectory, 250 Hz for 20 s) as UR's driver publishes it by default:
effort = motor current (the torque over each joint's ``torque_constant`` of ``ur5.yaml``).
Both publish the joints in alphabetical order, as drivers often do.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import yaml

ROBOTS = Path(__file__).resolve().parent.parent / "config" / "robots"


def write_bag(out: Path, storage: str, t_ns: np.ndarray, names: list[str], q: np.ndarray, qd: np.ndarray, effort: np.ndarray) -> None:
    """One JointState message a sample on ``/joint_states``, joints in alphabetical order."""
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
            m = msg(header=header(stamp=stamp(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=""), name=[names[j] for j in order],
                    position=q[k, order].copy(), velocity=qd[k, order].copy(), effort=effort[k, order].copy())
            writer.write(connection, ns, store.serialize_cdr(m, kind))


def kuka(npz: Path, out: Path, storage: str) -> None:
    with np.load(npz) as a:
        t_ns = np.round(a["times"] * 1e9).astype(np.int64)
        write_bag(out, storage, t_ns, [f"lwr_{j}_joint" for j in range(7)], a["positions"], a["velocities"], a["torques"])


def ur5(out: Path, storage: str, seed: int = 0, rate_hz: float = 250.0, duration_s: float = 20.0) -> None:
    import pinocchio as pin

    rng = np.random.default_rng(seed)
    doc = yaml.safe_load((ROBOTS / "ur5.yaml").read_text())
    names, kt = [j["name"] for j in doc["joints"]], np.array([j["torque_constant"] for j in doc["joints"]])
    model = pin.buildModelFromUrdf(str(ROBOTS / "ur5.urdf"))
    data = model.createData()
    t_ns = 1_700_000_000 * 10**9 + np.round(np.arange(int(duration_s * rate_hz)) * 1e9 / rate_hz).astype(np.int64)
    t, w, h = (t_ns - t_ns[0]) * 1e-9, 2 * np.pi * 0.1, np.arange(1, 6)
    a, b = rng.uniform(-1, 1, (2, 6, 5)) * 0.35 / h
    ang = w * np.outer(t, h)
    q = np.array([0.0, -1.2, 1.2, -1.5, -1.5, 0.0]) + (np.sin(ang) @ a.T - np.cos(ang) @ b.T) / w
    qd = np.cos(ang) @ a.T + np.sin(ang) @ b.T
    qdd = w * (-(np.sin(ang) * h) @ a.T + (np.cos(ang) * h) @ b.T)
    tau = np.array([pin.rnea(model, data, q[k], qd[k], qdd[k]) for k in range(t.size)])
    tau += rng.uniform(2.0, 6.0, 6) * qd + rng.uniform(1.0, 4.0, 6) * np.sign(qd)
    write_bag(out, storage, t_ns, names, q, qd, tau / kt + rng.normal(0.0, 0.01, tau.shape))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="arm", required=True)
    k = sub.add_parser("kuka", help="a KUKA LWR4+ recording (NPZ) as a bag, effort = joint torque")
    k.add_argument("npz", type=Path)
    u = sub.add_parser("ur5", help="a simulated UR5 as a bag, effort = motor current")
    for p in (k, u):
        p.add_argument("out", type=Path, help="the bag's folder (must not exist)")
        p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    args = parser.parse_args()
    if args.arm == "kuka":
        kuka(args.npz, args.out, args.storage)
    else:
        ur5(args.out, args.storage)
    print(f"{args.out}: a rosbag2 bag ({args.storage})")


if __name__ == "__main__":
    main()

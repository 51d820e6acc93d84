"""What ``--ros2`` costs the process that owns the bus: the bridge's work per message, and
``armid record --rig config/rigs/sim.yaml`` with and without ``--ros2`` (lost cycles, records,
messages at the router).

    python benchmarks/bench_ros2.py [seconds] [--busy N]

A Zenoh router on loopback (multicast scouting off) stands in for rmw_zenohd and counts the
JointState messages that reach it. Per message: the CDR of one 6-joint JointState (rosbags'
typestore) and the put with its attachment, p50/p99/max over 5,000. ``--busy N``: N processes
each keeping a core busy beside the runs.
"""

from __future__ import annotations

import json
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _router(port: int):  # type: ignore[no-untyped-def]
    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", '"router"')
    c.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    c.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(c)


def per_message(router_port: int, n: int = 5000) -> str:
    from armid.io.rmw_zenoh import Ros2Node, open_session
    from armid.io.ros2_cdr import joint_state_cdr

    ros = open_session(f"tcp/127.0.0.1:{router_port}")
    node = Ros2Node(ros, "bench", 0)
    pub = node.publisher("/armid/bench/joint_states", "sensor_msgs/msg/JointState")
    names, q = [f"joint{i}" for i in range(6)], np.zeros(6)
    enc, put = np.empty(n), np.empty(n)
    try:
        for k in range(n):
            t0 = time.perf_counter()
            data = joint_state_cdr(names, 1_700_000_000_000_000_000 + k, q, q, q)
            t1 = time.perf_counter()
            pub.put(data)
            enc[k], put[k] = t1 - t0, time.perf_counter() - t1
    finally:
        node.close()
        ros.close()
    return "; ".join(f"{name} p50 {1e6 * np.percentile(v, 50):.1f} us, p99 {1e6 * np.percentile(v, 99):.1f} us, max {1e6 * v.max():.0f} us"
                     for name, v in (("CDR", enc), ("put", put)))


def record(router, router_port: int, seconds: float, ros2: bool) -> str:  # type: ignore[no-untyped-def]
    got = []
    sub = router.declare_subscriber("0/armid/puma560/joint_states/**", lambda s: got.append(1))
    try:
        extra = ["--ros2", "--ros2-router", f"tcp/127.0.0.1:{router_port}"] if ros2 else []
        with __import__("tempfile").TemporaryDirectory() as out:
            r = subprocess.run([sys.executable, "-m", "armid.cli", "record", "--rig", str(ROOT / "config/rigs/sim.yaml"), "--duration",
                                str(seconds), "--out", out, "--zenoh-listen", f"tcp/127.0.0.1:{_free_port()}", *extra],
                               capture_output=True, text=True, cwd=ROOT)
        time.sleep(0.5)
    finally:
        sub.undeclare()
    line = next((m.group(0) for m in (re.search(r"\d+ records, .*", x) for x in r.stderr.splitlines()) if m), r.stderr[-300:])
    return f"{'--ros2   ' if ros2 else 'no --ros2'}: exit {r.returncode}; {line}; JointState at the router {len(got)}"


def main(args: list[str]) -> None:
    from busy import busy_loops

    busy = int(args[args.index("--busy") + 1]) if "--busy" in args else 0
    if "--busy" in args:
        del args[args.index("--busy"): args.index("--busy") + 2]
    seconds = float(args[0]) if args else 5.0
    port = _free_port()
    router = _router(port)
    try:
        with busy_loops(busy):
            print(f"per message: {per_message(port)}" + (f"; beside {busy} busy processes" if busy else ""), flush=True)
            for ros2 in (False, True, False, True):
                print(record(router, port, seconds, ros2) + (f"; beside {busy} busy processes" if busy else ""), flush=True)
    finally:
        router.close()


if __name__ == "__main__":
    main(sys.argv[1:])

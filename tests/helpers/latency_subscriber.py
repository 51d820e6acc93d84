"""A subscriber in its own process: the latency of each joint_state record.

    python latency_subscriber.py ROBOT LISTEN_ENDPOINT OUT_FILE SECONDS

Writes "sequence latency_s" per record (receive wall time minus the record's SYNC time).
"""

import signal
import sys
import threading
import time

import zenoh

from armid.daq.stream import key, session_config
from armid.schema.joint_states import JointStates

robot, endpoint, out, seconds = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
rows: list[tuple[int, float]] = []
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())


def on_sample(sample) -> None:  # type: ignore[no-untyped-def]
    now = time.time()
    r = JointStates.unpack(sample.payload.to_bytes())
    rows.extend(zip(r.sequence.tolist(), (now - r.time).tolist()))


with zenoh.open(session_config(listen=[endpoint])) as session:
    sub = session.declare_subscriber(key(robot, "joint_state"), on_sample)
    print("ready", flush=True)
    stop.wait(seconds)
    sub.undeclare()
with open(out, "w") as f:
    f.write("\n".join(f"{s} {lat:.6f}" for s, lat in rows))

"""A subscriber in its own process: collects sequence numbers of armid/<robot>/joint_state.

    python zenoh_subscriber.py ROBOT LISTEN_ENDPOINT OUT_FILE SECONDS [SLEEP_PER_SAMPLE]

Writes one sequence number per line to OUT_FILE when it stops (after SECONDS or on SIGTERM).
"""

import signal
import sys
import threading
import time

import zenoh

from armid.daq.stream import key, session_config
from armid.schema.joint_state import check_encoding
from armid.schema.joint_states import JointStates

robot, endpoint, out, seconds = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
slow = float(sys.argv[5]) if len(sys.argv) > 5 else 0.0
seqs: list[int] = []
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())


def on_sample(sample) -> None:  # type: ignore[no-untyped-def]
    check_encoding(str(sample.encoding))
    seqs.extend(JointStates.unpack(sample.payload.to_bytes()).sequence.tolist())
    if slow:
        time.sleep(slow)


with zenoh.open(session_config(listen=[endpoint])) as session:
    sub = session.declare_subscriber(key(robot, "joint_state"), on_sample)
    print("ready", flush=True)
    stop.wait(seconds)
    sub.undeclare()
with open(out, "w") as f:
    f.write("\n".join(str(s) for s in seqs))

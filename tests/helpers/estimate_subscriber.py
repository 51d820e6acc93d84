"""A subscriber in its own process: collects armid/<robot>/estimate/payload documents.

    python estimate_subscriber.py ROBOT LISTEN_ENDPOINT OUT_FILE SECONDS

Writes one JSON document per line to OUT_FILE when it stops (after SECONDS or on SIGTERM).
"""

import json
import signal
import sys
import threading

import zenoh

from armid.daq.stream import key, session_config

robot, endpoint, out, seconds = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
docs: list[dict] = []
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())

with zenoh.open(session_config(listen=[endpoint])) as session:
    sub = session.declare_subscriber(key(robot, "estimate/payload"), lambda s: docs.append(json.loads(s.payload.to_bytes())))
    print("ready", flush=True)
    stop.wait(seconds)
    sub.undeclare()
with open(out, "w") as f:
    f.write("\n".join(json.dumps(d) for d in docs))

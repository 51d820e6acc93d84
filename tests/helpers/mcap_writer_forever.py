"""Write synthetic 6-joint records to an MCAP file at 500 Hz until killed; print progress."""

import sys
import time

import numpy as np

from armid.daq.recorder import McapRecorder
from armid.drivers.interface import Sample
from armid.schema.joint_states import JointStates

rec = McapRecorder(sys.argv[1], [f"j{k + 1}" for k in range(6)], {"robot": "synthetic"})
k = 0
next_t = time.perf_counter()
while True:
    t = k * 0.002
    s = Sample(k, t, np.ones(6, bool), np.sin(t + np.arange(6)), np.cos(t + np.arange(6)), np.ones(6, bool),
               np.zeros(6), 0.1 * np.sin(t) * np.ones(6), np.full(6, 0x27), 0.1 * np.sin(t) * np.ones(6))
    rec.write(JointStates.of_sample(k, s))
    k += 1
    if k % 100 == 0:
        print(k, flush=True)
    next_t += 0.002
    time.sleep(max(0.0, next_t - time.perf_counter()))

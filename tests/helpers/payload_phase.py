"""Run the demo's payload phase in a fresh process: ``payload_phase.py ARM_AND_TRAJECTORY.pkl OUT``.

The test gives this process (and so the estimator's, ``armid estimate live``, which it
starts) an empty numba cache; it prints the phase's result as JSON.
"""

from __future__ import annotations

import json
import pickle
import sys
import uuid
from contextlib import closing
from pathlib import Path

from armid.demo import DEFAULT_RIG, payload_estimator, run_payload
from armid.identify.payload.rls import identification_document
from armid.io.rig_file import load_rig


def main() -> None:
    with open(sys.argv[1], "rb") as f:
        arm, trajectory = pickle.load(f)
    out = Path(sys.argv[2])
    rig = load_rig(DEFAULT_RIG).with_bus(channel=f"armid-phase-{uuid.uuid4().hex[:8]}")
    with closing(payload_estimator(rig, identification_document(arm), out)) as estimator:
        result = run_payload(rig, estimator, trajectory, out)
    result.pop("report", None)
    print(json.dumps(result))


if __name__ == "__main__":
    main()

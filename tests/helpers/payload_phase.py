"""Run the demo's payload phase in a fresh process: ``payload_phase.py ARM_AND_TRAJECTORY.pkl OUT (warm|cold)``.

The test gives this process an empty numba cache, so nothing is compiled before the phase
starts; it prints the phase's result as JSON, with the numba kernels compiled during it.
"""

from __future__ import annotations

import json
import pickle
import sys
import uuid
from pathlib import Path

from armid.demo import DEFAULT_RIG, run_payload
from armid.io.rig_file import load_rig


def main() -> None:
    with open(sys.argv[1], "rb") as f:
        arm, trajectory = pickle.load(f)
    out = Path(sys.argv[2])
    rig = load_rig(DEFAULT_RIG).with_bus(channel=f"armid-phase-{uuid.uuid4().hex[:8]}")
    result = run_payload(rig, arm, trajectory, out, None, warm=sys.argv[3] == "warm")
    from armid.identify import _regressor_lanes

    result["regressor_kernel_compiled"] = bool(_regressor_lanes.regressor_kernel.signatures)
    result.pop("report", None)
    print(json.dumps(result))


if __name__ == "__main__":
    main()

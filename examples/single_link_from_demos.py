"""``armid identify --single-link`` on demos' recordings, against the simulator's truth.

For each ``armid demo`` output folder given, the six single-link recordings
(``runs/link*/run.mcap``, cut to their excitation windows by ``runs.json`` as the command cuts
them) go through Khosla's sequence as the command runs it, with each preparation recipe
(``identify``, the command's default: the low-pass chosen from the spectrum; ``drives``: the
demo's own), and each combination is compared with the truth of that demo's arm seed. Prints a
line per demo beside the demo's own truth check, then the z RMS and counts over all of them.

    python examples/single_link_from_demos.py REPORT_DIR [REPORT_DIR ...]
"""

from __future__ import annotations

import json
import sys
import warnings
from dataclasses import replace

import numpy as np

from armid.commands.identify import _single_joint_run
from armid.demo import DEFAULT_RIG, true_parameters
from armid.identify.preprocess import prepare
from armid.identify.single_link import single_link_sequence
from armid.io.rig_file import load_rig
from armid.pipeline import RECIPES


def z_scores(folder: str, recipe_name: str) -> np.ndarray:
    """The sequence's (estimate - truth) / std on one demo's recordings, prepared by one recipe."""
    base = load_rig(DEFAULT_RIG)
    doc = json.loads(open(f"{folder}/demo.json").read())
    rig = replace(base, simulation={**base.simulation, "seed": doc["arm_seed"]})
    runs: dict[int, list] = {}  # type: ignore[type-arg]
    for k in range(6, 0, -1):
        rec, link = _single_joint_run(f"{folder}/runs/link{k}/run.mcap", rig.robot)
        runs.setdefault(link, []).append(prepare(rec, rig.robot, RECIPES[recipe_name].prepare))
    seq = single_link_sequence(rig.robot, runs)
    phi = true_parameters(rig, seq.names)
    return np.asarray((seq.beta - np.array([f.row @ phi for f in seq.functionals])) / seq.std)


def main(folders: list[str]) -> None:
    warnings.simplefilter("ignore")
    every: dict[str, list[np.ndarray]] = {name: [] for name in RECIPES}
    for folder in folders:
        line = [folder]
        for name in RECIPES:
            z = z_scores(folder, name)
            every[name].append(z)
            line.append(f"{name}: {int((np.abs(z) < 3).sum())}/{z.size} max {np.abs(z).max():.2f}")
        demo = json.loads(open(f"{folder}/demo.json").read())["truth_check"]["single_link"]
        print(" | ".join(line + [f"the demo: {demo['within_3_sigma']}/{demo['combinations']} max {demo['max_abs_z']:.2f}"]), flush=True)
    for name, zs in every.items():
        z = np.concatenate(zs)
        print(f"{name}: z RMS {np.sqrt(np.mean(z**2)):.3f} over {len(zs)} demos; all within 3 sigma in {sum(bool((np.abs(v) < 3).all()) for v in zs)}; "
              f"beyond 3 sigma {int((np.abs(z) > 3).sum())} (expected {0.0027 * z.size:.1f})")


if __name__ == "__main__":
    main(sys.argv[1:])

"""The demo's six single-link runs on the bus, each time on a fresh simulated arm: how far each
combination of Khosla's sequence falls from the truth, in its reported standard deviations.

The demo's designs (seed 0), run through the CANopen driver on the virtual bus as ``armid demo``
runs them, each draw with its own arm seed (the drives' current noise), then the sequence on the
recordings. Per combination over the draws: the mean z (0 when unbiased; its own error is about
1/sqrt(draws)) and the z's spread (1 when its sigma is right); overall the z RMS and the share of
draws with all 28 within 3 sigma (92.7 % when every sigma is right and the estimates
independent). About 40 s a draw on a 2-core machine (docs/methods.md: 25 draws).

    python examples/single_link_on_the_bus.py 25
"""

from __future__ import annotations

import secrets
import sys
import tempfile
import uuid
from dataclasses import replace
from pathlib import Path

import numpy as np

from armid.demo import DEFAULT_RIG, true_parameters
from armid.experiments import Experiment, design_experiments, prepared_runs, run_experiments
from armid.identify.single_link import single_link_sequence
from armid.io.rig_file import load_rig
from armid.simulated import excitation_session


def draw(experiments: list[Experiment], out: Path) -> tuple[list[str], np.ndarray] | None:
    """One fresh arm: the six runs on the bus and the sequence's z; None if a run stopped."""
    rig = load_rig(DEFAULT_RIG).with_bus(channel=f"armid-draw-{uuid.uuid4().hex[:8]}")
    rig = replace(rig, simulation={**rig.simulation, "seed": secrets.randbits(31)})
    with excitation_session(rig, simulate=True) as session:
        reports = run_experiments(session, experiments, out)
    if not all(r.completed for r in reports):
        print(f"a run stopped: {next(r.stop_reason for r in reports if not r.completed)}", flush=True)
        return None
    prepared = prepared_runs(reports, rig.robot, rig.period_s)
    seq = single_link_sequence(rig.robot, {e.link: [prepared[e.name]] for e in experiments})
    truth = np.array([fn.row @ true_parameters(rig, seq.names) for fn in seq.functionals])
    return [f"link {fn.link + 1}: {fn.expression}" for fn in seq.functionals], (seq.beta - truth) / seq.std


def main(draws: int) -> None:
    rig = load_rig(DEFAULT_RIG)
    start = np.asarray(rig.simulation["initial_position"], float)
    experiments = design_experiments(rig.robot, start, list(range(rig.n_joints - 1, -1, -1)), [], rig.period_s, seed=0)
    zs: list[np.ndarray] = []
    names: list[str] = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(draws):
            got = draw(experiments, Path(tmp) / str(k))
            if got is not None:
                names, z = got
                zs.append(z)
                print(f"draw {k + 1}: z rms {np.sqrt(np.mean(z**2)):.3f}, largest |z| {np.abs(z).max():.2f}", flush=True)
    z_all = np.array(zs)
    n = len(z_all)
    for name, column in zip(names, z_all.T):
        print(f"{name[:60]:60s} mean z {column.mean():+.2f} +- {column.std(ddof=1) / np.sqrt(n):.2f}, spread {column.std(ddof=1):.2f}")
    print(f"{n} draws: z rms {np.sqrt(np.mean(z_all**2)):.3f}; {int((np.abs(z_all) > 3).sum())} beyond 3 sigma "
          f"({0.0027 * z_all.size:.1f} expected); all within 3 sigma in {np.mean((np.abs(z_all) < 3).all(axis=1)):.0%} of draws")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 10)

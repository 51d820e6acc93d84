"""How far the identified combinations fall from the truth, in their reported standard
deviations, on the simulated PUMA 560 off the bus (the designs of tests/test_excitation.py).

    python examples/z_scores.py 1 3 5 7
    python examples/z_scores.py $(seq 100 159)     (the calibration over 60 draws: 10 minutes)

Per seed: Khosla's single-link sequence (links 6..1) and a whole-arm run validated on a
second one; prints the z rms, the largest |z| and every |z| beyond 2.5 with its expression.
Over several seeds, per part: the mean of z^2 (1 when each sigma is right), the share of seeds
with every z within 3 (0.9973^n when right), the chi-square of the whole error vector per degree
of freedom, and each combination whose mean z over the seeds is beyond 2.5 of its own error.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from armid.demo import true_parameters  # noqa: E402
from armid.identify import excitation as ex  # noqa: E402
from armid.identify.identification import IdentifyOptions, identify  # noqa: E402
from armid.identify.preprocess import PrepareOptions, prepare  # noqa: E402
from armid.identify.single_link import single_link_sequence  # noqa: E402
from armid.io.recordings import Recording  # noqa: E402
from armid.io.rig_file import load_rig  # noqa: E402
from armid.sim_bus.offline import simulate  # noqa: E402
from armid.sim_bus.physics import simulation_config  # noqa: E402

RIG = ROOT / "config" / "rigs" / "sim.yaml"
HOLD = np.array([0.0, 0.7854, -0.7854, 0.0, 0.0, 0.0])


def z_scores(seed: int) -> tuple[list[str], np.ndarray, dict[str, float]]:
    rig = load_rig(RIG)
    robot = rig.robot
    cfg = simulation_config(rig.simulation, robot.n_joints)
    limits = ex.Limits.of(robot)
    options = PrepareOptions(lowpass_hz=None, torque_hold=True)

    def run(design: ex.Design, periods: int, sim_seed: int):  # type: ignore[no-untyped-def]
        plan = ex.plan(design, HOLD, limits, periods=periods)
        r = simulate(robot, cfg, plan.evaluate, plan.duration_s, seed=sim_seed)
        t0, t1 = plan.excitation_window
        keep = (r.t >= t0) & (r.t <= t1)
        return prepare(Recording("sim", r.t[keep], r.position[keep], r.torque[keep], r.velocity[keep]), robot, options)

    experiments = {}
    for k in range(robot.n_joints - 1, -1, -1):
        hold = ex.choose_hold(robot, k, HOLD, seed=seed + k)
        experiments[k] = [run(ex.design(robot, moving=(k,), q_hold=hold, base_frequency_hz=0.5, seed=seed + k), 3, 100 * seed + k)]
    seq = single_link_sequence(robot, experiments)
    truth = np.array([fn.row @ true_parameters(rig, seq.names) for fn in seq.functionals])
    whole_runs = [run(ex.design(robot, base_frequency_hz=0.2, seed=seed + 50 + i, margin=0.6), 2 - i, 100 * seed + 50 + i) for i in range(2)]
    whole = identify(robot, [whole_runs[0]], [whole_runs[1]], IdentifyOptions(exclude_reversals=True))
    z_whole = (whole.estimate.beta - whole.base.base_values(true_parameters(rig, whole.names))) / whole.estimate.std
    e_whole = whole.estimate.beta - whole.base.base_values(true_parameters(rig, whole.names))
    chi2 = {"single-link": float((seq.beta - truth) @ np.linalg.pinv(seq.covariance) @ (seq.beta - truth)) / truth.size,
            "whole-arm": float(e_whole @ np.linalg.pinv(whole.estimate.covariance) @ e_whole) / e_whole.size}
    m, p = whole.covariance_batches, e_whole.size
    if m is not None and m > p + 1:  # the covariance from m batch means: Hotelling's F per degree of freedom (armid.demo._truth_test)
        chi2["whole-arm, Hotelling F"] = chi2["whole-arm"] * (m - p) / (m - 1)
    names = [f"single-link {fn.expression}" for fn in seq.functionals] + [f"whole-arm {e}" for e in whole.base.expressions()]
    return names, np.concatenate([(seq.beta - truth) / seq.std, z_whole]), chi2


def summary(names: list[str], zs: np.ndarray, chi2: list[dict[str, float]]) -> None:
    """Over the seeds (rows of ``zs``): how right the sigmas are, part by part."""
    n = zs.shape[0]
    for part in ("single-link", "whole-arm"):
        cols = [k for k, name in enumerate(names) if name.startswith(part)]
        z = zs[:, cols]
        print(f"{part}: {len(cols)} combinations over {n} seeds: mean z^2 {np.mean(z**2):.2f}, every z within 3 in "
              f"{np.mean(np.all(np.abs(z) <= 3, axis=1)):.0%} of seeds (right sigmas: {0.9973 ** len(cols):.0%}), "
              f"chi-square per dof {np.mean([c[part] for c in chi2]):.2f}"
              + (f", Hotelling's F per dof {np.mean([c[part + ', Hotelling F'] for c in chi2 if part + ', Hotelling F' in c]):.2f}"
                 if any(part + ", Hotelling F" in c for c in chi2) else ""))
        for k in cols:
            if abs(zs[:, k].mean()) > 2.5 / np.sqrt(n):
                print(f"    mean z {zs[:, k].mean():+.2f} (+-{1 / np.sqrt(n):.2f})  {names[k][:100]}")


def main() -> None:
    rows, chi2 = [], []
    names: list[str] = []
    for seed in [int(s) for s in sys.argv[1:]] or [0]:
        names, z, c = z_scores(seed)
        rows.append(z)
        chi2.append(c)
        print(f"seed {seed}: {z.size} estimates, z rms {np.sqrt(np.mean(z**2)):.2f}, max |z| {np.abs(z).max():.2f}, "
              f"beyond 3 sigma {int((np.abs(z) > 3).sum())}", flush=True)
        for name, zz in zip(names, z):
            if abs(zz) > 2.5:
                print(f"    {zz:+.2f}  {name[:100]}")
    if len(rows) > 1 and len({z.size for z in rows}) == 1:
        summary(names, np.array(rows), chi2)


if __name__ == "__main__":
    main()

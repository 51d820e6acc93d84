"""What Khosla's single-link sequence needs from the KUKA LWR4+, and what it would give.

The shared KUKA recordings move all seven joints at once (not one sample of 15,081 has one
joint moving alone), so ``armid identify --single-link`` refuses them, naming the joints that
moved. This script designs the seven single-joint runs the sequence needs (joint 7 first,
each joint alone with the joints before it at the pose that identifies the most of its link,
:func:`~armid.identify.excitation.choose_hold`), simulates them on the KUKA's model (the
URDF's CAD inertials as the truth, friction and current noise as on the simulated rig), and runs the
sequence: how many combinations it identifies per link, how many of the 64 whole-arm base
parameters are among them, and how far each lies from the truth in its standard deviations.

    python examples/kuka_single_link.py [SEED]
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from armid.demo import true_parameters
from armid.identify import excitation as ex
from armid.identify.identification import IdentifyOptions, identify
from armid.identify.preprocess import PrepareOptions, prepare
from armid.identify.single_link import single_link_sequence
from armid.io.recordings import Recording
from armid.io.rig_file import load_rig
from armid.io.robot_file import load_robot
from armid.sim_bus.offline import simulate
from armid.sim_bus.physics import simulation_config

ROOT = Path(__file__).resolve().parent.parent
KUKA = load_robot(ROOT / "config" / "robots" / "kuka_lwr4.yaml")
HOLD = np.zeros(KUKA.n_joints)
SIMULATION = {"current_noise_a": 0.005, "current_time_constant_s": 0.0002, "substeps": 2,
              "effects": [{"joint": "all", "viscous": 0.5, "coulomb": 0.8}]}
"""The simulated rig's noise and friction; no rotor inertia: the LWR's sensors measure the torque after the gear."""


def _run(robot, cfg, d, start, seed: int):  # type: ignore[no-untyped-def]
    """One simulated run of design ``d`` from ``start``, cut to its excitation window and prepared."""
    p = ex.plan(d, start, ex.Limits.of(robot), periods=3)
    run = simulate(robot, cfg, p.evaluate, p.duration_s, seed=seed)
    t0, t1 = p.excitation_window
    keep = (run.t >= t0) & (run.t <= t1)
    rec = Recording("sim", run.t[keep], run.position[keep], run.torque[keep], run.velocity[keep])
    return prepare(rec, robot, PrepareOptions(lowpass_hz=None, torque_hold=True))


def main(seed: int) -> None:
    rig = replace(load_rig(ROOT / "config" / "rigs" / "sim.yaml"), robot=KUKA, simulation=SIMULATION)
    cfg = simulation_config(rig.simulation, KUKA.n_joints)
    runs = {}
    for k in range(KUKA.n_joints - 1, -1, -1):
        hold = ex.choose_hold(KUKA, k, HOLD, seed=seed + k)
        d = ex.design(KUKA, moving=(k,), q_hold=hold, base_frequency_hz=0.5, seed=seed + k)
        runs[k] = [_run(KUKA, cfg, d, hold, 100 * seed + k)]
        print(f"joint {k + 1}: held the joints before it at {np.round(hold[:k], 2).tolist()} rad")
    seq = single_link_sequence(KUKA, runs)
    truth = np.array([fn.row for fn in seq.functionals]) @ true_parameters(rig, seq.names)
    z = (seq.beta - truth) / seq.std
    for fn, zz, b, s, tr in zip(seq.functionals, z, seq.beta, seq.std, truth):
        if abs(zz) > 3:
            print(f"  beyond 3 sigma: link {fn.link + 1} {fn.expression}: {b:.5g} +- {s:.2g} against {tr:.5g} (z = {zz:.2f})")
    whole_design = ex.design(KUKA, base_frequency_hz=0.2, seed=seed + 50, margin=0.6)
    whole = identify(KUKA, [_run(KUKA, cfg, whole_design, HOLD, 100 * seed + 50)], None, IdentifyOptions(exclude_reversals=True))
    shared = [c for c in seq.compare(whole) if c["single_link"] is not None]
    for step in seq.steps:
        print(f"link {step['link']}: {step['identified']} combinations")
    print(f"single-link sequence: {len(seq.functionals)} combinations identified; {len(shared)} of the whole-arm model's "
          f"{whole.base.n_base} base parameters among them; max |z| against the truth {np.abs(z).max():.2f}, "
          f"{int((np.abs(z) > 3).sum())} beyond 3 sigma")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 0)

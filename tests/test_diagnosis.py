"""Diagnosis on data from the simulated arm with one undeclared effect on a random joint."""

from __future__ import annotations

import dataclasses
import os
import zlib
from pathlib import Path

import numpy as np
import pytest

from armid.identify.diagnosis.search import diagnose
from armid.identify.preprocess import PrepareOptions, prepare
from armid.identify.robot import DeclaredEffect, Robot
from armid.identify.trajectories import random_fourier_trajectory
from armid.io.robot_file import load_robot
from armid.sim_bus.offline import simulate
from armid.sim_bus.physics import JointEffects, SimulationConfig

ROOT = Path(__file__).resolve().parent.parent
PUMA = load_robot(ROOT / "config" / "robots" / "puma560.yaml")
LIMIT = np.array([j.limits.torque for j in PUMA.joints])
ROTOR = [0.78, 2.32, 0.58, 0.19, 0.17, 0.19]  # Corke's motor inertia times gear ratio squared
BASE = {"viscous": ("viscous_friction", 0.01 * LIMIT), "coulomb": ("coulomb_friction", 0.015 * LIMIT), "rotor_inertia": ("rotor_inertia", np.array(ROTOR))}


def _run(seed: int, undeclared: dict[str, float] | None = None, joint: int | None = None, tilt: tuple[float, float] = (0.0, 0.0)):  # type: ignore[no-untyped-def]
    """Identification and validation runs of the simulated PUMA; the robot file declares
    viscous and Coulomb friction and rotor inertia, except what ``undeclared`` adds."""
    undeclared = undeclared or {}
    effects = [{k: float(v[j]) for k, (_, v) in BASE.items()} for j in range(6)]
    declared = []
    for key, (name, _) in BASE.items():
        for j in range(6):
            if not (key in undeclared and j == joint):
                declared.append(DeclaredEffect(name, j + 1, {}))
    if joint is not None:
        effects[joint].update(undeclared)
    robot: Robot = dataclasses.replace(PUMA, effects=tuple(declared))
    config = SimulationConfig(joints=tuple(JointEffects(**e) for e in effects), current_noise_a=0.005,
                              current_time_constant_s=0.0002, substeps=2, gravity_tilt_rad=tilt)
    prepared = []
    for k, duration in ((0, 16.0), (1, 8.0)):
        traj = random_fourier_trajectory(robot, harmonics=5, base_frequency_hz=0.125, fill=0.5, seed=1000 * seed + k)
        run = simulate(robot, config, traj.evaluate, duration, seed=1000 * seed + k)
        prepared.append(prepare(run.recording(), robot, PrepareOptions(lowpass_hz=20.0, torque_hold=True)))
    return diagnose(robot, [prepared[0]], [prepared[1]])


def _assert_found(d, effect: str, joint: int | None) -> None:  # type: ignore[no-untyped-def]
    names = [(f.effect, f.joint) for f in d.found]
    # named either as found, or as the look-alike the data cannot tell apart from what was found
    named = names + [(f.lookalike, f.joint) for f in d.found if f.lookalike]
    assert (effect, joint) in named, f"expected {effect} on joint {joint}, found {names}; rounds {d.rounds[:2]}"
    # on the equations the search scores (filtered, joints clear of rest), as before the
    # raw-stamp errors existed; those include the raw current noise that no model removes
    before, after = d.before["moving_equations"]["relative_error"], d.after["moving_equations"]["relative_error"]
    assert after <= 0.5 * before, (before, after)


CASES = {
    "viscous_friction": lambda rng: ({"viscous": 1.5}, None),
    "coulomb_friction": lambda rng: ({"coulomb": 1.5}, None),
    "stribeck_friction": lambda rng: ({"stribeck": 3.0, "stribeck_velocity": float(rng.uniform(0.15, 0.3))}, None),
    "torque_offset": lambda rng: ({"offset": float(rng.choice([-1.0, 1.0]))}, None),
    "time_delay": lambda rng: ({"delay_s": float(rng.uniform(0.015, 0.025))}, None),
    "cogging": lambda rng: ({"cogging": 0.8, "cogging_period": float(2 * np.pi / rng.integers(8, 30)), "cogging_phase": float(rng.uniform(0, 6))}, None),
    "spring": lambda rng: ({"spring": 20.0, "spring_rest": float(rng.uniform(-0.5, 0.5))}, None),
    # a torque-constant error shows where the rigid body carries the torque: joints 1-3 of the PUMA
    "torque_gain": lambda rng: ({"torque_gain": float(rng.choice([0.75, 1.3]))}, int(rng.integers(0, 3))),
    # joint 1's rotor inertia is absorbed (vertical axis): its own test below
    "rotor_inertia": lambda rng: ({"rotor_inertia": 0.0}, int(rng.integers(1, 6))),
}


# every effect with ARMID_BLIND_FULL=1; CI runs the four whose path the blind sweep does not
# take on this simulator (a delay's refinement, a drive gain, cogging, a spring), to keep its
# run under 15 minutes on two cores: tests/test_blind_diagnosis.py names every effect on data
# armid did not make
FULL = os.environ.get("ARMID_BLIND_FULL") == "1"
EFFECTS = sorted(CASES) if FULL else ["cogging", "spring", "time_delay", "torque_gain"]


@pytest.mark.parametrize("effect", EFFECTS)
def test_undeclared_effect_on_a_random_joint_is_found(effect: str) -> None:
    rng = np.random.default_rng(zlib.crc32(effect.encode()))
    undeclared, joint = CASES[effect](rng)
    joint = int(rng.integers(0, 6)) if joint is None else joint
    if effect == "rotor_inertia":
        undeclared = {"rotor_inertia": ROTOR[joint] + 0.5}
    d = _run(seed=int(rng.integers(0, 1000)), undeclared=undeclared, joint=joint)
    _assert_found(d, effect, joint)


def test_gravity_tilt_is_found_for_the_arm() -> None:
    d = _run(seed=3, tilt=(0.03, -0.02))
    _assert_found(d, "gravity_tilt", None)
    f = next(f for f in d.found if f.effect == "gravity_tilt")
    assert f.parameters["tilt_x_rad"] == pytest.approx(0.03, abs=0.005)
    assert f.parameters["tilt_y_rad"] == pytest.approx(-0.02, abs=0.005)


def test_rotor_inertia_of_the_vertical_first_joint_is_absorbed_not_found() -> None:
    d = _run(seed=5, undeclared={"rotor_inertia": ROTOR[0] + 0.5}, joint=0)
    assert ("rotor_inertia", 0) not in [(f.effect, f.joint) for f in d.found]
    absorbed = [a for a in d.absorbed if a["effect"] == "rotor_inertia" and a["joint"] == 1]
    assert absorbed and "Iyy1" in absorbed[0]["into"]


# all ten seeds with ARMID_BLIND_FULL=1 (as the blind sweep); CI runs three, to keep its run
# under 15 minutes on two cores (each diagnosis also searches the Coulomb smoothing twice)
CLEAN_SEEDS = range(10) if FULL else range(3)


@pytest.mark.parametrize("seed", CLEAN_SEEDS)
def test_nothing_is_found_without_an_undeclared_effect(seed: int) -> None:
    d = _run(seed=seed)
    assert d.found == [], [f.sentence() for f in d.found]


def test_armid_diagnose_cli_writes_json_report_and_predictions(tmp_path: Path) -> None:
    """The command on the shipped example: JSON as INTERFACES.md says, a report, predictions."""
    import json
    import subprocess
    import sys

    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "armid.cli", "diagnose", str(ROOT / "examples/puma560_excitation.csv"), "--robot",
         str(ROOT / "config/robots/puma560.yaml"), "--validate", str(ROOT / "examples/puma560_validation.csv"),
         "--json", str(out / "d.json"), "--report", str(out), "--predictions", str(out / "p.csv")],
        cwd=ROOT, capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((out / "d.json").read_text())
    assert set(doc) >= {"found", "before", "after"}
    assert set(doc["before"]) >= {"relative_error", "rms", "relative"}
    assert (out / "diagnosis.md").exists() and (out / "diagnosis_joint1.png").exists()
    header = (out / "p.csv").read_text().splitlines()[0]
    assert header.split(",")[:2] == ["t", "tau_hat1"]
    missing = subprocess.run([sys.executable, "-m", "armid.cli", "diagnose", str(tmp_path / "nope.csv"), "--robot",
                              str(ROOT / "config/robots/puma560.yaml"), "--validate", str(tmp_path / "nope.csv")],
                             cwd=ROOT, capture_output=True, text=True)
    assert missing.returncode == 2 and "nope.csv" in missing.stderr and len(missing.stderr.strip().splitlines()) == 1


def test_after_is_identify_with_the_findings_declared() -> None:
    """The 'after' model is `identify` on the declared model plus the findings (findings_model):
    a lab that declares what diagnose found gets the same predictions, sample for sample."""
    import warnings

    from armid.identify.diagnosis.search import findings_model
    from armid.identify.identification import identify

    rng = np.random.default_rng(7)
    undeclared, _ = CASES["cogging"](rng)
    robot: Robot = dataclasses.replace(PUMA, effects=tuple(DeclaredEffect(name, j + 1, {}) for _, (name, _) in BASE.items() for j in range(6)))
    config = SimulationConfig(joints=tuple(JointEffects(**({k: float(v[j]) for k, (_, v) in BASE.items()} | (undeclared if j == 2 else {})))
                                           for j in range(6)), current_noise_a=0.005, current_time_constant_s=0.0002, substeps=2)
    prepared = []
    for k, duration in ((0, 16.0), (1, 8.0)):
        traj = random_fourier_trajectory(robot, harmonics=5, base_frequency_hz=0.125, fill=0.5, seed=77 + k)
        run = simulate(robot, config, traj.evaluate, duration, seed=77 + k)
        prepared.append(prepare(run.recording(), robot, PrepareOptions(lowpass_hz=20.0, torque_hold=True)))
    d = diagnose(robot, [prepared[0]], [prepared[1]])
    _assert_found(d, "cogging", 2)
    model, options = findings_model(robot, d.found)
    assert ("cogging", 3) in {(e.effect, e.joint) for e in model.effects}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = identify(model, [prepared[0]], [prepared[1]], options)
    _, _, tau_hat = result.predict_stamps([s for s in prepared[1].segments])
    assert d.predictions is not None
    np.testing.assert_allclose(tau_hat, d.predictions[2], rtol=0, atol=1e-9 * float(np.abs(tau_hat).max()))
    assert result.validation is not None and result.validation["relative_error"] == pytest.approx(d.after["relative_error"], rel=1e-12)

"""Load-dependent Coulomb friction declared in the robot file
(``{effect: load_dependent_coulomb, joint: J}``, issue 15: friction growing with the joint's
load torque, ``(fc + fl |tau_load|) sign(qd)``), fitted by `armid identify` on data armid did
not make (tests/blindgen.py: Pinocchio RNEA along analytic trajectories, no armid code).

- ``fc`` and ``fl`` come back within 5 % of the generator's, and the held-out error of
  `--predictions` against the raw torque falls to within 10 % of the noise floor, from
  above it with Coulomb friction alone declared.
- The column's load is the model's own rigid-body torque, at every sample (against
  Pinocchio's RNEA); the payload estimator's arm model carries the same load, with or without
  modeled inertial values in the robot file.
- A robot file without inertial values: the diagnosis still names it.
"""

from __future__ import annotations

import json
from pathlib import Path

import blindgen
import numpy as np
import pytest
from conftest import ROBOTS, declare, identify_blind

from armid.cli import main
from armid.identify.effects import load_friction
from armid.identify.identification import declared_effects, stacked_regressor
from armid.identify.payload.rls import arm_model_from_identification
from armid.io.robot_file import load_robot
from armid.schema.errors import RobotFileError

SPECS = {s["seed"]: s for s in blindgen.blind_specs("effects", 5, seed0=100, effects=["load_coulomb"])}


@pytest.mark.parametrize("seed", sorted(SPECS))
def test_a_declared_load_dependent_friction_is_fitted_to_the_noise_floor(tmp_path: Path, seed: int) -> None:
    case = blindgen.make_case(out_dir=tmp_path / "case", **SPECS[seed])
    truth = json.loads((tmp_path / "case" / "truth.json").read_text())["effect"]["params"]
    joint = case.effect_joint
    coulomb = {"effect": "coulomb_friction", "joint": joint}
    before, _ = identify_blind(case, declare(case.robot_yaml, tmp_path / "coulomb.yaml", [coulomb]), tmp_path / "without")
    after, report = identify_blind(case, declare(case.robot_yaml, tmp_path / "load.yaml", [coulomb, {"effect": "load_dependent_coulomb", "joint": joint}]),
                              tmp_path / "with")
    got = {e["effect"]: e for e in report["effects"] if e["joint"] == joint}
    fc, fl = got["coulomb_friction"]["parameters"]["fc"], got["load_dependent_coulomb"]["parameters"]["fl"]
    print(f"\nseed {seed}: joint {joint} fc {fc:.4g} (truth {truth['fc'][0]:.4g}), fl {fl:.4g} (truth {truth['c_load'][0]:.4g}); "
          f"held-out with Coulomb alone {before:.4f} -> {after:.4f}, noise floor {case.noise_floor:.4f}")
    assert abs(fl / truth["c_load"][0] - 1.0) < 0.05
    assert abs(fc / truth["fc"][0] - 1.0) < 0.05
    assert after <= 1.10 * case.noise_floor < before


@pytest.mark.parametrize("inertials", [True, False], ids=["modeled", "no-inertials"])
def test_the_payload_arm_model_carries_the_fitted_load(tmp_path: Path, inertials: bool) -> None:
    """The payload estimator's arm model (plain numpy, its load its own rigid-body torque)
    against the identification's regressor with the estimate's load, at random motion."""
    case = blindgen.make_case(out_dir=tmp_path / "case", **SPECS[104])
    path = declare(case.robot_yaml, tmp_path / "load.yaml", [{"effect": "coulomb_friction", "joint": 2},
                                                   {"effect": "load_dependent_coulomb", "joint": 2}], inertials)
    _, doc = identify_blind(case, path, tmp_path / "fit")
    robot = load_robot(path)
    arm = arm_model_from_identification(robot, doc)
    coef = np.zeros(robot.n_parameters + sum(len(e.parameter_names) for e in arm.effects))
    coef[arm.columns] = arm.beta
    settings = {(e["effect"], e["joint"] - 1): e.get("setting", {}) for e in doc["effects"]}
    effects = [e.with_setting(**settings[(e.effect, e.joint)]) if settings[(e.effect, e.joint)] else e
               for e in declared_effects(robot, coef[: robot.n_parameters])]
    rng = np.random.default_rng(1)
    q, qd, qdd = (rng.normal(size=(40, robot.n_joints)) for _ in range(3))
    expected = (stacked_regressor(robot, effects, q, qd, qdd) @ coef).reshape(40, -1)
    assert np.allclose(arm.torque(q, qd, qdd), expected, rtol=1e-9, atol=1e-9 * float(np.abs(expected).max()))


def test_a_declared_smoothing_is_kept(tmp_path: Path) -> None:
    case = blindgen.make_case(out_dir=tmp_path / "case", **SPECS[101])
    path = declare(case.robot_yaml, tmp_path / "load.yaml", [{"effect": "coulomb_friction", "joint": 2},
                                                   {"effect": "load_dependent_coulomb", "joint": 2, "velocity": 0.05}])
    _, doc = identify_blind(case, path, tmp_path / "fit")
    (load,) = [e for e in doc["effects"] if e["effect"] == "load_dependent_coulomb"]
    assert load["setting"] == {"smoothing": 0.05}


def test_a_bad_smoothing_is_refused_with_its_field(tmp_path: Path) -> None:
    case = blindgen.make_case(out_dir=tmp_path / "case", **SPECS[101])
    path = declare(case.robot_yaml, tmp_path / "bad.yaml", [{"effect": "load_dependent_coulomb", "joint": 2, "velocity": -1}])
    with pytest.raises(RobotFileError, match=r"effects\[\d\]\.velocity: must be a velocity >= 0"):
        load_robot(path)


def test_the_diagnosis_names_it_without_modeled_inertials(tmp_path: Path) -> None:
    """Its load then comes from the fit (the robot file has no rigid body to offer)."""
    case = blindgen.make_case(out_dir=tmp_path / "case", **SPECS[104])
    path = declare(case.robot_yaml, tmp_path / "bare.yaml", [], inertials=False)
    out = tmp_path / "d.json"
    assert main(["diagnose", *map(str, case.ident_csvs), "--robot", str(path), "--validate", str(case.valid_csv), "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert ("load_dependent_coulomb", case.effect_joint) in [(f["effect"], f["joint"]) for f in doc["found"]], doc["found"]


def test_the_load_is_the_rigid_body_torque_of_the_given_parameters() -> None:
    """Against Pinocchio's RNEA: the column is |rnea_j(q, qd, qdd)| sign(qd_j)."""
    import pinocchio as pin

    from armid.identify.pinocchio_bridge import to_pinocchio

    robot = load_robot(ROBOTS / "ur5.yaml")
    model = to_pinocchio(robot)
    data = model.createData()
    rng = np.random.default_rng(0)
    q, qd, qdd = (rng.normal(size=(50, robot.n_joints)) for _ in range(3))
    effect = load_friction(robot, 2, robot.modeled_parameters())
    column = effect.columns(q, qd, qdd)[:, 0]
    rnea = np.array([pin.rnea(model, data, q[k], qd[k], qdd[k])[2] for k in range(50)])
    assert np.allclose(column, np.abs(rnea) * np.sign(qd[:, 2]), rtol=1e-9, atol=1e-9)

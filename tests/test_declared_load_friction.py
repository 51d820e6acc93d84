"""Load-dependent Coulomb friction declared in the robot file
(``{effect: load_dependent_coulomb, joint: J}``, issue 15: friction growing with the joint's
load torque, ``(fc + fl |tau_load|) sign(qd)``), fitted by `armid identify` on data armid did
not make (tests/blindgen.py: Pinocchio RNEA along analytic trajectories, no armid code).

- ``fc`` and ``fl`` come back close to the generator's, and the held-out error of
  `--predictions` against the raw torque falls to within 10 % of the noise floor.
- The column's load is the model's own rigid-body torque, at every sample: the prediction at
  a validation stamp is the model there, not a fit to the validation torque.
"""

from __future__ import annotations

import json
from pathlib import Path

import blindgen
import numpy as np
import pytest
import yaml

from armid.cli import main
from armid.identify.effects import load_friction
from armid.io.robot_file import load_robot

SPECS = {s["seed"]: s for s in blindgen.blind_specs("effects", 5, seed0=100, effects=["load_coulomb"])}


def _identify(case: blindgen.Case, robot: Path, out: Path) -> tuple[float, dict]:
    pred, doc = out.with_suffix(".csv"), out.with_suffix(".json")
    assert main(["identify", *map(str, case.ident_csvs), "--robot", str(robot), "--validate", str(case.valid_csv),
                 "--predictions", str(pred), "--json", str(doc)]) == 0
    err, covered = blindgen.relative_error(case.valid_csv, pred)
    assert covered == 1.0
    return err, json.loads(doc.read_text())


@pytest.mark.parametrize("seed", sorted(SPECS))
def test_a_declared_load_dependent_friction_is_fitted_to_the_noise_floor(tmp_path: Path, seed: int) -> None:
    case = blindgen.make_case(out_dir=tmp_path / "case", **SPECS[seed])
    truth = json.loads((tmp_path / "case" / "truth.json").read_text())["effect"]["params"]
    joint = case.effect_joint
    doc = yaml.safe_load(case.robot_yaml.read_text())
    doc["effects"] = [*(doc.get("effects") or []), {"effect": "coulomb_friction", "joint": joint},
                      {"effect": "load_dependent_coulomb", "joint": joint}]
    declared = tmp_path / "robot_load.yaml"
    declared.write_text(yaml.safe_dump(doc))
    before, _ = _identify(case, case.robot_yaml, tmp_path / "without")
    after, report = _identify(case, declared, tmp_path / "with")
    got = {e["effect"]: e for e in report["effects"] if e["joint"] == joint}
    fc, fl = got["coulomb_friction"]["parameters"]["fc"], got["load_dependent_coulomb"]["parameters"]["fl"]
    print(f"\nseed {seed}: joint {joint} fc {fc:.4g} (truth {truth['fc'][0]:.4g}), fl {fl:.4g} (truth {truth['c_load'][0]:.4g}); "
          f"held-out {before:.4f} -> {after:.4f}, noise floor {case.noise_floor:.4f}")
    assert abs(fl / truth["c_load"][0] - 1.0) < 0.10
    assert abs(fc / truth["fc"][0] - 1.0) < 0.10
    assert after <= 1.10 * case.noise_floor < before


def test_the_load_is_the_rigid_body_torque_of_the_given_parameters() -> None:
    """Against Pinocchio's RNEA: the column is |rnea_j(q, qd, qdd)| sign(qd_j)."""
    import pinocchio as pin

    from armid.identify.pinocchio_bridge import to_pinocchio

    robot = load_robot(Path(__file__).resolve().parents[1] / "config" / "robots" / "ur5.yaml")
    model = to_pinocchio(robot)
    data = model.createData()
    rng = np.random.default_rng(0)
    q, qd, qdd = (rng.normal(size=(50, robot.n_joints)) for _ in range(3))
    effect = load_friction(robot, 2, robot.modeled_parameters())
    column = effect.columns(q, qd, qdd)[:, 0]
    rnea = np.array([pin.rnea(model, data, q[k], qd[k], qdd[k])[2] for k in range(50)])
    assert np.allclose(column, np.abs(rnea) * np.sign(qd[:, 2]), rtol=1e-9, atol=1e-9)

"""What a fleet compares from one identification (identify/tracked.py), on recordings armid did
not make (tests/blindgen.py): one arm, one trajectory, recorded 16 times with new noise.

- The declared drive gain's standard deviation (Gauss-Newton on the R factors, times the
  residual's correlation length) is the scatter of the gain over the 16 recordings: their
  ratio within 0.6-1.6 (measured 0.98 with 20 recordings).
- The quantities are the base parameters led by a link parameter, each declared effect's
  coefficient per joint and the declared gain, each with its unit; none is counted twice.
"""

from __future__ import annotations

from pathlib import Path

import blindgen as bg
import numpy as np

from armid import pipeline
from armid.identify.tracked import expression_unit, gain_std, leading_link, tracked_quantities
from armid.io.robot_file import load_robot


def test_the_gain_std_is_the_gain_scatter_over_noise(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    arm, boxes = bg.random_arm(rng, 4, "dh", None)
    traj = bg.random_fourier(rng, arm, 0.2)
    t = bg.stamps(rng, 20.0, 200.0, 0.0)
    effects = [bg.Effect("coulomb_friction", [0, 1, 2, 3], {"fc": [0.3, 0.2, 0.05, 0.02]}),
               bg.Effect("viscous_friction", [0, 1, 2, 3], {"fv": [0.2, 0.1, 0.02, 0.01]}), bg.Effect("torque_gain", [1], {"gain": [1.1]})]
    clean, _ = bg.recorded_torque(arm, traj, t, effects)
    level = bg.NOISE_LEVELS["medium"]
    sensor = bg.Sensor(200.0, 0.0, "medium", True, False, None, level["torque"] * np.abs(clean).max(axis=0), level["qd"], level["counts"], level["q"])
    bg._write_robot(tmp_path / "robot.yaml", "gain4", arm, bg.modeled_links(rng, arm, boxes), 2 * np.abs(clean).max(axis=0),
                    [{"effect": "viscous_friction", "joint": None}, {"effect": "coulomb_friction", "joint": None, "velocity": 0.0},
                     {"effect": "torque_gain", "joint": 2}])
    robot = load_robot(tmp_path / "robot.yaml")
    gains, stds = [], []
    for k in range(16):
        bg.record(np.random.default_rng(100 + k), arm, traj, t, effects, sensor, tmp_path / f"r{k}.csv", None)
        inputs = pipeline.load(robot, pipeline.USER_LOG, [tmp_path / f"r{k}.csv"])
        result, _ = pipeline.identify(robot, inputs.experiments, [], pipeline.USER_LOG)
        assert result.torque_scale is not None
        gains.append(float(result.torque_scale[1]))
        stds.append(float(gain_std(result)[1]))
        assert np.isnan(gain_std(result)[[0, 2, 3]]).all()
    ratio = float(np.mean(stds) / np.std(gains, ddof=1))
    print(f"\ngain {np.mean(gains):.5f} (truth 1.1): std said {np.mean(stds):.3g}, scatter {np.std(gains, ddof=1):.3g}, ratio {ratio:.2f}")
    assert abs(np.mean(gains) - 1.1) < 0.01 and 0.6 < ratio < 1.6
    quantities = tracked_quantities(result)
    keys = [(q.parameter, q.joint) for q in quantities]
    assert len(keys) == len(set(keys))
    assert [q for q in quantities if q.kind == "gain"][0].joint == 2
    assert sorted(q.joint for q in quantities if q.parameter == "coulomb_friction.fc") == [1, 2, 3, 4]
    assert all(q.unit == "N m" for q in quantities if q.parameter == "coulomb_friction.fc")
    assert all(q.kind == "base" and leading_link(q.parameter) is not None for q in quantities if q.unit.startswith("kg"))


def test_a_base_parameter_is_named_by_its_first_term() -> None:
    assert leading_link("Ixx2 - Izz2 + 0.003894*m2 + Izz3") == 2 and expression_unit("Ixx2 - Izz2") == "kg m^2"
    assert leading_link("msx4 + 0.2683*m4") == 4 and expression_unit("msx4 + 0.2683*m4") == "kg m"
    assert leading_link("m7") == 7 and expression_unit("m7") == "kg"
    assert leading_link("fc3") is None and expression_unit("fc3") == ""

"""Identification on data armid did not make: the blind generator (tests/blindgen.py, Pinocchio
RNEA along analytic trajectories, no armid code) at 100 Hz-1 kHz, with and without velocity,
torque or currents, jittery stamps, three noise levels.

With no undeclared effect, ``armid identify --predictions`` (its defaults: filtering chosen
from the data) must predict every validation sample at its own stamp within 10 % of the
noise floor, the error of the noise-free torque against the noisy one (issue 15).
"""

from __future__ import annotations

import json
from pathlib import Path

import blindgen
import pytest

from armid.cli import main

CLEAN = blindgen.blind_specs("clean", 20)
# the cases nearest the bar in a full sweep of the twenty (100 Hz with velocity, 1 kHz
# without, currents, jitter), and one of each rate
CASES = [0, 1, 3, 4, 12, 15, 16, 19]


@pytest.mark.slow
@pytest.mark.parametrize("index", CASES)
def test_clean_blind_case_is_predicted_at_the_noise_floor(index: int, tmp_path: Path) -> None:
    case = blindgen.make_case(out_dir=tmp_path / "case", **CLEAN[index])
    pred, out = tmp_path / "pred.csv", tmp_path / "id.json"
    code = main(["identify", str(case.ident_csv), "--robot", str(case.robot_yaml), "--validate", str(case.valid_csv),
                 "--predictions", str(pred), "--json", str(out)])
    assert code == 0
    error, covered = blindgen.relative_error(case.valid_csv, pred)
    assert covered >= 0.99, f"only {covered:.3f} of the validation stamps predicted"
    floor = case.noise_floor
    assert error <= 1.10 * floor, f"{case.rate_hz:g} Hz, noise {case.noise}: held-out {100 * error:.3f} % against a floor of {100 * floor:.3f} %"
    doc = json.loads(out.read_text())
    filtering = doc["filtering"][0]
    assert {"cutoff_hz", "decimation", "excitation_band_hz", "why"} <= set(filtering)
    assert doc["validation"]["left_out"] <= 0.01 * doc["validation"]["input_samples"]


@pytest.mark.slow
def test_without_the_chosen_filter_a_1khz_log_is_far_from_its_floor(tmp_path: Path) -> None:
    """The bar above is not met by default: a 1 kHz log without velocity, unfiltered."""
    case = blindgen.make_case(out_dir=tmp_path / "case", **CLEAN[3])
    pred = tmp_path / "pred.csv"
    assert main(["identify", str(case.ident_csv), "--robot", str(case.robot_yaml), "--validate", str(case.valid_csv),
                 "--predictions", str(pred), "--lowpass", "off"]) == 0
    error, _ = blindgen.relative_error(case.valid_csv, pred)
    assert error > 2.0 * case.noise_floor


@pytest.mark.slow
def test_a_log_stamped_in_epoch_seconds_is_predicted_at_its_own_stamps(tmp_path: Path) -> None:
    """Loggers stamp in seconds since 1970 (1.7e9 s): a prediction written with ten
    significant digits would land on whole seconds, at no input stamp."""
    import numpy as np

    case = blindgen.make_case(out_dir=tmp_path / "case", **CLEAN[0])
    epoch = 1_764_000_000.0
    shifted = {}
    for name, path in (("ident", case.ident_csv), ("valid", case.valid_csv)):
        lines = Path(path).read_text().splitlines()
        t = np.array([float(line.split(",", 1)[0]) for line in lines[1:]])
        shifted[name] = tmp_path / f"{name}_epoch.csv"
        shifted[name].write_text("\n".join([lines[0], *(f"{epoch + x:.6f},{line.split(',', 1)[1]}" for x, line in zip(t, lines[1:]))]) + "\n")
    (tmp_path / "robot.yaml").write_text(Path(case.robot_yaml).read_text())
    for extra in Path(case.robot_yaml).parent.glob("*.urdf"):
        (tmp_path / extra.name).write_text(extra.read_text())
    pred = tmp_path / "pred.csv"
    assert main(["identify", str(shifted["ident"]), "--robot", str(tmp_path / "robot.yaml"), "--validate", str(shifted["valid"]),
                 "--predictions", str(pred)]) == 0
    error, covered = blindgen.relative_error(shifted["valid"], pred, tmp_path / "robot.yaml")
    assert covered >= 0.99, f"only {covered:.3f} of the validation stamps predicted"
    assert error <= 1.10 * case.noise_floor

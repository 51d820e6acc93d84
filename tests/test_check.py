"""``armid check``: a model identified without a tool, checked on runs with an undeclared tool
on the last link (tests/checkgen.py, which shares no code with armid), on runs without one,
and ``armid diagnose`` validating on a loaded run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from checkgen import make_check_case

from armid.cli import main

KUKA = Path(__file__).resolve().parents[2] / "shared" / "data" / "kuka_lwr4"
ROBOTS = Path(__file__).resolve().parents[1] / "config" / "robots"


def _identified(case, tmp_path: Path) -> Path:
    model = tmp_path / "model.json"
    assert main(["identify", str(case.ident), "--robot", str(case.robot), "--json", str(model)]) == 0
    return model


def _check(case, model: Path, mass: float, out: Path) -> dict:
    assert main(["check", str(case.checks[mass]), "--robot", str(case.robot), "--model", str(model), "--json", str(out)]) == 0
    return json.loads(out.read_text())


@pytest.mark.slow
@pytest.mark.parametrize("family", ["dh6", "mdh6"])
def test_a_tool_is_named_with_its_mass_and_centre_and_no_tool_holds(family: str, tmp_path: Path, capsys) -> None:
    """Tools of 0.5 and 5 kg are one load on the last link within 10 % of their mass and 2 cm of
    their centre, bringing the error back near the floor; the run without a tool holds, nothing found."""
    case = make_check_case(2, family, tmp_path / "case", masses=(0.5, 5.0))
    model = _identified(case, tmp_path)
    clean = _check(case, model, 0.0, tmp_path / "c0.json")
    assert clean["holds"] is True and clean["found"] == []
    for mass in (0.5, 5.0):
        doc = _check(case, model, mass, tmp_path / f"c{mass}.json")
        assert doc["holds"] is False
        loads = [f for f in doc["found"] if f["effect"] == "payload"]
        assert len(loads) == 1 and loads[0]["joint"] == 6
        p = loads[0]["parameters"]
        assert abs(p["m"] - mass) <= 0.1 * mass
        assert np.linalg.norm(np.array([p["cx"], p["cy"], p["cz"]]) - np.array(case.offset_m)) <= 0.02
        assert doc["after"]["relative_error"] < 0.5 * doc["before"]["relative_error"]
        assert doc["after"]["relative_error"] <= 1.25 * max(doc["noise_floor"]["relative_error"], doc["reference"]["relative_error"])
    out = capsys.readouterr().out
    assert "the model holds on these data" in out and "does NOT hold" in out and "a load of" in out


@pytest.mark.slow
def test_diagnose_never_says_the_model_explains_a_loaded_validation(tmp_path: Path, capsys) -> None:
    """Identified without the tool, validated on a run with 2 kg: diagnose says the validation
    data differ, and its check names the load, instead of 'explains the data to its noise'."""
    case = make_check_case(3, "mdh6", tmp_path / "case", masses=(2.0,))
    out_json = tmp_path / "d.json"
    assert main(["diagnose", str(case.ident), "--robot", str(case.robot), "--validate", str(case.checks[2.0]), "--json", str(out_json)]) == 0
    out = capsys.readouterr().out
    assert "explains the data to its noise" not in out
    assert "the validation data differ from the identification data" in out
    doc = json.loads(out_json.read_text())
    differs = doc["validation_differs"]
    assert differs is not None and differs["holds"] is False
    load = next(f for f in differs["found"] if f["effect"] == "payload")
    assert abs(load["parameters"]["m"] - 2.0) <= 0.2


def test_check_keeps_the_model_fixed_and_reproduces_its_own_fit(tmp_path: Path) -> None:
    """On the model's own identification data, check's 'before' is the identification's fit
    error at the stamps: the JSON's model read back predicts what identify predicted."""
    case = make_check_case(5, "dh6", tmp_path / "case", masses=())
    model = tmp_path / "model.json"
    pred_identify = tmp_path / "p_identify.csv"
    assert main(["identify", str(case.ident), "--robot", str(case.robot), "--json", str(model), "--validate", str(case.checks[0.0]),
                 "--predictions", str(pred_identify)]) == 0
    pred_check = tmp_path / "p_check.csv"
    doc_path = tmp_path / "c.json"
    assert main(["check", str(case.checks[0.0]), "--robot", str(case.robot), "--model", str(model), "--json", str(doc_path),
                 "--predictions", str(pred_check)]) == 0
    a = np.loadtxt(pred_identify, delimiter=",", skiprows=1)
    b = np.loadtxt(pred_check, delimiter=",", skiprows=1)
    assert a.shape == b.shape
    np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-9)
    doc = json.loads(doc_path.read_text())
    assert {"holds", "found", "before", "after", "noise_floor", "notes"} <= set(doc)
    assert doc["holds"] is True and doc["reference"]["kind"] == "validation"
    assert doc["before"]["relative_error"] == pytest.approx(json.loads(model.read_text())["validation"]["relative_error"], rel=1e-9)


def test_a_model_of_another_arm_is_refused_in_one_line(tmp_path: Path, capsys) -> None:
    case = make_check_case(6, "dh6", tmp_path / "case", masses=())
    other = make_check_case(7, "mdh6", tmp_path / "other", masses=())
    model = tmp_path / "model.json"
    assert main(["identify", str(other.ident), "--robot", str(other.robot), "--json", str(model)]) == 0
    capsys.readouterr()
    assert main(["check", str(case.checks[0.0]), "--robot", str(case.robot), "--model", str(model)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "base parameters do not match" in err[0]
    (tmp_path / "broken.json").write_text("{\"base_parameters\": 3}")
    assert main(["check", str(case.checks[0.0]), "--robot", str(case.robot), "--model", str(tmp_path / "broken.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "broken.json" in err[0] and "base_parameters" in err[0]


@pytest.mark.slow
@pytest.mark.skipif(not KUKA.exists(), reason="the shared KUKA LWR4+ recordings are not beside the repository")
def test_kuka_model_holds_on_recording_2(tmp_path: Path, capsys) -> None:
    """The KUKA LWR4+ identified on recording 1 holds on recording 2 (the same kind of motion)."""
    model = tmp_path / "m1.json"
    robot = str(ROBOTS / "kuka_lwr4.yaml")
    assert main(["identify", str(KUKA / "measurements_1.npz"), "--robot", robot, "--json", str(model)]) == 0
    doc_path = tmp_path / "c2.json"
    assert main(["check", str(KUKA / "measurements_2.npz"), "--robot", robot, "--model", str(model), "--json", str(doc_path)]) == 0
    doc = json.loads(doc_path.read_text())
    assert doc["holds"] is True and doc["found"] == []


@pytest.mark.slow
@pytest.mark.skipif(not KUKA.exists(), reason="the shared KUKA LWR4+ recordings are not beside the repository")
def test_a_load_dependent_friction_is_held_with_the_load_identify_used(tmp_path: Path) -> None:
    """With a declared load-dependent friction (its load the fit's own rigid body), check's
    model read back from the JSON predicts exactly what identify predicted on the same data."""
    robot = str(ROBOTS / "kuka_lwr4_load.yaml")
    model, p_identify, p_check = tmp_path / "m.json", tmp_path / "pi.csv", tmp_path / "pc.csv"
    assert main(["identify", str(KUKA / "measurements_1.npz"), "--robot", robot, "--validate", str(KUKA / "measurements_2.npz"),
                 "--json", str(model), "--predictions", str(p_identify)]) == 0
    assert main(["check", str(KUKA / "measurements_2.npz"), "--robot", robot, "--model", str(model), "--predictions", str(p_check)]) == 0
    a = np.loadtxt(p_identify, delimiter=",", skiprows=1)
    b = np.loadtxt(p_check, delimiter=",", skiprows=1)
    np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-9)

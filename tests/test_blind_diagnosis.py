"""Diagnosis on data armid did not make (issue 16): the blind generator (tests/blindgen.py,
Pinocchio RNEA along analytic trajectories, no armid code) makes random 3-7 joint arms in DH
and MDH, sampled at 100 Hz-1 kHz, torque or current, with or without velocity, jittery or
not, at three noise levels.

- Each catalogue effect (and friction on every joint, the arm-wide family), on a random
  joint, at sizes from barely above the noise floor to large, over five seeds: ``armid
  diagnose`` names it with its joint (or arm-wide; or as the look-alike of what it found, when
  it says the data cannot tell the two apart) and its ``--predictions`` close at least
  half the gap between the declared model's error (``identify --predictions``, which is
  diagnose's "before") and the noise floor. Every error is against the validation file's raw
  torque at its own stamps (blindgen.relative_error).
- Twenty clean seeds across rates and noise levels: no finding at all.

The cases are the generator's (blind_specs), not chosen after the fact; CI runs a fixed part
of them (see FULL below), the README gives the whole sweep's result.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import blindgen
import numpy as np
import pytest

from armid.cli import main
from armid.identify.diagnosis.refit import sign_reversed
from armid.identify.diagnosis.report import extrapolated_findings
from armid.identify.diagnosis.search import Finding, set_aside_sentence

CATALOGUE = ["viscous_friction", "coulomb_friction", "stribeck_friction", "torque_offset", "rotor_inertia", "torque_gain",
             "time_delay", "cogging", "spring", "gravity_tilt", "friction_all", "load_coulomb"]
# the whole sweep (5 seeds per effect, 20 clean seeds: 311 s on 2 cores at load 3-4) runs with
# ARMID_BLIND_FULL=1; CI runs its first seed of every effect and four clean seeds (one per rate,
# every noise level, with and without jitter): the whole suite must stay within CI's 15 minutes
FULL = os.environ.get("ARMID_BLIND_FULL") == "1"
EFFECTS = blindgen.blind_specs("effects", 5, effects=CATALOGUE)
CLEAN = blindgen.blind_specs("clean", 20)
if not FULL:
    EFFECTS, CLEAN = EFFECTS[::5], CLEAN[:4]


def _name(spec: dict) -> str:
    sig = "i" if spec["currents"] else "tau"
    return f"{spec.get('effect', 'clean')}-{spec['rate_hz']:g}Hz-{sig}{'' if spec['velocity'] else '-noqd'}{'-jit' if spec['jitter'] else ''}-{spec['noise']}-s{spec['seed']}"


def _diagnose(spec: dict, tmp_path: Path) -> tuple[blindgen.Case, dict, float]:
    case = blindgen.make_case(out_dir=tmp_path / "case", **spec)
    pred, out = tmp_path / "pred.csv", tmp_path / "d.json"
    code = main(["diagnose", *[str(p) for p in case.ident_csvs], "--robot", str(case.robot_yaml), "--validate", str(case.valid_csv),
                 "--predictions", str(pred), "--json", str(out)])
    assert code == 0
    after, covered = blindgen.relative_error(case.valid_csv, pred)
    assert covered >= 0.99, f"only {covered:.3f} of the validation stamps predicted"
    return case, json.loads(out.read_text()), after


@pytest.mark.parametrize("spec", EFFECTS, ids=_name)
def test_blind_effect_is_named_and_closes_half_the_gap(spec: dict, tmp_path: Path) -> None:
    case, doc, after = _diagnose(spec, tmp_path)
    found = [(f["effect"], f["joint"]) for f in doc["found"]]
    # named as found, or as the look-alike the finding says this data cannot tell apart from it
    # (Coulomb/Stribeck, gain/rotor inertia, delay/viscous, offset/spring), with the experiment that would
    named = found + [(f["lookalike"]["effect"], f["joint"]) for f in doc["found"] if f.get("lookalike")]
    joint = case.effect_joint  # 1-based, None for an arm-wide effect
    assert any(e == case.expected and (joint is None or j in (joint, None)) for e, j in named), \
        f"expected {case.expected} on joint {joint}, found {found}"
    before, floor = doc["before"]["relative_error"], case.noise_floor
    assert before - after >= 0.5 * (before - floor), f"before {100 * before:.3f} %, after {100 * after:.3f} %, floor {100 * floor:.3f} %"


@pytest.mark.parametrize("spec", CLEAN, ids=_name)
def test_blind_clean_case_finds_nothing(spec: dict, tmp_path: Path) -> None:
    _, doc, _ = _diagnose(spec, tmp_path)
    assert doc["found"] == [], [(f["effect"], f["joint"], f["parameters"]) for f in doc["found"]]
    assert doc["noise_floor"]["relative_error"] is not None and doc["chosen_on"] != doc["measured_on"]


# gate (f): a clean 100 Hz low-noise 7-joint arm (sweep seed 3000) whose odd tenths a spring on
# the light joint 6 cleared every other gate on (the prior holding poorly excited parameters at
# the modeled values leaves a slow model error there); on the validation run it takes joint 6
# from 0.719 % to 0.761 % over most of its tenths: set aside. And a real drive gain (seed 28)
# that extrapolates a little worse on its joint (2.03 % -> 2.05 %, in a few tenths) is kept:
# a veto on any rise took it
SPRING_ON_TENTHS = blindgen.blind_specs("clean", 1, seed0=3000)[0]
GAIN_A_LITTLE_WORSE = blindgen.blind_specs("effects", 5, effects=CATALOGUE)[28]


def test_a_finding_the_validation_contradicts_is_set_aside(tmp_path: Path) -> None:
    """The identification runs carry a cogging on joint 2 that the validation run does not
    (a gearbox changed between them): found on the identification data, it raises joint 2's
    validation error consistently over its tenths and is set aside. On the clean runs alone
    nothing is found. (This clean 100 Hz case used to grow a spring that the veto removed:
    the plain 5-point filter's droop, 2 % at 3 Hz on 10 ms samples, left a residual a spring
    could fit; with the sharpened filter no candidate comes up.)"""
    assert SPRING_ON_TENTHS["rate_hz"] == 100.0 and SPRING_ON_TENTHS["noise"] == "low"
    clean, doc, _ = _diagnose(SPRING_ON_TENTHS, tmp_path / "clean")
    assert doc["found"] == [], [(f["effect"], f["joint"], f["parameters"]) for f in doc["found"]]
    cogged = blindgen.make_case(out_dir=tmp_path / "cogged", **SPRING_ON_TENTHS, effect="cogging", effect_joint=2, effect_size=0.1)
    out = tmp_path / "d.json"
    code = main(["diagnose", *[str(p) for p in cogged.ident_csvs], "--robot", str(clean.robot_yaml), "--validate", str(clean.valid_csv),
                 "--json", str(out)])
    doc = json.loads(out.read_text())
    assert code == 0 and doc["found"] == [], [(f["effect"], f["joint"], f["parameters"]) for f in doc["found"]]
    vetoed = [c for c in doc["set_aside"] if c["reason"] == "validation"]
    assert [(c["effect"], c["joint"]) for c in vetoed] == [("cogging", 2)], doc["set_aside"]
    assert all(c["validation_error_with"] > c["validation_error_before"] and c["t"] > 1.83 for c in vetoed)
    assert "veto" in doc["chosen_on"]


def test_a_real_effect_a_little_worse_on_the_validation_is_kept(tmp_path: Path) -> None:
    assert GAIN_A_LITTLE_WORSE["effect"] == "torque_gain" and GAIN_A_LITTLE_WORSE["seed"] == 28
    test_blind_effect_is_named_and_closes_half_the_gap(GAIN_A_LITTLE_WORSE, tmp_path)


# a Stribeck peak on the light wrist (joint 6, 0.4 N*m of torque) of a 200 Hz current log: its
# peak took joint 6's validation error from 1.18 to 0.88 of its noise and the arm's, which the
# shoulder's noise sets, by 0.01 %: judged on the arm's error it was named Coulomb
WRIST_STRIBECK = blindgen.blind_specs("effects", 5, effects=CATALOGUE)[13]


def test_a_friction_shape_is_judged_on_its_own_joint(tmp_path: Path) -> None:
    """The Stribeck peak must be material on its joint's validation error, not the arm's:
    named as found (not only as a look-alike), nothing left as negligible."""
    assert WRIST_STRIBECK["effect"] == "stribeck_friction" and WRIST_STRIBECK["seed"] == 13
    case, doc, _ = _diagnose(WRIST_STRIBECK, tmp_path)
    assert [(f["effect"], f["joint"]) for f in doc["found"]] == [("stribeck_friction", case.effect_joint)], doc["found"]
    assert doc["negligible"] == [], doc["negligible"]


# a Stribeck peak on joint 3 of a 1 kHz current log, velocity from 2^14-count encoders, high
# noise: its columns computed on the filtered velocity fitted the peak at -10 N*m (true 18.6),
# and on the arm's rows whitened by the declared model's residual (joint 3's inflated by the
# friction sought) the true peak lost to Coulomb; it was named Coulomb, Stribeck its look-alike
HIGH_NOISE_STRIBECK = blindgen.blind_specs("effects", 5, effects=CATALOGUE)[11]


def test_a_stribeck_peak_is_fitted_as_the_torque_was_filtered(tmp_path: Path) -> None:
    """Named as found, no look-alike; its Coulomb level, peak and velocity the generator's
    (within 10 % and a grid step), and the validation error at the noise floor (within 5 %)."""
    assert HIGH_NOISE_STRIBECK["effect"] == "stribeck_friction" and HIGH_NOISE_STRIBECK["seed"] == 11
    case, doc, after = _diagnose(HIGH_NOISE_STRIBECK, tmp_path)
    assert [(f["effect"], f["joint"], f.get("lookalike")) for f in doc["found"]] == [("stribeck_friction", case.effect_joint, None)], doc["found"]
    got, true = doc["found"][0]["parameters"], {k: v[0] for k, v in case.params.items()}
    assert abs(got["fc"] - true["fc"]) < 0.1 * true["fc"] and abs(got["fs"] - (true["fs"] - true["fc"])) < 0.1 * (true["fs"] - true["fc"]), (got, true)
    assert 1 / 1.34 < got["velocity"] / true["vs"] < 1.34, (got, true)
    assert after < 1.05 * case.noise_floor, (after, case.noise_floor)


# cases that once failed, run in CI too: a drive gain of 0.25 on the distal joint 6 of a 500 Hz
# high-noise arm (a gain linearised about the current fit came out negative and was refused;
# joint 3 was named instead); and a 100 Hz cogging whose period exceeds the joint's range of
# motion (no cogging candidate), whose residual on that one joint a gravity tilt was bent to fit
# (validation 5.9 % -> 18.9 %): an arm-wide effect must show on more than one joint
DISTAL_GAIN = blindgen.blind_specs("effects", 5, effects=CATALOGUE)[26]
ONE_JOINT_RESIDUAL = blindgen.blind_specs("effects", 5)[40]


def test_distal_drive_gain_is_named_on_its_joint(tmp_path: Path) -> None:
    assert DISTAL_GAIN["effect"] == "torque_gain"
    test_blind_effect_is_named_and_closes_half_the_gap(DISTAL_GAIN, tmp_path)


def test_one_joint_residual_is_not_an_arm_wide_finding(tmp_path: Path) -> None:
    """... and the spring found instead on the prismatic joint 2 (the local slope of the
    0.18 m ripple over 0.145 m of motion), found on -0.093..0.053 m while the validation goes
    to 0.092 m (5.96 % -> 12.2 %), is reported as extrapolated: nothing in the identification
    data can tell, so the output says where the finding is an extrapolation."""
    assert ONE_JOINT_RESIDUAL["effect"] == "cogging" and ONE_JOINT_RESIDUAL["rate_hz"] == 100.0
    _, doc, _ = _diagnose(ONE_JOINT_RESIDUAL, tmp_path)
    assert not [f for f in doc["found"] if f["joint"] is None], doc["found"]
    for f in doc["found"]:
        if f["effect"] in ("spring", "cogging") and f["joint"] == 2:
            (x,) = [x for x in doc["extrapolated"] if x["joint"] == 2 and x["effect"] == f["effect"]]
            assert x["beyond_fraction"] > 0.2 and x["validation_range"][1] > x["identified_range"][1]


def test_extrapolated_compares_the_ranges() -> None:
    found = [Finding("spring", 0, {"stiffness": 1.0}, 0.1, 0.02, 0.01), Finding("cogging", 1, {}, 0.1, 0.02, 0.01),
             Finding("viscous_friction", 0, {}, 0.1, 0.02, 0.01)]
    q_ident = np.column_stack([np.linspace(-1.0, 1.0, 50), np.linspace(0.0, 2.0, 50)])
    q_valid = np.column_stack([np.linspace(-0.5, 1.5, 50), np.linspace(0.05, 2.05, 50)])  # 25 % beyond; 2.5 % beyond
    (x,) = extrapolated_findings(found, q_ident, q_valid)
    assert (x["effect"], x["joint"]) == ("spring", 1)
    assert x["beyond_fraction"] == pytest.approx(0.25) and x["identified_range"] == [-1.0, 1.0] and x["validation_range"] == [-0.5, 1.5]
    assert extrapolated_findings(found, q_ident, q_ident) == []


def test_before_is_what_identify_predicts(tmp_path: Path) -> None:
    """diagnose's 'before' is the declared model exactly as `armid identify` fits it."""
    case = blindgen.make_case(out_dir=tmp_path / "case", **EFFECTS[0])
    files = [str(p) for p in case.ident_csvs]
    assert main(["identify", *files, "--robot", str(case.robot_yaml), "--validate", str(case.valid_csv), "--predictions", str(tmp_path / "i.csv")]) == 0
    assert main(["diagnose", *files, "--robot", str(case.robot_yaml), "--validate", str(case.valid_csv), "--json", str(tmp_path / "d.json")]) == 0
    before, _ = blindgen.relative_error(case.valid_csv, tmp_path / "i.csv")
    assert json.loads((tmp_path / "d.json").read_text())["before"]["relative_error"] == pytest.approx(before, rel=1e-9)


# a clean, low-noise 200 Hz case (`examples/blind_cases.py --set clean --ptp`, seed 1001) where a
# cogging on joint 3 of 0.0013 N*m, 6 % of that joint's torque noise, passed every held-out test
# of the long filtered record and was reported (validation 0.676 % -> 0.675 %): a finding must
# change the prediction by a quarter of its joint's noise at least
LOW_NOISE_CLEAN = {"seed": 1001, "rate_hz": 200.0, "currents": False, "velocity": True, "jitter": 0.1, "noise": "low"}


def test_an_effect_far_below_the_noise_is_not_a_finding(tmp_path: Path) -> None:
    test_blind_clean_case_finds_nothing(LOW_NOISE_CLEAN, tmp_path)


def test_a_finding_whose_final_fit_turns_its_sign_is_set_aside() -> None:
    """Seen on an independent generator's 1 kHz KUKA-like arm: a Stribeck term on joint 6 at the
    grid's edge (v_s 1 rad/s) positive on the search's blocks came out fs -0.69 in the final
    fit with the other findings; it is set aside with the reason, the others refitted."""
    stribeck = Finding("stribeck_friction", 5, {"fs": -0.6926, "velocity": 1.0}, 0.05, 0.02, 0.019)
    kept = [Finding("rotor_inertia", 3, {"ia": 0.94}, 0.2, 0.05, 0.03), Finding("spring", 2, {"stiffness": 3.0}, 0.1, 0.03, 0.02),
            Finding("load_dependent_coulomb", 1, {"fc": -0.1, "fl": 0.05}, 0.1, 0.03, 0.02)]
    pushing = Finding("spring", 4, {"stiffness": -3.0}, 0.1, 0.03, 0.02)  # pushes away from its rest: no passive spring (issue 33)
    held = Finding("viscous_friction", 0, {"fv": 0.0}, 0.1, 0.03, 0.02)  # held at its bound by the bounded fit: explains nothing
    assert sign_reversed([*kept, stribeck, pushing, held]) == [stribeck, pushing, held]
    text = set_aside_sentence({"effect": "stribeck_friction", "joint": 6, "parameters": stribeck.parameters, "reason": "sign"})
    assert "fs came out -0.6926" in text and "not physical" in text


# issue 62: a Stribeck curve named Coulomb friction, a spring named an offset (and a cogging).
# Ten seeds of each on the generator's own sweep (sensors and sizes rotating: whole-arm effect
# 1.5-25 times the noise), nothing declared, and ten springs beside declared Coulomb and viscous
# friction on every joint: each is named as found, on its joint
NAMED_AS_FOUND = blindgen.blind_specs("effects", 10, seed0=6200, effects=["stribeck_friction", "spring"])
_FRICTION = {"declare": [{"effect": "coulomb_friction", "joint": None}, {"effect": "viscous_friction", "joint": None}],
             "extra_effects": [{"effect": "coulomb_friction", "joint": "all", "size": 0.1},
                               {"effect": "viscous_friction", "joint": "all", "size": 0.1}]}
SPRINGS = blindgen.blind_specs("effects", 10, seed0=6300, effects=["spring"])
SPRINGS_BESIDE_FRICTION = [{**s, **_FRICTION} for s in blindgen.blind_specs("effects", 10, seed0=6400, effects=["spring"])]


def _named_as_found(spec: dict, tmp_path: Path) -> dict:
    case, doc, after = _diagnose(spec, tmp_path)
    found = [(f["effect"], f["joint"]) for f in doc["found"]]
    assert (case.expected, case.effect_joint) in found, f"expected {case.expected} on joint {case.effect_joint}, found {found}"
    before, floor = doc["before"]["relative_error"], case.noise_floor
    assert before - after >= 0.5 * (before - floor), f"before {100 * before:.3f} %, after {100 * after:.3f} %, floor {100 * floor:.3f} %"
    return doc


# seed 6308 (a spring of 0.08 N*m/rad on the light joint 4 of a 100 Hz high-noise arm): ranked
# first and significant, it fixes its joint's held-out error (0.18 of it) but moves the arm's by
# under the 0.5 % gate (b) asks; nothing is named (validation 3.40 % for a 3.31 % floor)
_BELOW_THE_ARM_GATE = pytest.mark.xfail(reason="below gate (b)'s arm drop, nothing named", strict=True)


@pytest.mark.slow
@pytest.mark.parametrize("spec", NAMED_AS_FOUND + [pytest.param(s, marks=_BELOW_THE_ARM_GATE) if s["seed"] == 6308 else s for s in SPRINGS]
                         + SPRINGS_BESIDE_FRICTION, ids=lambda s: _name(s) + ("-friction" if "declare" in s else ""))
def test_stribeck_and_spring_are_named_as_found(spec: dict, tmp_path: Path) -> None:
    _named_as_found(spec, tmp_path)


# seed 6206: a Stribeck peak (v_s 0.083 rad/s, fs - fc 0.39 N*m) on joint 2 of a 500 Hz current
# log; the final fit searched its Coulomb level's smoothing on the data (0.086 rad/s beside
# v_s 0.075), fitted the peak 1.41, and the peak was judged negligible: named Coulomb friction
STRIBECK_SMOOTHED_AWAY = NAMED_AS_FOUND[6]
# seed 6306: a spring (rest 0.10 m) on the prismatic joint 3, moving over -0.06..0.09 m: mostly a
# constant torque; the offset ranked first by a hair, and the stiffness left over cleared no gate
SPRING_MOSTLY_CONSTANT = SPRINGS[6]


def test_a_stribeck_peak_keeps_the_sharp_level_it_was_found_with(tmp_path: Path) -> None:
    """Named as found, nothing negligible, its peak the generator's (within 25 %) and the
    validation error at the noise floor (within 5 %)."""
    assert STRIBECK_SMOOTHED_AWAY["effect"] == "stribeck_friction" and STRIBECK_SMOOTHED_AWAY["seed"] == 6206
    case, doc, after = _diagnose(STRIBECK_SMOOTHED_AWAY, tmp_path)
    assert [(f["effect"], f["joint"]) for f in doc["found"]] == [("stribeck_friction", case.effect_joint)], doc["found"]
    assert doc["negligible"] == [], doc["negligible"]
    got, true = doc["found"][0]["parameters"], {k: v[0] for k, v in case.params.items()}
    assert abs(got["fs"] - (true["fs"] - true["fc"])) < 0.25 * (true["fs"] - true["fc"]), (got, true)
    assert after < 1.05 * case.noise_floor, (after, case.noise_floor)


def test_a_spring_mostly_constant_is_a_spring(tmp_path: Path) -> None:
    assert SPRING_MOSTLY_CONSTANT["effect"] == "spring" and SPRING_MOSTLY_CONSTANT["seed"] == 6306
    doc = _named_as_found(SPRING_MOSTLY_CONSTANT, tmp_path)
    assert [f["effect"] for f in doc["found"]] == ["spring"], doc["found"]


def test_a_stribeck_findings_coulomb_level_is_declared_sharp() -> None:
    """findings_model declares a Stribeck finding's Coulomb level (found with it, or found
    before it on its joint) as sign(qd), not a smoothing the settings' search would choose."""
    from armid.identify.diagnosis.search import findings_model
    from armid.identify.robot import DeclaredEffect

    robot = _bare_puma()
    stribeck = Finding("stribeck_friction", 1, {"fc": 0.4, "fs": 0.5, "velocity": 0.075}, 0.1, 0.02, 0.01)
    model, _ = findings_model(robot, [stribeck])
    assert DeclaredEffect("coulomb_friction", 2, {"velocity": 0.0}) in model.effects
    level, peak = Finding("coulomb_friction", 2, {"fc": 0.4}, 0.1, 0.02, 0.01), Finding("stribeck_friction", 2, {"fs": 0.5, "velocity": 0.1}, 0.1, 0.02, 0.01)
    model, _ = findings_model(robot, [level, peak])
    assert DeclaredEffect("coulomb_friction", 3, {"velocity": 0.0}) in model.effects
    model, _ = findings_model(robot, [level])  # alone: its smoothing chosen on the data, as a declared one's
    assert DeclaredEffect("coulomb_friction", 3, {}) in model.effects


def _bare_puma():  # the PUMA 560 without its declared effects
    from dataclasses import replace

    from armid.commands.arguments import load_robot_argument

    return replace(load_robot_argument(str(Path(__file__).resolve().parent.parent / "config" / "robots" / "puma560.yaml")), effects=())

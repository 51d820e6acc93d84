"""The model's held-out error (identify/model_errors.py): each fold predicted by the fit of the
other nine, checked against least squares on the other nine folds' rows themselves
(numpy's lstsq, not the R factors the code stacks), and on the KUKA LWR4+'s real recordings
against a second recording of the same motion."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from armid import pipeline
from armid.cli import main
from armid.identify.equations import regression_system
from armid.identify.estimation import solve_factors
from armid.identify.identification import identify
from armid.identify.metrics import summary
from armid.identify.model_errors import BLOCKS, FOLDS, equation_folds, fold_of, held_out_error
from armid.io.robot_file import load_robot

ROOT = Path(__file__).resolve().parent.parent
KUKA = ROOT.parent / "shared" / "data" / "kuka_lwr4"
ROBOT = ROOT / "config" / "robots" / "kuka_lwr4.yaml"


def test_blocks_are_dealt_to_the_folds_in_turn() -> None:
    t = np.linspace(0.0, 10.0, 100_001)
    fold = fold_of(t, 0.0, 10.0)
    block = np.minimum((t / 10.0 * BLOCKS).astype(int), BLOCKS - 1)
    assert np.array_equal(fold, block % FOLDS)
    assert set(np.unique(fold)) == set(range(FOLDS))
    # every fold spans the whole run: its first block in the first tenth, its last in the last
    for f in range(FOLDS):
        mine = t[fold == f]
        assert mine.min() < 1.0 and mine.max() > 9.0


@pytest.mark.skipif(not KUKA.exists(), reason="needs ../shared/data/kuka_lwr4")
def test_each_fold_is_predicted_by_least_squares_on_the_other_nine() -> None:
    """Ordinary least squares without a prior: the ten fits equal numpy's lstsq on the rows of
    the other nine folds, and so does the error at each fold's own samples."""
    robot = load_robot(ROBOT)
    recipe = pipeline.USER_LOG.with_options(prior="none", weighting="ols")
    data = pipeline.load(robot, recipe, [KUKA / "measurements_1.npz"]).experiments
    result = identify(robot, data, None, recipe.identify)
    segments = [s for p in data for s in p.segments]
    system = regression_system(robot, result.effects, segments)
    got = held_out_error(result, system, segments, lambda f: solve_factors(f, "ols"))
    assert got is not None and got["folds"] == FOLDS

    fold = equation_folds(segments)
    cols = result.base.independent
    taus, hats = [], []
    for f in range(FOLDS):
        rows = fold != f
        a = np.vstack([system[j][cols][:, rows].T for j in range(robot.n_joints)])
        y = np.concatenate([system[j][-1][rows] for j in range(robot.n_joints)])
        beta = np.linalg.lstsq(a, y, rcond=None)[0]
        model = replace(result, estimate=replace(result.estimate, beta=beta), _at_stamps={})
        for seg in segments:
            st = seg.at_stamps
            mine = fold_of(st.t, float(seg.t[0]), float(seg.t[-1])) == f
            taus.append(st.tau[mine])
            hats.append(model.predict_times(st.t[mine], st.q[mine], st.qd[mine], st.qdd[mine]))
    want = summary(np.concatenate(taus), np.concatenate(hats))
    assert got["relative_error"] == pytest.approx(want["relative_error"], rel=1e-9)
    assert np.allclose(got["relative"], want["relative"], rtol=1e-9)
    assert got["relative_error"] > result.fit["relative_error"]


@pytest.mark.skipif(not KUKA.exists(), reason="needs ../shared/data/kuka_lwr4")
def test_the_held_out_error_is_what_a_repeat_of_the_motion_shows(tmp_path: Path) -> None:
    """Recording 2 repeats recording 1's trajectory: recording 1's held-out error stands
    between its fit error (optimistic) and 1.1x its error on recording 2; ``armid check``
    takes it as the model's own where the model was not validated."""
    out = tmp_path / "m1.json"
    assert main(["identify", str(KUKA / "measurements_1.npz"), "--robot", str(ROBOT), "--validate",
                 str(KUKA / "measurements_2.npz"), "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    fit, held, valid = (doc[k]["relative_error"] for k in ("fit", "held_out", "validation"))
    assert fit < held < 1.1 * valid, (fit, held, valid)
    del doc["validation"]
    out.write_text(json.dumps(doc))
    verdict = tmp_path / "check.json"
    assert main(["check", str(KUKA / "measurements_2.npz"), "--robot", str(ROBOT), "--model", str(out), "--json", str(verdict)]) == 0
    check = json.loads(verdict.read_text())
    assert check["holds"] and check["reference"]["kind"] == "held_out"
    assert check["reference"]["relative_error"] == pytest.approx(held)

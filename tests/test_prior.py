"""The modeled values as a prior (identify/prior.py) on the real KUKA LWR4+ recordings.

- Identified on recording 1 and predicting recording 3 (another trajectory, faster, other
  poses), armid's default estimate beats both least squares alone and the plain pipeline
  (``../shared/tools/baseline.py``, no armid code), every error computed here from the
  ``--predictions`` files against the raw torque at every validation stamp. Measured:
  armid 9.91 %, least squares alone 14.0 %, plain pipeline 12.68 %.
- A robot file whose inertials are placeholders (the URDF's masses and inertias at 1 %)
  does not pull the estimate: the prior is widened until the data agree with it (measured
  4,580x in variance), and the held-out error is no worse than least squares alone.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import blindgen
import numpy as np
import pytest
from conftest import ROBOTS, SHARED

from armid.cli import main

KUKA = SHARED / "data" / "kuka_lwr4"
pytestmark = pytest.mark.skipif(not (KUKA / "measurements_1.npz").exists(), reason="shared KUKA data not beside the repository")


def _csv(k: int, out: Path) -> Path:
    """Recording ``k`` as an INTERFACES.md CSV (t from 0, q, qd, tau), as a user would write it."""
    d = np.load(KUKA / f"measurements_{k}.npz")
    t = np.round(d["times"] - d["times"][0], 6)
    cols = ["t", *(f"{s}{j + 1}" for s in ("q", "qd", "tau") for j in range(7))]
    path = out / f"m{k}.csv"
    np.savetxt(path, np.column_stack([t, d["positions"], d["velocities"], d["torques"]]), delimiter=",", header=",".join(cols), comments="", fmt="%.9g")
    return path


def _armid(ident: Path, valid: Path, robot: Path, out: Path, *extra: str) -> tuple[float, dict]:
    pred, doc = out.with_suffix(".csv"), out.with_suffix(".json")
    assert main(["identify", str(ident), "--robot", str(robot), "--validate", str(valid), "--predictions", str(pred), "--json", str(doc), *extra]) == 0
    err, covered = blindgen.relative_error(valid, pred)
    assert covered == 1.0
    return err, json.loads(doc.read_text())


def test_prior_beats_least_squares_and_the_plain_pipeline_on_another_trajectory(tmp_path: Path) -> None:
    m1, m3 = _csv(1, tmp_path), _csv(3, tmp_path)
    robot = ROBOTS / "kuka_lwr4.yaml"
    armid, doc = _armid(m1, m3, robot, tmp_path / "prior")
    alone, doc_none = _armid(m1, m3, robot, tmp_path / "none", "--prior", "none")
    plain = tmp_path / "plain.csv"
    subprocess.run([sys.executable, str(SHARED / "tools" / "baseline.py"), str(m1), "--robot", str(robot), "--validate", str(m3),
                    "--predictions", str(plain)], check=True, capture_output=True)
    baseline, _ = blindgen.relative_error(m3, plain)
    print(f"KUKA 1 -> 3: armid {armid:.4f}, least squares alone {alone:.4f}, plain pipeline {baseline:.4f}")
    assert doc["prior"]["used"] and doc["prior"]["widened_by"] == 1.0 and doc_none["prior"] is None
    assert armid < baseline and armid < alone


def test_placeholder_inertials_are_widened_not_followed(tmp_path: Path) -> None:
    urdf = (KUKA / "kuka_lwr4.urdf").read_text()
    urdf = re.sub(r'<mass value="([^"]+)"', lambda m: f'<mass value="{float(m.group(1)) * 0.01:.6g}"', urdf)
    urdf = re.sub(r"<inertia ([^/]*)", lambda m: "<inertia " + " ".join(f'{k}="{float(v) * 0.01:.6g}"' for k, v in re.findall(r'(\w+)="([^"]+)"', m.group(1))), urdf)
    (tmp_path / "placeholder.urdf").write_text(urdf)
    robot = tmp_path / "placeholder.yaml"
    robot.write_text((ROBOTS / "kuka_lwr4.yaml").read_text().replace("urdf: kuka_lwr4.urdf", "urdf: placeholder.urdf"))
    m1, m2 = _csv(1, tmp_path), _csv(2, tmp_path)
    with_prior, doc = _armid(m1, m2, robot, tmp_path / "prior")
    alone, _ = _armid(m1, m2, robot, tmp_path / "none", "--prior", "none")
    print(f"placeholder inertials, KUKA 1 -> 2: widened {doc['prior']['widened_by']:.3g}x, {with_prior:.5f} against least squares alone {alone:.5f}")
    assert doc["prior"]["widened_by"] > 100.0
    assert with_prior <= 1.01 * alone


def test_diagnosis_sets_aside_what_pulls_away_from_the_model_and_improves_every_kuka_pair(tmp_path: Path) -> None:
    """Identified on recording 1, validated on recording 3 (another trajectory): a gravity
    tilt fits recording 1's held-out tenths but moves least squares away from the modeled
    first moments (the prior would have to widen 3x) and, taken, made recording 3 worse
    (9.91 % -> 11.4 %). It is set aside, reported as such, and the findings kept improve the
    other trajectory; errors from ``--predictions`` files against the raw torque."""
    m1, m3 = _csv(1, tmp_path), _csv(3, tmp_path)
    robot = ROBOTS / "kuka_lwr4.yaml"
    pred, doc = tmp_path / "diag.csv", tmp_path / "diag.json"
    assert main(["diagnose", str(m1), "--robot", str(robot), "--validate", str(m3), "--predictions", str(pred), "--json", str(doc)]) == 0
    after, covered = blindgen.relative_error(m3, pred)
    report = json.loads(doc.read_text())
    before = report["before"]["relative_error"]  # the declared model as `identify` fits it, at the same stamps
    print(f"KUKA 1 -> 3: before {before:.4f}, after {after:.4f}; found {[(f['effect'], f['joint']) for f in report['found']]}, "
          f"set aside {[(c['effect'], c['joint'], c['prior_widened_by'] / c['before']) for c in report['set_aside']]}")
    assert covered == 1.0
    assert any(c["effect"] == "gravity_tilt" and c["prior_widened_by"] > 1.5 * c["before"] for c in report["set_aside"])
    assert not any(f["effect"] == "gravity_tilt" for f in report["found"])
    assert after < before

"""Identification on a second independent generator: ``examples/lab_cases/gen.py``, written by a
helper session from a brief without reading armid or tests/blindgen.py (the UR5 and KUKA LWR4+
URDFs with inertials off by 10-30 %, Coulomb ``fc tanh(qd / 0.02)``, viscous friction and an
offset on every joint, 2^17-count encoders, jittery stamps, 100 Hz quantised currents or 1 kHz
torque sensors). With ``--effects declared`` the robot file declares all it has, so the
held-out error of ``armid identify --predictions`` must come within 10 % of the noise floor
(issue 15). Scored by the generator's own runner (``examples/lab_cases/run.py``), no armid code.

These cases found the Coulomb smoothing grid too coarse (0.01 or 0.03 for the true 0.02):
d2, d6 and d3 were at 1.22x, 1.53x and 1.31x the floor before the search refined it between
grid values; and the
diagnosis naming broad "Stribeck" terms on joints that never outran them.
"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from armid.cli import main

LAB = Path(__file__).resolve().parents[1] / "examples" / "lab_cases"
CASES = {  # run.py's d2, d3 and d6: currents at 100 Hz without velocity; torque at 1 kHz
    "d2": "--arm ur5 --sensor current --qd no --valid ptp --nident 2 --seed 12",
    "d3": "--arm kuka --sensor torque --qd no --valid ptp --nident 1 --seed 13",
    "d6": "--arm kuka --sensor current --qd no --valid fourier --nident 1 --seed 16",
}


def _runner():  # type: ignore[no-untyped-def]
    spec = importlib.util.spec_from_file_location("lab_run", LAB / "run.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _held_out(command: str, name: str, tmp_path: Path, *extra: str) -> tuple[float, float]:
    """``armid <command>`` on the declared-only lab case ``name``: its held-out error against
    the raw validation torque, and the noise floor, both as the generator's runner scores them."""
    case = tmp_path / name
    subprocess.run([sys.executable, str(LAB / "gen.py"), *CASES[name].split(), "--effects", "declared", "--out", str(case)],
                   check=True, capture_output=True)
    ident = sorted(str(p) for p in case.glob("ident?.csv"))
    pred = tmp_path / "pred.csv"
    assert main([command, *ident, "--robot", str(case / "robot.yaml"), "--validate", str(case / "valid.csv"),
                 "--predictions", str(pred), *extra]) == 0
    run = _runner()
    joints = yaml.safe_load((case / "robot.yaml").read_text())["joints"]
    kt = np.array([float(j.get("torque_constant", 1.0)) for j in joints])
    valid, clean = run.load(case / "valid.csv"), run.load(case / "valid_clean.csv")
    tau, tau_clean = run.raw_tau(valid, len(joints), kt), run.raw_tau(clean, len(joints), kt)
    scored = run.score(pred, valid["t"], tau, len(joints))
    assert scored["coverage"] >= 0.99, scored
    return scored["error"], float(np.linalg.norm(tau_clean - tau) / np.linalg.norm(tau))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["d2", "d6"])  # 1 kHz: d3 below, through the diagnosis
def test_declared_lab_case_is_predicted_at_the_noise_floor(name: str, tmp_path: Path) -> None:
    error, floor = _held_out("identify", name, tmp_path)
    assert error <= 1.10 * floor, f"{name}: held-out {100 * error:.3f} % against a floor of {100 * floor:.3f} %"


@pytest.mark.slow
def test_diagnosis_of_a_declared_lab_case_invents_nothing(tmp_path: Path) -> None:
    """A 1 kHz log without velocity where every effect is declared: the diagnosis must name
    nothing. Before the Stribeck velocities were limited to those the joint's motion outruns,
    it named a Stribeck term at 0.75 rad/s on joint 2 (and at 1 rad/s on three joints of d8)."""
    out = tmp_path / "dg.json"
    error, floor = _held_out("diagnose", "d3", tmp_path, "--json", str(out))
    doc = json.loads(out.read_text())
    assert doc["found"] == [], doc["found"]
    assert error <= 1.10 * floor, f"held-out {100 * error:.3f} % against a floor of {100 * floor:.3f} %"

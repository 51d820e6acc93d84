"""Issue 62: reports a lab can read, from a small simulated identification (no demo).

A random 3-joint arm with a prismatic second joint, simulated by the model's own inverse
dynamics on epoch time stamps (a logger's: 1.79e9 s) with seeded torque noise, identified on one
run and validated on another; then the identification report (with the physically consistent
estimate) and the diagnosis report. Each names one validation error per model, writes every
error in percent, labels every axis with the joint's unit (N*m and rad for the revolute joints,
N and m for the prismatic one) and plots time from the first sample, and a diagnosis plot says
which samples it shows.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import pytest
from conftest import random_robot

from armid.identify.dynamics import inverse_dynamics
from armid.identify.preprocess import Prepared, prepare
from armid.identify.recordings import Recording
from armid.identify.robot import Robot
from armid.identify.trajectories import random_fourier_trajectory

matplotlib.use("Agg")

EPOCH_S = 1.79e9
PERIOD_S = 0.004
PERCENT = re.compile(r"\d+(\.\d+)? %")
FRACTION = re.compile(r"(?<![\d.])0\.\d+(?![\d.]| ?%)")
"""A bare fraction such as 0.02256 where an error is written (the parameter tables excepted)."""


def _run(robot: Robot, seed: int, start_s: float) -> Prepared:
    traj = random_fourier_trajectory(robot, harmonics=4, base_frequency_hz=0.2, fill=0.7, seed=seed)
    t = np.arange(0.0, 10.0, PERIOD_S)
    q, qd, qdd = traj.evaluate(t)
    tau = inverse_dynamics(robot, q, qd, qdd)
    tau += 0.01 * np.random.default_rng(seed + 100).normal(size=tau.shape) * np.std(tau, axis=0)
    return prepare(Recording(f"run_{seed}.csv", start_s + t, q, tau, qd), robot)


@pytest.fixture(scope="module")
def identified() -> tuple[Robot, Prepared, Prepared, Any]:
    from armid.identify.identification import identify

    robot = random_robot(3, "dh", 1, 21)
    ident, valid = _run(robot, 1, EPOCH_S), _run(robot, 2, EPOCH_S + 3600.0)
    return robot, ident, valid, identify(robot, [ident], [valid])


class Figures:
    """Every figure a report saves: its axes' labels and the x extent of what they plot."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        from matplotlib.figure import Figure

        self.saved: list[dict[str, Any]] = []
        save = Figure.savefig

        def record(fig: Figure, path: Any, *args: Any, **kwargs: Any) -> Any:
            axes = []
            for ax in fig.axes:
                xs = [np.asarray(line.get_xdata(), float) for line in ax.get_lines() if np.size(line.get_xdata()) > 2]
                axes.append({"x": ax.get_xlabel(), "y": ax.get_ylabel(), "x_min": min((float(x.min()) for x in xs), default=None),
                             "x_max": max((float(x.max()) for x in xs), default=None)})
            self.saved.append({"name": Path(path).name, "title": fig._suptitle.get_text() if fig._suptitle else "", "axes": axes})
            return save(fig, path, *args, **kwargs)

        monkeypatch.setattr(Figure, "savefig", record)


def _section(text: str, title: str) -> str:
    return text.split(f"## {title}", 1)[1].split("\n## ", 1)[0]


def _table_rows(section: str) -> list[list[str]]:
    return [[c.strip() for c in line.strip().strip("|").split("|")] for line in section.splitlines()
            if line.startswith("|") and not line.startswith("|---")]


def _check_errors_are_percent(text: str) -> None:
    """No error written as a fraction: on a line that names an error, nor in a table row of fit
    or validation figures (the old report's ``| validation | 0.02241 |``)."""
    for line in text.splitlines():
        first = line.strip("| ").lower()
        if "error" in line.lower() or (line.startswith("|") and first.startswith(("fit", "validation"))):
            assert not FRACTION.search(line.replace("|tau - tau_hat| / |tau|", "")), line


def test_identification_report_names_one_error_per_model_in_percent_with_units(identified: Any, tmp_path: Path,
                                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    from armid.identify.feasible import feasible_estimate
    from armid.report import percent, write_report

    robot, ident, valid, result = identified
    doc = result.to_json()
    doc["feasible"] = feasible_estimate(result, [valid]).to_json()
    figures = Figures(monkeypatch)
    path = write_report(result, doc, list(valid.segments), tmp_path, "validation data", identification=list(ident.segments))
    text = path.read_text()

    # one fit error and one validation error per model, named (which model, which data), in percent
    errors = _section(text, "Errors")
    header, *rows = _table_rows(errors)
    assert header == ["model (identified on run_1.csv)", "fit error (on run_1.csv)", "validation error (on run_2.csv)"]
    models = [r for r in rows if r[0].startswith(("least squares", "physically consistent"))]
    assert [r[0].split(" ")[0] for r in models] == ["least", "physically"]
    for row in models:
        assert all(PERCENT.fullmatch(cell) for cell in row[1:]), row
    assert models[0][1:] == [percent(doc["fit"]["relative_error"]), percent(doc["validation"]["relative_error"])]
    assert text.lower().count("validation error") == 1 and text.lower().count("fit error") == 1
    assert text.count("condition number") == 1
    _check_errors_are_percent(text)
    # the per-joint rms carries each joint's unit
    units = {r[0]: r[1] for r in _table_rows(errors) if r[0] in ("1", "2", "3")}
    assert units == {"1": "N*m", "2": "N", "3": "N*m"}

    # plots: the joint's unit on every torque axis, time from the first sample (not the epoch)
    plots = [f for f in figures.saved if f["name"].startswith("joint")]
    assert [f["name"] for f in plots] == ["joint1.png", "joint2.png", "joint3.png"]
    for j, fig in enumerate(plots):
        unit = "N" if j == 1 else "N*m"
        torque, residual = fig["axes"]
        assert torque["y"] == f"tau{j + 1} [{unit}]" and residual["y"] == f"residual [{unit}]"
        assert residual["x"].endswith("[s]") and "first sample" in residual["x"]
        assert torque["x_min"] == 0.0 and 9.0 < torque["x_max"] < 10.0
        assert "or N" not in torque["y"]


def test_diagnosis_report_says_which_samples_each_plot_shows_with_units(identified: Any, tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    from armid.identify.diagnosis.search import diagnose
    from armid.report import percent, write_diagnosis_report

    robot, ident, valid, _ = identified
    diag = diagnose(robot, [ident], [valid])
    figures = Figures(monkeypatch)
    text = write_diagnosis_report(diag, robot, tmp_path, identified_on="run 1", validated_on="run 2").read_text()

    # one validation error per model: the declared one, and the one with the findings
    head = text.split("## Findings", 1)[0]
    rows = [r for r in _table_rows(head) if r[0] != "model"]
    assert len(rows) == 2 and rows[0][1] == percent(diag.before["relative_error"])
    assert rows[1][1].startswith(percent(diag.after["relative_error"]).join("**") if diag.found else percent(diag.after["relative_error"]))
    assert "identified on run 1" in head and "samples of run 2" in head
    _check_errors_are_percent(text)

    plots = [f for f in figures.saved if f["name"].startswith("diagnosis_joint")]
    assert len(plots) == 3
    for j, fig in enumerate(plots):
        velocity, position, acceleration, time = fig["axes"]
        prismatic = j == 1
        assert velocity["y"] == f"residual tau{j + 1} [{'N' if prismatic else 'N*m'}]"
        assert velocity["x"] == f"velocity qd{j + 1} [{'m/s' if prismatic else 'rad/s'}]"
        assert position["x"] == f"position q{j + 1} [{'m' if prismatic else 'rad'}]"
        assert acceleration["x"] == f"acceleration qdd{j + 1} [{'m/s^2' if prismatic else 'rad/s^2'}]"
        assert time["x"].endswith("[s]") and time["x_min"] is not None and 0.0 <= time["x_min"] < 1.0 and time["x_max"] < 20.0
        # which samples: the moving ones of the validation, said in the plot and in the report
        assert re.search(r"the [\d,]+ of [\d,]+ validation samples where the joint moves|all [\d,]+ validation samples", fig["title"])
        assert f"- joint {j + 1}: " in text


def test_a_thinned_plot_says_every_kth_sample() -> None:
    from armid.report import MAX_POINTS, _shown

    used = np.ones(3 * MAX_POINTS + 5, bool)
    used[:5] = False
    index, text = _shown(used)
    assert index.size <= MAX_POINTS
    assert text == f"the {3 * MAX_POINTS:,} of {used.size:,} validation samples where the joint moves (clear of rest and of a velocity " \
                   f"reversal: the samples the diagnosis scores), every 3rd of them ({index.size:,} shown)"


def test_recordings_are_laid_end_to_end_from_zero() -> None:
    from armid.report import elapsed

    t = np.concatenate([EPOCH_S + np.arange(0.0, 2.0, 0.5), EPOCH_S + 3600.0 + np.arange(0.0, 1.0, 0.5)])
    x, joins = elapsed(t)
    assert np.allclose(x, [0.0, 0.5, 1.0, 1.5, 2.0, 2.5]) and joins == [2.0]


def test_truth_check_names_the_parameters_that_miss() -> None:
    from armid.demo import _truth_test, truth_lines

    truth = np.zeros(4)
    values = np.array([0.1, -0.2, 0.5, 0.05])
    test = _truth_test(values, np.diag([0.01, 0.01, 0.01, 0.01]), truth, ["m1", "m2", "Izz3", "fv1"])
    assert [m["name"] for m in test["misses"]] == ["Izz3"] and test["misses"][0]["z"] == pytest.approx(5.0)
    text = "\n".join(truth_lines("Whole-arm model", test))
    assert "`Izz3` | 0.5 | 0 | 0.1 | +5.00 |" in text
    assert "(chi2/dof 7.56), p < 0.001: **the joint test rejects the standard deviations" in text


def test_without_the_identification_samples_the_consistency_figures_are_named(identified: Any, tmp_path: Path) -> None:
    """``armid identify --report`` with ``--validate`` hands the report the validation samples
    alone: the physically consistent model's validation error is at the stamps as the least
    squares one is; its fit error, on the fitted equations only, is said to be so, as is every
    figure of the consistency check's own table."""
    from armid.identify.feasible import feasible_estimate
    from armid.report import percent, write_report

    _, _, valid, result = identified
    doc = result.to_json()
    doc["feasible"] = feasible_estimate(result, [valid]).to_json()
    text = write_report(result, doc, list(valid.segments), tmp_path, "validation data").read_text()
    rows = _table_rows(_section(text, "Errors"))
    consistent = next(r for r in rows if r[0].startswith("physically consistent"))
    assert consistent[1] == "— (on the fitted equations: below)" and PERCENT.fullmatch(consistent[2])
    section = _section(text, "Physical consistency")
    assert "| relative error (not at the stamps) |" in section and "not at the samples' stamps" in section
    ls = doc["feasible"]["least_squares"]["validation"]["relative_error"]
    assert f"| held-out (validation) data | {percent(ls, 4)} |" in section
    assert text.lower().count("validation error") == 1 and text.lower().count("fit error") == 1
    _check_errors_are_percent(text)

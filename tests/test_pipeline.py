"""Issue 32: one recording gives one answer whichever command reads it.

Two runs of the simulated PUMA 560 (the shipped example's, with seeded sensor noise so that
``--lowpass auto`` filters), each recorded as MCAP by the recorder ``armid record`` uses and
exported to CSV, go through every entry point: ``armid identify`` and ``armid diagnose`` (CSV
and MCAP), ``armid serve``'s whole-arm path (its own ``process``, both recipes), the demo's
path (:func:`armid.experiments.prepared_runs` and :func:`~armid.experiments.identify_whole_arm`)
and ``armid estimate --replay`` (CSV and MCAP). For the same recipe every one gives the same
parameters to 1e-12; a recipe that differs in one option gives other parameters (the
comparison is not blind).
"""

from __future__ import annotations

import json
import socket
from pathlib import Path

import numpy as np
import pytest

from armid.cli import build_parser, main

ROOT = Path(__file__).resolve().parent.parent
ROBOT = ROOT / "config" / "robots" / "puma560.yaml"
PERIOD_S = 0.002
ROWS = 3000
"""Samples per run (6 s at 2 ms): enough for 52 base parameters, quick to identify."""
SAME = 1e-12


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _relative(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / max(float(np.linalg.norm(b)), 1e-300))


def _records(csv: str, first: int, seed: int) -> list[bytes]:
    """The example run as the drives stream it: 2 ms cycles numbered from ``first``, encoder and
    current noise drawn from ``seed``."""
    from armid.schema.joint_state import Sample
    from armid.schema.joint_states import JointStates

    a = np.loadtxt(ROOT / "examples" / csv, delimiter=",", skiprows=1)[:ROWS]
    rng = np.random.default_rng(seed)
    q = a[:, 1:7] + rng.normal(0.0, 2e-4, (ROWS, 6))
    qd = a[:, 7:13] + rng.normal(0.0, 2e-2, (ROWS, 6))
    tau = a[:, 13:19] + rng.normal(0.0, 0.05, (ROWS, 6))
    ones, zeros = np.ones(6, bool), np.zeros(6)
    return [JointStates.of_sample(first + k, Sample(first + k, PERIOD_S * k, ones, q[k], qd[k], ones, zeros, zeros, np.full(6, 0x27, np.int64),
                                               torque=tau[k])).pack() for k in range(ROWS)]


def _write_run(records: list[bytes], folder: Path) -> tuple[Path, Path]:
    """The run as ``armid record`` writes it (MCAP), and exported to CSV from what the MCAP holds
    (every float written as the shortest text that reads back as itself)."""
    from armid.daq.recorder import McapRecorder
    from armid.io.recordings import read_recording
    from armid.io.robot_file import load_robot
    from armid.schema.joint_states import JointStates

    robot = load_robot(ROBOT)
    folder.mkdir(parents=True)
    mcap = folder / "run.mcap"
    rec = McapRecorder(mcap, [j.name for j in robot.joints], {"robot": robot.name, "period_s": PERIOD_S})
    try:
        for data in records:
            rec.write(JointStates.unpack(data))
    finally:
        rec.close()
    r = read_recording(mcap, robot)
    assert r.qd is not None and r.t.size == ROWS
    header = ["t", *(f"{c}{j + 1}" for c in ("q", "qd", "tau") for j in range(6))]
    rows = np.column_stack([r.t, r.q, r.qd, r.tau])
    csv = folder / "run.csv"
    csv.write_text(",".join(header) + "\n" + "".join(",".join(repr(float(x)) for x in row) + "\n" for row in rows))
    return mcap, csv


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """Two runs (``a`` to identify on, ``b`` to validate on), each as records, MCAP and CSV."""
    base = tmp_path_factory.mktemp("runs")
    out: dict[str, object] = {}
    for name, csv, first, seed in (("a", "puma560_excitation.csv", 0, 1), ("b", "puma560_validation.csv", ROWS + 100, 2)):
        records = _records(csv, first, seed)
        mcap, csv_path = _write_run(records, base / name)
        out[name] = {"records": records, "mcap": mcap, "csv": csv_path, "first": first}
    return out


def _cli_json(tmp_path: Path, name: str, argv: list[str]) -> dict:
    out = tmp_path / f"{name}.json"
    assert main([*argv, "--robot", str(ROBOT), "--json", str(out)]) == 0
    return json.loads(out.read_text())


def _values(doc: dict) -> tuple[np.ndarray, np.ndarray]:
    """An ``identify --json`` document's base parameters and their std."""
    return (np.array([b["value"] for b in doc["base_parameters"]], float), np.array([b["std"] for b in doc["base_parameters"]], float))


def _same(name: str, beta: np.ndarray, std: np.ndarray, reference: tuple[np.ndarray, np.ndarray]) -> None:
    assert beta.shape == reference[0].shape, name
    assert _relative(beta, reference[0]) <= SAME, (name, "value", _relative(beta, reference[0]))
    assert _relative(std, reference[1]) <= SAME, (name, "std", _relative(std, reference[1]))


def _service_fits(runs: dict, tmp_path: Path, whole_arm: str) -> dict:
    """``armid serve``'s whole-arm fits after runs ``a`` and ``b`` (its own ``process``; a real
    Zenoh session on loopback): run ``a``'s fit is validated on ``b``."""
    import zenoh

    from armid.daq.experiment_stream import CollectedExperiment
    from armid.daq.stream import session_config
    from armid.io.robot_file import load_robot
    from armid.schema.joint_states import JointStates
    from armid.serve import EstimatorService, ServiceOptions

    session = zenoh.open(session_config(listen=[f"tcp/127.0.0.1:{_free_port()}"]))
    service = EstimatorService(session, load_robot(ROBOT), tmp_path / f"serve-{whole_arm}", ServiceOptions(whole_arm=whole_arm, payload=False))
    experiment = {"kind": "whole_arm", "metadata": {"period_s": PERIOD_S}}
    try:
        for name in ("a", "b"):
            r = runs[name]
            seqs = list(range(r["first"], r["first"] + ROWS))
            stop = {"completed": True, "experiment": experiment, "window_s": [0.0, 1e9], "first_cycle": r["first"],
                    "first_sequence": seqs[0], "last_sequence": seqs[-1]}
            records = JointStates.unpack(b"".join(r["records"]))  # the payloads back to back: one payload of many records
            service.process(CollectedExperiment(name, {"experiment": experiment}, stop, records, 0, [[seqs[0], seqs[-1]]]))
        assert not service.errors, service.errors
        assert service._whole_docs["a"]["validated_on"] == ["b"]
        return dict(service.whole_fits)
    finally:
        service.close()
        session.close()


def _replay(tmp_path: Path, name: str, params: Path, data: Path) -> list[dict]:
    out = tmp_path / f"{name}.jsonl"
    assert main(["estimate", "--robot", str(ROBOT), "--params", str(params), "--replay", str(data), "--out", str(out)]) == 0
    return [json.loads(line) for line in out.read_text().splitlines()]


def _column(docs: list[dict], key: str) -> np.ndarray:
    return np.array([np.full(3, np.nan) if d[key] is None and key == "com" else (np.nan if d[key] is None else d[key]) for d in docs], float)


def test_the_command_lines_defaults_are_the_user_log_recipe() -> None:
    """The library's recipe for a user's log is what ``armid identify`` and ``armid diagnose``
    do unless told otherwise, and ``armid serve --whole-arm`` names exactly the recipes there are."""
    from dataclasses import replace

    from armid.commands.identify import recipe_from_arguments
    from armid.pipeline import DRIVE_RUN, RECIPES, USER_LOG
    from armid.serve import WHOLE_ARM_PIPELINES

    def recipe(command: str, *flags: str) -> object:
        args = build_parser().parse_args([command, "x.csv", "--robot", "r.yaml", "--validate", "v.csv", *flags])
        return recipe_from_arguments(args, weighting=args.weighting, prior=args.prior) if command == "identify" else recipe_from_arguments(args)

    for command in ("identify", "diagnose"):
        assert recipe(command) == USER_LOG, command
        # --recipe drives is what the demo and the service do (a flag left out keeps the recipe's value)
        assert recipe(command, "--recipe", "drives") == DRIVE_RUN, command
        changed = recipe(command, "--recipe", "drives", "--lowpass", "20", "--max-gap-factor", "5")
        assert changed == DRIVE_RUN.with_options(lowpass_hz=20.0, max_gap_factor=5.0), command
        assert recipe(command, "--lowpass", "off", "--torque-hold") == replace(USER_LOG, prepare=replace(USER_LOG.prepare, lowpass_hz="off", torque_hold=True))
    assert recipe("identify", "--weighting", "ols", "--prior", "none") == USER_LOG.with_options(weighting="ols", prior="none")
    assert WHOLE_ARM_PIPELINES == tuple(RECIPES)
    commands = build_parser()._subparsers._group_actions[0].choices
    whole_arm = next(a for a in commands["serve"]._actions if a.dest == "whole_arm")
    assert tuple(whole_arm.choices) == tuple(RECIPES)
    for command in ("identify", "diagnose"):
        assert tuple(next(a for a in commands[command]._actions if a.dest == "recipe").choices) == tuple(RECIPES), command
    # and the library's own defaults are the command line's (issue 32: lowpass_hz was None)
    from armid.identify.identification import IdentifyOptions
    from armid.identify.preprocess import PrepareOptions

    assert USER_LOG.prepare == PrepareOptions() and USER_LOG.identify == IdentifyOptions()


@pytest.mark.slow
def test_one_recording_gives_one_answer_through_every_entry_point_as_a_user_log(runs: dict, tmp_path: Path) -> None:
    """The user-log recipe (the command line's defaults; the recording's currents held over a
    period, as an MCAP says and ``--torque-hold`` says of the CSV): identify and diagnose on the
    CSV and on the MCAP, the service's ``--whole-arm identify`` path and the library's pipeline
    give the same parameters, and ``estimate --replay`` the same payload estimates."""
    from armid import pipeline
    from armid.io.robot_file import load_robot

    a, b = runs["a"], runs["b"]
    csv = _cli_json(tmp_path, "csv", ["identify", str(a["csv"]), "--torque-hold", "--validate", str(b["csv"])])
    mcap = _cli_json(tmp_path, "mcap", ["identify", str(a["mcap"]), "--validate", str(b["mcap"])])
    reference = _values(mcap)
    _same("identify CSV", *_values(csv), reference)
    assert "low-pass" in json.dumps(mcap["filtering"]), "the noise must make --lowpass auto filter"

    robot = load_robot(ROBOT)
    inputs = pipeline.load(robot, pipeline.USER_LOG, [a["mcap"]], [b["mcap"]])
    fit, _ = pipeline.identify(robot, inputs.experiments, inputs.validation, pipeline.USER_LOG)
    _same("pipeline USER_LOG", fit.estimate.beta, fit.estimate.std, reference)

    served = _service_fits(runs, tmp_path, "identify")["a"]
    _same("serve --whole-arm identify", served.estimate.beta, served.estimate.std, reference)
    assert abs(served.validation["relative_error"] - mcap["validation"]["relative_error"]) <= SAME

    for name, data in (("diagnose CSV", ["diagnose", str(a["csv"]), "--torque-hold", "--validate", str(b["csv"])]),
                       ("diagnose MCAP", ["diagnose", str(a["mcap"]), "--validate", str(b["mcap"])])):
        before = _cli_json(tmp_path, name.replace(" ", "-"), data)["before"]  # the declared model as identify fits it
        assert abs(before["relative_error"] - mcap["validation"]["relative_error"]) <= SAME * mcap["validation"]["relative_error"], name
        assert _relative(np.array(before["relative"]), np.array(mcap["validation"]["relative"])) <= SAME, name

    from_csv = _replay(tmp_path, "replay-csv", tmp_path / "csv.json", a["csv"])
    from_mcap = _replay(tmp_path, "replay-mcap", tmp_path / "mcap.json", a["mcap"])
    assert len(from_csv) == len(from_mcap) > 0
    for key in ("record_time", "mass", "mass_std", "com"):
        x, y = _column(from_csv, key), _column(from_mcap, key)
        assert np.array_equal(np.isnan(x), np.isnan(y)), key
        assert _relative(np.nan_to_num(x), np.nan_to_num(y)) <= SAME, key

    # not blind: the same data with one option changed (the CSV's torque taken as sampled) differs
    unheld = _cli_json(tmp_path, "unheld", ["identify", str(a["csv"]), "--validate", str(b["csv"])])
    assert _relative(_values(unheld)[0], reference[0]) > 1e3 * SAME


@pytest.mark.slow
def test_one_recording_gives_one_answer_through_every_entry_point_as_a_drive_run(runs: dict, tmp_path: Path) -> None:
    """The drive-run recipe: the demo's path (its run reports, the excitation window, its fit),
    the service's ``--whole-arm drives`` path and the library's pipeline on the CSV give the
    same parameters; the user-log recipe on the same runs gives others."""
    from armid import pipeline
    from armid.daq.excite import RunReport
    from armid.experiments import identify_whole_arm, prepared_runs
    from armid.io.robot_file import load_robot

    robot = load_robot(ROBOT)
    reports = [RunReport(name, True, None, None, ROWS, ROWS, runs[name]["first"], [], [], [], str(runs[name]["mcap"]), (0.0, 1e9))
               for name in ("a", "b")]
    prepared = prepared_runs(reports, robot, PERIOD_S)
    demo = identify_whole_arm(robot, prepared["a"], [prepared["b"]])
    reference = (demo.estimate.beta, demo.estimate.std)

    served = _service_fits(runs, tmp_path, "drives")["a"]
    _same("serve --whole-arm drives", served.estimate.beta, served.estimate.std, reference)
    assert abs(served.validation["relative_error"] - demo.validation["relative_error"]) <= SAME  # type: ignore[index]

    inputs = pipeline.load(robot, pipeline.DRIVE_RUN, [runs["a"]["csv"]], [runs["b"]["csv"]])
    fit, _ = pipeline.identify(robot, inputs.experiments, inputs.validation, pipeline.DRIVE_RUN)
    _same("pipeline DRIVE_RUN on the CSV", fit.estimate.beta, fit.estimate.std, reference)

    user, _ = pipeline.identify(robot, inputs.experiments, inputs.validation, pipeline.USER_LOG)
    assert _relative(user.estimate.beta, reference[0]) > 1e3 * SAME  # not blind: another recipe, other parameters

"""A recording of a run that ended on a stop says so wherever it is read (issue 62).

The recording is the shipped PUMA 560 example written by the recorder itself
(``daq.recorder.McapRecorder``), cut after 4,157 records and closed as ``armid excite`` closes
a stopped run: its ``armid.run_end`` metadata gives the stop's line. ``armid identify`` (text
and JSON), the pipeline every command reads through (``diagnose``, the demo, the service),
``armid estimate --replay`` and a fleet's row all name the file and the line.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from armid.cli import main
from armid.daq.recorder import McapRecorder
from armid.drivers.interface import Sample
from armid.io.recordings import read_mcap_arrays, read_recording
from armid.io.robot_file import load_robot
from armid.schema.joint_states import JointStates

ROOT = Path(__file__).resolve().parent.parent
PUMA = ROOT / "config" / "robots" / "puma560.yaml"
EXAMPLE = ROOT / "examples" / "puma560_excitation.csv"
STOP = "joint 3: no frames for 3 cycles at cycle 4157"
RECORDS = 4157


def _record(path: Path, end: dict[str, object] | None) -> Path:
    """The example's first records as ``armid excite`` records them, closed with ``end``."""
    robot = load_robot(PUMA)
    rec = read_recording(EXAMPLE, robot)
    kt = np.array([j.torque_constant for j in robot.joints])
    recorder = McapRecorder(path, [j.name for j in robot.joints], {"robot": robot.name, "period_s": 0.002})
    n = robot.n_joints
    assert rec.qd is not None
    for k in range(RECORDS):
        current = rec.tau[k] / kt
        recorder.write(JointStates.of_sample(k, Sample(k, float(rec.t[k]), np.ones(n, bool), rec.q[k], rec.qd[k], np.ones(n, bool),
                                                  current, current, np.full(n, 0x27), rec.tau[k])))
    recorder.close(end)
    return path


@pytest.fixture(scope="module")
def stopped(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _record(tmp_path_factory.mktemp("stopped") / "run.mcap", {"completed": False, "stop": STOP, "stop_cycle": RECORDS})


def test_the_recorder_writes_how_the_run_ended_and_the_reader_carries_it(stopped: Path, tmp_path: Path) -> None:
    arrays, metadata, notes = read_mcap_arrays(stopped)
    assert not notes and arrays["sequence"].size == RECORDS  # the end record costs no record
    assert metadata["robot"] == "puma560" and metadata["completed"] == "false" and metadata["stop"] == STOP
    assert metadata["stop_cycle"] == str(RECORDS) and metadata["records"] == str(RECORDS)
    assert read_recording(stopped, load_robot(PUMA)).stopped == STOP
    completed = _record(tmp_path / "completed.mcap", {"completed": True})
    assert read_recording(completed, load_robot(PUMA)).stopped is None
    assert read_mcap_arrays(completed)[1]["completed"] == "true"
    unsaid = _record(tmp_path / "unsaid.mcap", None)  # armid record, the service's copy: no end record
    assert "completed" not in read_mcap_arrays(unsaid)[1] and read_recording(unsaid, load_robot(PUMA)).stopped is None


def test_identify_says_the_run_ended_on_a_stop_in_its_output_and_its_json(stopped: Path, tmp_path: Path,
                                                                          capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "identify.json"
    assert main(["identify", str(stopped), "--robot", str(PUMA), "--json", str(out)]) == 0
    err = capsys.readouterr().err
    assert f"armid identify: warning: {stopped}: the run ended on a stop: {STOP}" in err, err
    doc = json.loads(out.read_text())
    assert doc["recordings"] == [{"path": str(stopped), "role": "identification", "stopped": STOP}]


def test_every_reader_path_names_the_file_and_the_stop(stopped: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from armid import pipeline
    from armid.fleet.outputs import in_order, write_parameters
    from armid.fleet.task import Job, identify_recording

    said = f"{stopped}: the run ended on a stop: {STOP}"
    robot = load_robot(PUMA)
    # the pipeline's read and load: diagnose, the demo, the service and the checks read through them
    inputs = pipeline.load(robot, pipeline.USER_LOG, [stopped])
    assert said in inputs.warnings and inputs.stopped == {str(stopped): STOP}
    _, found = pipeline.load_run(stopped, robot, pipeline.DRIVE_RUN)
    assert said in found
    # estimate --replay reads the MCAP's records itself
    params = tmp_path / "identify.json"
    assert main(["identify", str(stopped), "--robot", str(PUMA), "--json", str(params)]) == 0
    capsys.readouterr()
    assert main(["estimate", "--robot", str(PUMA), "--params", str(params), "--replay", str(stopped), "--out", str(tmp_path / "e.jsonl")]) in (0, 2)
    assert f"armid estimate: warning: {said}" in capsys.readouterr().err
    # a fleet's row: the recording fails with the stop's line as its error, never tracked
    arm = tmp_path / "lab" / "puma"
    arm.mkdir(parents=True)
    (arm / "robot.yaml").write_text(PUMA.read_text())
    (arm / "run.mcap").write_bytes(stopped.read_bytes())
    result = identify_recording(Job("puma", str(tmp_path / "lab"), "puma/run.mcap", str(arm / "robot.yaml")))
    assert not result.ok and result.error == f"the run ended on a stop: {STOP}; not tracked" and not result.quantities
    write_parameters(tmp_path / "parameters.csv", in_order([result]))
    [row] = list(csv.DictReader((tmp_path / "parameters.csv").open()))
    assert row["status"] == "failed" and STOP in row["error"]


def test_a_stopped_excitation_run_writes_its_stop_line_into_its_recording(tmp_path: Path) -> None:
    """``ExcitationSession.run`` closes the recording with how the run ended: the stop's line
    as ``armid excite`` prints it after ``STOPPED:``."""
    from armid.daq.excite import ExcitationSession

    class _Stopped(ExcitationSession):
        def __init__(self) -> None:  # only what _run_end reads
            from types import SimpleNamespace

            self.control = SimpleNamespace(stop_reason=STOP, stop_cycle=RECORDS)  # type: ignore[assignment]

    end = _Stopped()._run_end(None)
    assert end == {"completed": False, "stop": STOP, "stop_cycle": RECORDS}
    interrupted = _Stopped()
    interrupted.control.stop_reason = None  # type: ignore[misc]
    assert interrupted._run_end(KeyboardInterrupt()) == {"completed": False, "stop": "interrupted: KeyboardInterrupt", "stop_cycle": None}

"""``armid watch`` as a lab's live view (issue 66): the parameters the estimator service
publishes, every set of them, the payload in words, findings and drive faults, read off its
screen through a pseudo-terminal. Real parts: ``armid watch`` as a process on a pty, the
estimator service (:class:`armid.serve.EstimatorService`) in a real Zenoh session on a
loopback endpoint (multicast scouting off), its analysis thread identifying the shipped example
recordings, its payload estimator fed on the live ``joint_state`` stream."""

from __future__ import annotations

import fcntl
import json
import os
import pty
import re
import socket
import struct
import subprocess
import sys
import termios
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
ROBOT = ROOT / "config" / "robots" / "puma560.yaml"
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]|\x1b[()][A-Z0-9]|\r")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Screen:
    """What a process wrote to its terminal (a pty of ``rows`` x ``cols``), escape sequences taken out."""

    def __init__(self, argv: list[str], rows: int = 120, cols: int = 240) -> None:
        master, slave = pty.openpty()
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", rows, cols, 0, 0))
        env = {**os.environ, "PYTHONPATH": str(ROOT), "TERM": "xterm-256color", "COLUMNS": str(cols), "LINES": str(rows)}
        self.proc = subprocess.Popen(argv, stdin=slave, stdout=slave, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env)
        os.close(slave)
        self.master, self.raw = master, bytearray()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while True:
            try:
                data = os.read(self.master, 65536)
            except OSError:  # the process closed its end
                return
            if not data:
                return
            self.raw += data

    def text(self) -> str:
        return ANSI.sub("", self.raw.decode(errors="replace"))

    def last_frame(self) -> str:
        """The last full view drawn (each starts with the line naming the key space)."""
        text = self.text()
        return text[text.rfind("armid/puma560  records"):]

    def wait(self, predicate: Callable[[], object], seconds: float) -> bool:
        deadline = time.monotonic() + seconds
        while not predicate() and time.monotonic() < deadline:
            time.sleep(0.1)
        return bool(predicate())


def _records(csv: str, first: int) -> tuple[object, np.ndarray]:
    from armid.schema.joint_state import Sample
    from armid.schema.joint_states import JointStates

    a = np.loadtxt(ROOT / "examples" / csv, delimiter=",", skiprows=1)
    parts = [JointStates.of_sample(first + k, Sample(first + k, row[0], np.ones(6, bool), row[1:7], row[7:13], np.ones(6, bool), np.zeros(6),
                                                     np.zeros(6), np.full(6, 0x27, np.int64), torque=row[13:19])) for k, row in enumerate(a)]
    return JointStates.concat(parts), a


def test_watch_shows_every_published_parameter_set_the_payload_and_faults_in_words(tmp_path: Path) -> None:
    """During the service's run, ``armid watch`` on a terminal shows each parameter set the
    service publishes (a refused run, then two whole-arm runs: the run, what it gave), the
    newest set's every base parameter as value +- std with the run that gave it, the payload
    with its band and its verdict, and a drive fault and an experiment's start in words; no
    event's raw document (a trajectory's coefficients) reaches the screen."""
    import zenoh

    from armid.daq.experiment_stream import CollectedExperiment
    from armid.daq.stream import Stream, key, session_config
    from armid.io.robot_file import load_robot
    from armid.schema.joint_states import JointStates
    from armid.serve import EstimatorService
    from armid.watch import payload_line

    robot = load_robot(ROBOT)
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    session = zenoh.open(session_config(listen=[endpoint]))
    docs: list[dict] = []
    payloads: list[dict] = []
    service = EstimatorService(session, robot, tmp_path / "serve", on_publish=docs.append)
    publisher = zenoh.open(session_config(connect=[endpoint]))
    stream = Stream(publisher, robot.name, "excite", lambda: {})
    listener = publisher.declare_subscriber(key(robot.name, "estimate/payload"), lambda s: payloads.append(json.loads(s.payload.to_bytes())))
    screen = Screen([sys.executable, "-m", "armid.cli", "watch", "--robot", robot.name, "--zenoh-connect", endpoint, "--duration", "300"])
    experiment = {"kind": "whole_arm", "metadata": {"period_s": 0.002}, "trajectory": {"fourier": {"a": [[0.123456, 0.654321]]}}}
    try:
        assert screen.wait(lambda: "alive: estimator, excite" in screen.text(), 60), screen.text()[-3000:]
        stream.event("start", run="whole", duration_s=10.0, experiment=experiment)
        stream.event("fault", joint=3, node=4, code=0x2310, meaning="over-current", type="EmergencyFault")
        first, _ = _records("puma560_excitation.csv", 0)
        still = JointStates.concat([first[:1]] * 600)  # nothing moves: refused, with its reason
        still = replace(still, sequence=np.arange(600), time=0.002 * np.arange(600))
        runs = [("still", still), ("whole", _records("puma560_excitation.csv", 1000)[0]), ("whole", _records("puma560_validation.csv", 7000)[0])]
        for name, records in runs:
            stop = {"completed": True, "experiment": experiment, "window_s": [0.0, 10.0], "first_sequence": int(records.sequence[0])}
            service._jobs.append(CollectedExperiment(name, {"experiment": experiment}, stop, records, 0, [[int(records.sequence[0]), int(records.sequence[-1])]]))
        service._job_ready.set()
        assert screen.wait(lambda: len(docs) == 3, 240), service.errors
        assert service.payload_service is not None  # started on the first whole-arm fit
        live, _ = _records("puma560_excitation.csv", 20000)
        live.position[500, 1] = np.nan  # one record the estimator cannot use: counted, and the view says so
        for k in range(0, len(live), 10):  # the arm goes on: records on the live stream, ten a put
            stream.publish(live[k : k + 10])
            time.sleep(0.004)
        assert screen.wait(lambda: payloads and payloads[-1]["sequence"] >= 20000 + len(live) - 10, 60), (len(payloads), service.errors)
        time.sleep(1.5)  # two refreshes of the view after the last estimate
        frame = screen.last_frame()
    finally:
        screen.proc.terminate()
        screen.proc.wait(30)
        listener.undeclare()
        stream.close()
        publisher.close()
        service.close()
        session.close()
    log = screen.proc.stderr.read() if screen.proc.stderr else ""
    assert screen.proc.returncode == 0, log
    runs_shown = [d["experiment"]["run"] for d in docs]
    assert runs_shown == ["still", "whole", "whole@7000"], runs_shown
    # every parameter set published, in order, with the run and what became of it
    assert re.search(r"#1 \S+ run 'still' \(whole-arm, 600 records\): not excited: joints 1, 2, 3, 4, 5, 6 did not move", frame), frame
    assert re.search(r"#2 \S+ run 'whole' \(whole-arm, 5000 records\): \d+ base parameters from whole-arm run 'whole'", frame), frame
    assert re.search(r"#3 \S+ run 'whole@7000' \(whole-arm, \d+ records\): \d+ base parameters from whole-arm run 'whole@7000'", frame), frame
    # the newest set's every base parameter, value +- std, and the run that gave it
    newest = docs[-1]
    assert "parameters from whole-arm run 'whole@7000' (set 3)" in frame, frame
    for b in newest["base_parameters"]:
        shown = f"{b['expression']} = {b['value']:.4g} +- {b['std']:.4g}"
        assert shown in frame, shown
    # the payload in words: its band and its verdict, as the last estimate published says
    assert payload_line(payloads[-1]) in frame, (payload_line(payloads[-1]), frame[-2000:])
    assert re.search(r"payload: -?\d+\.\d{3} \+- [\d.e+-]+ kg \(1 sigma: data [\d.e+-]+, torque constants [\d.e+-]+\)", frame), frame
    assert "the payload estimator did not use: dropped 1 not finite (last: record 20500: position not finite (NaN or infinite))" in frame, frame
    # findings and events in words; no raw document
    assert "FAULT joint 3 (node 4): over-current [0x2310]" in frame and "run 'still': not excited" in frame, frame
    assert "started run 'whole': whole-arm, 10.0 s" in frame, frame
    assert "0.123456" not in screen.text() and "{'" not in screen.text()
    assert "3 parameter sets" in log and "payload estimates" in log, log


def test_raw_shows_the_events_documents_and_words_leave_out_what_is_not_words() -> None:
    """``--raw``: every field as it came; without it an event of another kind keeps its plain
    fields only (a trajectory's coefficients, drive settings are not words)."""
    from armid.watch import WatchState

    doc = {"time": 0.0, "event": "start", "run": "whole", "experiment": {"kind": "whole_arm", "trajectory": {"a": [[0.123456]]}}}
    other = {"time": 0.0, "event": "calibrated", "joint": 2, "settings": {"gain": 0.987654}}
    words, raw = WatchState(), WatchState(raw=True)
    for state in (words, raw):
        for d in (doc, other):
            state.on_event(json.dumps(d).encode())
    assert [line.split(" ", 1)[1] for line in words.events] == ["started run 'whole': whole-arm", "calibrated joint=2"]
    assert all("0.123456" not in line and "0.987654" not in line for line in words.events)
    assert "0.123456" in raw.events[0] and "0.987654" in raw.events[1]


@pytest.mark.slow
@pytest.mark.realtime
@pytest.mark.alone  # the whole demo: its estimator processes must keep up with the live stream (test_payload's, test_serve's)
def test_watch_joins_the_demo_and_shows_every_parameter_set_and_the_payload_in_words(tmp_path: Path) -> None:
    """Issue 66: ``armid demo`` prints where its service meets it (a loopback endpoint) and the
    ``armid watch`` command that joins it; that command, run on a terminal during the demo,
    shows every parameter set the demo's estimator service published, in order, and the
    payload estimate in words, as the demo's own records of them say (``service.json``,
    ``payload_estimates.json``). Real parts throughout: the demo as a user runs it."""
    from armid.watch import parameter_set_line, payload_line

    out = tmp_path / "demo"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "120"}
    demo = subprocess.Popen([sys.executable, "-m", "armid.cli", "demo", "--out", str(out)], stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env)
    said: list[str] = []
    command: list[str] = []
    screen = None
    try:
        assert demo.stderr is not None
        for line in demo.stderr:  # until the demo says how to watch it
            said.append(line)
            found = re.search(r"armid watch --robot (\S+) --zenoh-connect (tcp/127\.0\.0\.1:\d+)\s*$", line)
            if found:
                command = ["--robot", found.group(1), "--zenoh-connect", found.group(2)]
                break
        assert command, "".join(said)
        rest = threading.Thread(target=lambda: said.extend(demo.stderr or []), daemon=True)
        rest.start()
        screen = Screen([sys.executable, "-m", "armid.cli", "watch", *command, "--duration", "600"])
        assert demo.wait(600) == 0, "".join(said)[-3000:]
        time.sleep(1.5)  # two refreshes of the view after the demo's last estimate
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait()
        if screen is not None:
            screen.proc.terminate()
            screen.proc.wait(30)
    doc = json.loads((out / "demo.json").read_text())
    assert doc["zenoh"]["endpoint"] == command[-1] and doc["zenoh"]["watch"] == "armid watch " + " ".join(command)
    text, frame = screen.text(), screen.last_frame()
    published = json.loads((out / "service.json").read_text())
    assert len(published) == 8, len(published)  # one per experiment: six single-link runs, two whole-arm
    for k, d in enumerate(published, 1):  # every parameter set, in order, with its run and what it gave
        assert re.search(rf"#{k} \S+ {re.escape(parameter_set_line(d))}", text), (k, parameter_set_line(d), text[-3000:])
    for b in published[-1]["base_parameters"]:  # the newest set's every base parameter, value +- std
        assert f"{b['expression']} = {b['value']:.4g} +- {b['std']:.4g}" in text, b
    estimates = json.loads((out / "payload_estimates.json").read_text())
    assert payload_line(estimates[-1]) in text, (payload_line(estimates[-1]), frame[-2000:])
    assert re.search(r"payload: -?\d+\.\d{3} \+- [\d.e+-]+ kg \(1 sigma: data [\d.e+-]+, torque constants [\d.e+-]+\)", frame), frame
    log = screen.proc.stderr.read() if screen.proc.stderr else ""
    assert screen.proc.returncode == 0, log
    assert "8 parameter sets" in log, log

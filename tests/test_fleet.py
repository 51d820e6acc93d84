"""``armid fleet`` on a lab of six arms recorded ten days each (tests/fleetgen.py, which shares
no code with armid): the friction step and the drive-gain drift are found at the recording
where they began (+-1), on the right joint, with the right sign, and the 1 kg tool as one load
on the last link, in kg, at the recording it began (its centre within 1 cm); the other arms
report nothing. A corrupt
recording, one of another robot and one of NaN are rows with their one-line errors and the
rest completes. Ray (a local cluster of 2 CPUs) gives what the local engine gives. The
unchanged arms' own estimates, shuffled in time, raise few false alarms.
"""

from __future__ import annotations

import csv
import dataclasses
import fcntl
import json
import os
import shutil
import signal
import socket
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import fleetgen
import numpy as np
import pytest

from armid.cli import main
from armid.identify.changes import ALPHA, family_wise, scan

BAD = {"corrupt": "not a text CSV file", "other_robot": "column q5 but cell1_left has 4 joints", "nan": "non-finite value"}


def once_per_run(tmp_path_factory: pytest.TempPathFactory, name: str, make: Callable[[Path], None]) -> Path:
    """``make(folder)`` once in the whole test run, its folder shared read-only by the module's
    tests: under pytest-xdist both workers see the run's folder (each worker's own is in it) and
    the one that comes second waits for the first's, instead of making it again (worksteal can
    split this module: the fleet and its local run, 15 s, were made on both workers)."""
    if "PYTEST_XDIST_WORKER" not in os.environ:
        make(folder := tmp_path_factory.mktemp(name))
        return folder
    run = tmp_path_factory.getbasetemp().parent
    folder, done = run / name, run / f"{name}.done"
    with (run / f"{name}.lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)  # what a failed first attempt left
            folder.mkdir()
            make(folder)
            done.touch()
    return folder


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> fleetgen.Fleet:
    def make(folder: Path) -> None:
        made = fleetgen.make_fleet(folder / "fleet")
        fleetgen.with_bad_recordings(made)
        (folder / "fleet.json").write_text(json.dumps(dataclasses.asdict(made), default=str))

    doc = json.loads((once_per_run(tmp_path_factory, "lab", make) / "fleet.json").read_text())
    return fleetgen.Fleet(**{**doc, "root": Path(doc["root"])})


def _read(out: Path) -> dict[str, Any]:
    with (out / "parameters.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    return {"rows": rows, "changes": json.loads((out / "changes.json").read_text()), "report": (out / "report.md").read_text()}


def _run(fleet: fleetgen.Fleet, out: Path, *extra: str) -> dict[str, Any]:
    assert main(["fleet", str(fleet.root), "--out", str(out), *extra]) == 0
    return _read(out)


@pytest.fixture(scope="module")
def local(fleet: fleetgen.Fleet, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    def make(folder: Path) -> None:
        assert main(["fleet", str(fleet.root), "--out", str(folder / "out"), "--engine", "local", "--workers", "1"]) == 0

    return _read(once_per_run(tmp_path_factory, "local", make) / "out")


def _index(fleet: fleetgen.Fleet, change: dict[str, Any]) -> int:
    """1-based place in time of the change's first recording (the generator's own order)."""
    return fleet.recordings[change["arm"]].index(change["recording"]) + 1


def test_each_planted_change_is_found_where_it_began(fleet: fleetgen.Fleet, local: dict[str, Any]) -> None:
    found = local["changes"]
    for c in found:
        print(f"\n{c['arm']}: joint {c['joint']} {c['parameter'][:50]} {c['kind']} from #{_index(fleet, c)} "
              f"{c['before']:.5g} -> {c['after']:.5g} {c['unit']}, significance {c['significance']:.2g}", end="")
    planted = {p["arm"]: p for p in fleet.changes}
    assert {c["arm"] for c in found} == set(planted), "a change on an arm where nothing changed, or a planted one missed"
    for arm, p in planted.items():
        mine = [c for c in found if c["arm"] == arm]
        assert all(abs(_index(fleet, c) - p["index"]) <= 1 for c in mine), f"{arm}: a change away from recording {p['index']}"
        if p["kind"] == "friction_step":
            assert [(c["parameter"], c["joint"]) for c in mine] == [("coulomb_friction.fc", p["joint"])]
            assert mine[0]["after"] > mine[0]["before"]
        elif p["kind"] == "gain_drift":
            assert [(c["parameter"], c["joint"]) for c in mine] == [("torque_gain", p["joint"])]
            assert mine[0]["after"] > mine[0]["before"] and mine[0]["kind"] == "drift"
        else:  # the tool: one load on the last link, in kg, at the recording it began
            assert [(c["parameter"], c["quantity"], c["joint"], c["unit"], c["kind"]) for c in mine] == [("load_mass", "load", 4, "kg", "step")]
            assert _index(fleet, mine[0]) == p["index"]
            _check_load(fleet, mine[0], p)


def _check_load(fleet: fleetgen.Fleet, load: dict[str, Any], planted: dict[str, Any]) -> None:
    """The 1 kg tool: 1.0 +- 0.15 kg, its std below that, its centre within 1 cm of the truth
    (fleetgen's offset in the last link's frame); every base parameter it explains moved as the
    truth says, by the sign of its step between the two days."""
    tool = fleetgen.CHANGES[load["arm"]]
    mass = load["after"] - load["before"]
    print(f"\n{load['arm']}: load {mass:.4f} +- {load['load_mass_std']:.2g} kg (truth {tool['mass_kg']}), centre "
          f"{load['load_com']} m (truth {list(tool['offset_m'])}), {load['load_model']}, fit {load['load_fit']}", end="")
    assert load["before"] == 0.0 and mass == pytest.approx(tool["mass_kg"], abs=0.15) and 0 < load["load_mass_std"] < 0.15
    assert load["load_com"] == pytest.approx(list(tool["offset_m"]), abs=0.01)
    assert load["explains"] and load["significance"] < ALPHA
    for expression in load["explains"]:
        assert "4" in expression
        truth = fleetgen.truth_change(fleet.root, load["arm"], expression, planted["index"] - 1, planted["index"])
        assert abs(truth) > 0, f"{expression}: explained, but the tool did not move it"


def test_the_load_is_a_sentence_in_kilograms_and_the_base_parameters_stay_in_the_table(fleet: fleetgen.Fleet, local: dict[str, Any]) -> None:
    load = next(c for c in local["changes"] if c["quantity"] == "load")
    assert f"a load of {load['after'] - load['before']:.2f} ± {load['load_mass_std']:.2f} kg on link 4 (the last)" in local["report"]
    assert "centre of mass [" in local["report"] and "the last link's load changed" not in local["report"]
    arm_rows = [r for r in local["rows"] if r["arm"] == load["arm"] and r["status"] == "ok"]
    for expression in load["explains"]:  # each explained base parameter still has its row per recording
        assert sum(r["parameter"] == expression and r["quantity"] == "base" for r in arm_rows) == len(fleet.recordings[load["arm"]])
    friction = next(c for c in local["changes"] if c["parameter"] == "coulomb_friction.fc")
    assert f"{friction['after'] / friction['before']:.3g} times what it was" in local["report"]


def test_a_bad_recording_is_a_row_with_its_error_and_the_rest_completes(fleet: fleetgen.Fleet, local: dict[str, Any]) -> None:
    failed = {r["recording"]: r["error"] for r in local["rows"] if r["status"] == "failed"}
    bad = fleet.bad
    assert set(failed) == set(bad.values())
    for kind, path in bad.items():
        assert BAD[kind] in failed[path] and "\n" not in failed[path] and "Traceback" not in failed[path]
    done = {r["recording"] for r in local["rows"] if r["status"] == "ok"}
    assert done == {p for paths in fleet.recordings.values() for p in paths}
    assert all(f"`{path}`" in local["report"] for path in bad.values())


def test_the_tables_say_what_the_interfaces_page_says(fleet: fleetgen.Fleet, local: dict[str, Any]) -> None:
    """Start times are the recordings' first stamps (read here from the files); the JSON keys
    are the documented ones; the report shows a plot per change, and the plots exist."""
    for row in local["rows"][:: 97]:
        with (fleet.root / row["recording"]).open() as handle:
            handle.readline()
            first = float(handle.readline().split(",")[0])
        if row["status"] == "ok":
            assert float(row["start_time"]) == pytest.approx(first, abs=1e-6)
            assert float(row["fit_error"]) < 0.05 and float(row["cv_error"]) < 0.08 and float(row["std"]) >= 0
    for arm, paths in fleet.recordings.items():  # each arm's rows in the order of time, not of name
        seen = [r["recording"] for r in local["rows"] if r["arm"] == arm and r["status"] == "ok"]
        assert list(dict.fromkeys(seen)) == paths and paths != sorted(paths)
    keys = {"arm", "recording", "start_time", "joint", "parameter", "before", "after", "significance"}
    assert all(keys <= set(c) and c["significance"] < ALPHA for c in local["changes"])
    report = local["report"]
    assert report.count("![") == len(local["changes"]) and "designed family-wise false-alarm rate 0.01" in report


def test_a_recording_gives_what_armid_identify_gives(fleet: fleetgen.Fleet, local: dict[str, Any], tmp_path: Path) -> None:
    """The fleet's row of a recording is ``armid identify RECORDING --robot ARM/robot.yaml --json``'s
    base parameters, declared effects and drive gain, and its fit error."""
    arm = "cell3_right"
    recording = fleet.recordings[arm][6]
    assert main(["identify", str(fleet.root / recording), "--robot", str(fleet.root / arm / "robot.yaml"), "--json", str(tmp_path / "i.json")]) == 0
    doc = json.loads((tmp_path / "i.json").read_text())
    mine = {(r["parameter"], r["joint"]): float(r["value"]) for r in local["rows"] if r["recording"] == recording}
    theirs = {(b["expression"], str(int(b["expression"].split()[0].lstrip("mIsxyz")))): b["value"]
              for b in doc["base_parameters"] if b["expression"][0] in "mI"}
    theirs |= {(f"{e['effect']}.{k}", str(e["joint"])): v for e in doc["effects"] for k, v in e["parameters"].items()}
    theirs[("torque_gain", "2")] = doc["torque_scale"][1]
    assert mine.keys() == theirs.keys()
    assert all(mine[k] == pytest.approx(theirs[k], rel=1e-10, abs=1e-14) for k in mine)
    row = next(r for r in local["rows"] if r["recording"] == recording)
    assert float(row["fit_error"]) == pytest.approx(doc["fit"]["relative_error"], rel=1e-10)


def test_unchanged_arms_shuffled_in_time_raise_few_false_alarms(local: dict[str, Any]) -> None:
    """The unchanged arms' real estimates in 400 random orders (exchangeable when nothing
    changed): how often the family of them reports a change, against the designed rate."""
    planted = set(fleetgen.CHANGES)
    arms: dict[str, dict[str, dict[tuple[str, str], tuple[float, float]]]] = {}
    for r in local["rows"]:
        if r["status"] == "ok" and r["arm"] not in planted:
            arms.setdefault(r["arm"], {}).setdefault(r["recording"], {})[(r["parameter"], r["joint"])] = (float(r["value"]), float(r["std"]))
    data = []
    for recs in arms.values():
        keys = sorted(next(iter(recs.values())))
        data.append(np.array([[[recs[rec][k][i] for k in keys] for rec in recs] for i in (0, 1)]))
    rng = np.random.default_rng(37)
    alarms = 0
    for _ in range(400):
        scans = [scan(*(d[:, rng.permutation(d.shape[1])])) for d in data]
        total = np.array([sum(int(s.candidates.sum()) for s in scans)])
        alarms += any((family_wise(s.p, total) < ALPHA).any() for s in scans)
    print(f"\n{alarms} of 400 shuffles of {len(data)} unchanged arms reported a change (designed family-wise rate {ALPHA})")
    assert alarms <= 3 * ALPHA * 400


@pytest.fixture(scope="module")
def ray_cluster() -> Iterator[None]:
    """A local Ray of 2 CPUs for this module's tests, shut down after (and the SIGTERM handler
    that ray.init installs in this process put back)."""
    ray = pytest.importorskip("ray", reason="Ray is not installed: pip install -e '.[fleet]' runs this test")
    handler = signal.getsignal(signal.SIGTERM)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()
    signal.signal(signal.SIGTERM, handler)


def test_ray_on_two_workers_gives_what_the_local_engine_gives(fleet: fleetgen.Fleet, local: dict[str, Any], ray_cluster: None,
                                                              tmp_path: Path) -> None:
    remote = _run(fleet, tmp_path / "ray", "--engine", "ray", "--workers", "2")
    assert len(remote["rows"]) == len(local["rows"])
    for a, b in zip(remote["rows"], local["rows"]):
        assert {k: v for k, v in a.items() if k not in ("value", "std", "fit_error", "cv_error")} == \
               {k: v for k, v in b.items() if k not in ("value", "std", "fit_error", "cv_error")}
        for k in ("value", "std", "fit_error", "cv_error"):
            assert (a[k] == b[k]) or float(a[k]) == pytest.approx(float(b[k]), rel=1e-9, abs=1e-12)
    assert [(c["arm"], c["recording"], c["parameter"], c["joint"]) for c in remote["changes"]] == \
           [(c["arm"], c["recording"], c["parameter"], c["joint"]) for c in local["changes"]]


def test_without_ray_the_ray_engine_is_one_line_naming_the_extra(fleet: fleetgen.Fleet, tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError, as where it is not installed
    assert main(["fleet", str(fleet.root), "--out", str(tmp_path / "x"), "--engine", "ray"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and 'pip install "armid[fleet]"' in err and "Traceback" not in err
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("argv, says", [
    (["--engine", "local", "--workers", "2"], "--engine local runs in this process"),
    (["--workers", "0"], "must be at least 1"),
])
def test_bad_options_are_one_line(fleet: fleetgen.Fleet, tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], says: str) -> None:
    try:
        code = main(["fleet", str(fleet.root), "--out", str(tmp_path / "x"), *argv])
    except SystemExit as stop:  # the parser's own refusal
        code = int(stop.code or 0)
    assert code == 2 and not (tmp_path / "x").exists()
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and says in err


def test_an_address_where_no_cluster_answers_is_one_line(fleet: fleetgen.Fleet, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("ray", reason="Ray is not installed: pip install -e '.[fleet]' runs this test")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nothing listens there
    assert main(["fleet", str(fleet.root), "--out", str(tmp_path / "x"), "--address", f"127.0.0.1:{port}"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no Ray cluster answers at" in err and not (tmp_path / "x").exists()


def test_a_root_without_arms_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "empty" / "notes").mkdir(parents=True)
    assert main(["fleet", str(tmp_path / "empty"), "--out", str(tmp_path / "out"), "--engine", "local"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no arm in it" in err[0]


@pytest.mark.slow
def test_a_fleet_where_nothing_changed_reports_nothing(tmp_path: Path) -> None:
    """Eight more arms (another seed, none of them among fleetgen.CHANGES), ten days each."""
    quiet = fleetgen.make_fleet(tmp_path / "quiet", seed=1, arms=tuple(f"quiet{k}" for k in range(1, 9)))
    assert not quiet.changes
    out = _run(quiet, tmp_path / "out", "--engine", "local")
    assert sum(r["status"] == "ok" for r in out["rows"]) > 0 and out["changes"] == []

"""Extras that fit the machines (issue 34): a DAQ PC without the identification's packages
records, simulates and designs; the analysis commands there end in one line naming the extra.

The machines are made here by an import blocker (a ``sitecustomize`` on ``PYTHONPATH``
whose finder refuses the named packages), in a subprocess running the real command line;
``armid.extras`` is the one table the messages read, checked against ``pyproject.toml``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from importlib import metadata
from importlib.util import find_spec
from pathlib import Path

import pytest

from armid import extras
from armid.cli import _exit_code, build_parser

ROOT = Path(__file__).resolve().parent.parent
RIG = ROOT / "config" / "rigs" / "sim.yaml"
NOT_EXTRAS = {"dev", "docs"}  # the developer's and the site's tools: no command needs them

BLOCKER = '''
import os, sys
BLOCKED = set(os.environ["ARMID_TEST_BLOCK"].split(","))

class _Blocker:
    """This machine does not have the blocked packages: importing one fails as if never installed."""
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None

sys.meta_path.insert(0, _Blocker())
'''


def _pyproject_extras() -> dict[str, list[str]]:
    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return {k: v for k, v in doc["project"]["optional-dependencies"].items() if k not in NOT_EXTRAS}


def _distributions(extra: str, groups: dict[str, list[str]]) -> set[str]:
    """The distribution names an extra installs, ``armid[a,b]`` followed."""
    out: set[str] = set()
    for req in groups[extra]:
        name = req.split(";")[0].split("[")[0].split("<")[0].split(">")[0].split("=")[0].strip()
        if name == "armid":
            for inner in req.split("[")[1].split("]")[0].split(","):
                out |= _distributions(inner.strip(), groups)
        else:
            out.add(name)
    return out


def _armid(tmp_path: Path, blocked: tuple[str, ...], *argv: str, timeout: float = 240) -> subprocess.CompletedProcess[str]:
    """``armid ARGV`` in a subprocess where ``blocked`` cannot be imported."""
    site = tmp_path / "site"
    site.mkdir(exist_ok=True)
    (site / "sitecustomize.py").write_text(BLOCKER)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")]),
           "ARMID_TEST_BLOCK": ",".join(blocked)}
    env.pop("ARMID_DEBUG", None)
    return subprocess.run([sys.executable, "-m", "armid.cli", *argv], capture_output=True, text=True, env=env, cwd=tmp_path, timeout=timeout)


IDENTIFY_ONLY = extras.EXTRAS["identify"].modules
DAQ_ONLY = extras.EXTRAS["daq"].modules


def test_the_table_names_exactly_the_extras_of_pyproject() -> None:
    groups = _pyproject_extras()
    assert set(extras.EXTRAS) == set(groups)
    assert set(extras.NEEDS.values()) <= set(groups)
    commands = set(build_parser()._subparsers._group_actions[0].choices)  # type: ignore[union-attr]
    assert set(extras.NEEDS) <= commands
    assert _distributions("all", groups) == _distributions("daq", groups) | _distributions("identify", groups) | _distributions("mujoco", groups)
    assert set(extras.OPTION_NEEDS.values()) <= set(groups)


@pytest.mark.parametrize("extra", sorted(extras.EXTRAS))
def test_each_extras_modules_are_installed_by_its_distributions(extra: str) -> None:
    """The modules the table probes for an extra are files of the distributions pyproject lists
    for it (and not of the core's): the probe says the extra is there, not something else."""
    dists = _distributions(extra, _pyproject_extras())
    for module in extras.EXTRAS[extra].modules:
        spec = find_spec(module)
        if spec is None:
            pytest.skip(f"{module} is not installed here ({extras.install_command(extra)} installs it)")
        origin = Path(spec.origin or next(iter(spec.submodule_search_locations or []))).resolve()
        owners = {d for d in dists if any(Path(str(f.locate())).resolve() == origin for f in metadata.files(d) or [])}
        assert owners, f"{module} ({origin}) is not a file of {extra}'s distributions {sorted(dists)}"


@pytest.mark.realtime
def test_a_daq_machine_records_the_simulated_arm(tmp_path: Path) -> None:
    done = _armid(tmp_path, IDENTIFY_ONLY, "record", "--rig", str(RIG), "--duration", "2", "--out", "run", "--no-zenoh")
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr and "records, invalid per joint [0, 0, 0, 0, 0, 0]" in done.stderr
    assert (tmp_path / "run" / "run.mcap").stat().st_size > 10_000 and (tmp_path / "run" / "can.log").is_file()


@pytest.mark.realtime
def test_a_daq_machine_simulates_the_arm(tmp_path: Path) -> None:
    done = _armid(tmp_path, IDENTIFY_ONLY, "sim", "--rig", str(RIG), "--duration", "1")
    assert done.returncode == 0, done.stderr
    assert "SYNC periods simulated" in done.stderr


@pytest.mark.slow
def test_a_daq_machine_designs_and_checks_an_excitation(tmp_path: Path) -> None:
    done = _armid(tmp_path, IDENTIFY_ONLY, "excite", "--rig", str(RIG), "--link", "6", "--dry-run", "--out", "ex")
    assert done.returncode == 0, done.stderr
    assert "checked against every limit" in done.stderr and (tmp_path / "ex" / "designs.json").is_file()


@pytest.mark.parametrize("command, argv", [
    ("identify", ["data.csv", "--robot", "puma560"]),
    ("diagnose", ["data.csv", "--robot", "puma560", "--validate", "data.csv"]),
    ("demo", ["--out", "report"]),
])
def test_analysis_on_a_daq_machine_is_one_line_naming_the_extra(tmp_path: Path, command: str, argv: list[str]) -> None:
    done = _armid(tmp_path, IDENTIFY_ONLY, command, *argv, timeout=60)
    assert done.returncode == 2
    extra = extras.NEEDS[command]
    missing = ", ".join(IDENTIFY_ONLY)
    assert done.stderr.splitlines() == [f"armid {command}: error: this command needs the {extras.EXTRAS[extra].purpose} "
                                        f"({missing} are not installed): pip install \"armid[{extra}]\""]
    assert not (tmp_path / "report").exists()


@pytest.mark.parametrize("command, argv", [
    ("identify", [str(ROOT / "examples" / "puma560_excitation.csv"), "--robot", "puma560"]),
    ("check", ["data.csv", "--robot", "puma560", "--model", "id.json"]),
])
def test_mjcf_without_mujoco_is_one_line_naming_its_extra(tmp_path: Path, command: str, argv: list[str]) -> None:
    """``--mjcf`` needs MuJoCo beyond its command's extra: without it, one line before any work;
    the same command without ``--mjcf`` needs no MuJoCo."""
    done = _armid(tmp_path, ("mujoco",), command, *argv, "--mjcf", "out.xml", timeout=60)
    assert done.returncode == 2
    assert done.stderr.splitlines() == [f"armid {command}: error: this command needs the MuJoCo extra (mujoco is not installed): "
                                        'pip install "armid[mujoco]"']
    if command == "identify":
        done = _armid(tmp_path, ("mujoco",), command, *argv, "--urdf", "out.urdf", timeout=120)
        assert done.returncode == 0, done.stderr
        assert (tmp_path / "out.urdf").is_file() and not (tmp_path / "out.xml").exists()


def test_an_identification_machine_identifies_without_the_buses(tmp_path: Path) -> None:
    """``armid[identify]`` alone: the feasible estimate (cvxpy) and the report's plots
    (matplotlib) with python-can, canopen and pyserial unimportable."""
    done = _armid(tmp_path, DAQ_ONLY, "identify", str(ROOT / "examples" / "puma560_excitation.csv"), "--robot", "puma560",
                  "--feasible", "--report", "rep", "--json", "id.json")
    assert done.returncode == 0, done.stderr
    assert "feasible: consistent" in done.stdout and (tmp_path / "rep" / "joint1.png").is_file() and (tmp_path / "id.json").is_file()


def test_recording_where_the_buses_are_not_installed_names_the_daq_extra(tmp_path: Path) -> None:
    done = _armid(tmp_path, DAQ_ONLY, "record", "--rig", str(RIG), "--duration", "2", "--out", "run", timeout=60)
    assert done.returncode == 2 and len(done.stderr.splitlines()) == 1, done.stderr
    assert 'needs the acquisition extra (can, canopen, serial are not installed): pip install "armid[daq]"' in done.stderr
    assert not (tmp_path / "run").exists()


def test_the_blocker_blocks(tmp_path: Path) -> None:
    """The machine above really lacks the package: a plain import of it fails there."""
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(BLOCKER)
    env = {**os.environ, "PYTHONPATH": str(site), "ARMID_TEST_BLOCK": "matplotlib"}
    done = subprocess.run([sys.executable, "-c", "import matplotlib.pyplot"], capture_output=True, text=True, env=env)
    assert done.returncode != 0 and "No module named 'matplotlib" in done.stderr


def test_an_import_that_fails_on_the_way_names_its_extra() -> None:
    """Past the check, a missing third-party module still ends in the one line (the boundary's
    catch), naming the extra that holds it; armid's own missing module stays a bug."""
    code, message = _exit_code(ModuleNotFoundError("No module named 'cvxpy'", name="cvxpy"), "identify")
    assert (code, message) == (2, 'this command needs the identification extra (cvxpy is not installed): pip install "armid[identify]"')
    code, message = _exit_code(ModuleNotFoundError("No module named 'canopen.pdo'", name="canopen.pdo"), "excite")
    assert code == 2 and message.endswith('pip install "armid[daq]"')
    code, message = _exit_code(ModuleNotFoundError("No module named 'armid.nothing'", name="armid.nothing"), "identify")
    assert code == 1 and message.startswith("internal error")

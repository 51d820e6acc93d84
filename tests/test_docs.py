"""The documentation holds: the README is short, the CLI reference is what the parser says, and
every shell command in the README and the guides runs as written on a fresh clone.

Every ``bash`` block of ``README.md`` and ``docs/guides/*.md`` carries a marker on the line
before its fence:

- ``<!-- docs-test: run -->``: run here, in order with the page's other ``run`` blocks, in one
  fresh clone (a temporary folder holding the repository's files, beside a link to
  ``../shared``), each block as one bash script with ``set -euo pipefail``;
- ``<!-- docs-test: run slow -->``: the same, marked ``slow``, and run only with
  ``ARMID_DOCS_FULL=1`` (CI's docs step sets it, after the suite, when there is time); such a
  block needs no other block's output (it runs alone, in a clone of its own);
- ``<!-- docs-test: skip REASON -->``: not run, for the stated reason (installing, the
  minutes-long demo, a real bus).

A block without a marker fails the test, so a new command cannot go unchecked. A failing block
is reported with its commands and their output. Zenoh sessions of the commands meet on a
loopback endpoint of their own (``ARMID_ZENOH_LOCAL``), never on another run's.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared"
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs" / "guides").glob("*.md"))]
README_LIMIT_BYTES = 12_000
BLOCK_TIMEOUT_S = 300
MARKER = re.compile(r"<!--\s*docs-test:\s*(run slow|run|skip)\b\s*(.*?)\s*-->")
FENCE = re.compile(r"^```(bash|sh|shell|console)\s*$")
COPIED = ("config", "examples")  # what a command may write into (a robot or rig file of one's own); the rest is linked
UNCOPIED = {".git", ".venv", ".venv-ci", "site", "report", "runs"}


@dataclass
class Block:
    page: Path
    line: int
    mode: str  # "run", "run slow", "skip", or "" (no marker)
    reason: str
    script: str

    @property
    def where(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


def blocks(page: Path) -> list[Block]:
    """Every shell block of a page, with the marker on the line before its fence."""
    lines = page.read_text().splitlines()
    out, k = [], 0
    while k < len(lines):
        if FENCE.match(lines[k].strip()):
            start = k
            k += 1
            body = []
            while k < len(lines) and lines[k].strip() != "```":
                body.append(lines[k])
                k += 1
            before = lines[start - 1] if start > 0 else ""
            m = MARKER.search(before)
            out.append(Block(page, start + 1, m.group(1) if m else "", m.group(2) if m else "", "\n".join(body) + "\n"))
        k += 1
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def fresh_clone(where: Path) -> Path:
    """A folder that looks like a fresh clone: the repository's tracked top level, ``config``
    and ``examples`` copied (commands may add files there), the rest linked; ``../shared``
    beside it when the repository has one beside it."""
    clone = where / "armid"
    clone.mkdir()
    for entry in ROOT.iterdir():
        if entry.name in UNCOPIED or entry.name.startswith(".pytest") or entry.name == "__pycache__":
            continue
        if entry.name in COPIED:
            shutil.copytree(entry, clone / entry.name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            (clone / entry.name).symlink_to(entry)
    if SHARED.is_dir():
        (where / "shared").symlink_to(SHARED)
    return clone


def run_block(block: Block, clone: Path) -> float:
    if "../shared/" in block.script and not (clone.parent / "shared").is_dir():
        pytest.skip(f"{block.where}: needs ../shared beside the repository (the shared KUKA recordings)")
    env = dict(os.environ)
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    env["ARMID_ZENOH_LOCAL"] = f"tcp/127.0.0.1:{_free_port()}"
    env.pop("ARMID_DEBUG", None)
    script = "set -euo pipefail\ntrap 'kill $(jobs -p) 2>/dev/null || true' EXIT\n" + block.script
    start = time.monotonic()
    try:
        done = subprocess.run(["bash", "-c", script], cwd=clone, env=env, capture_output=True, text=True, timeout=BLOCK_TIMEOUT_S)
    except subprocess.TimeoutExpired as err:
        pytest.fail(f"{block.where}: did not finish in {BLOCK_TIMEOUT_S} s:\n{block.script}\n--- output ---\n{err.stdout or ''}{err.stderr or ''}")
    seconds = time.monotonic() - start
    if done.returncode != 0:
        pytest.fail(f"{block.where}: exit {done.returncode} after {seconds:.1f} s:\n{block.script}\n"
                    f"--- stdout ---\n{done.stdout[-4000:]}\n--- stderr ---\n{done.stderr[-4000:]}")
    return seconds


def test_the_readme_is_under_12_kb() -> None:
    size = len((ROOT / "README.md").read_bytes())
    assert size < README_LIMIT_BYTES, f"README.md is {size} bytes; the limit is {README_LIMIT_BYTES}"


def test_the_readme_is_undated() -> None:
    dated = [f"README.md:{k}: {line.strip()}" for k, line in enumerate((ROOT / "README.md").read_text().splitlines(), 1)
             if re.search(r"\b(19|20)\d\d-\d\d-\d\d\b", line)]
    assert not dated, "the README holds no dates (history goes to CHANGELOG.md):\n" + "\n".join(dated)


def test_the_readme_keeps_its_two_setup_commands() -> None:
    text = (ROOT / "README.md").read_text()
    assert 'python3 -m venv .venv && . .venv/bin/activate && pip install -e ".[all,dev]" && armid demo --out report\n' in text
    assert ('\npython -m pytest tests -rs -m "not realtime" -n 2 && python -m pytest tests -rs -m "realtime and not alone" -n 3 '
            '&& python -m pytest tests -rs -m alone\n') in text  # -rs: each skipped test's reason


def test_the_cli_reference_is_what_the_parser_says() -> None:
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "gen_cli_reference.py"), "--check"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def test_the_figures_are_what_the_benchmarks_wrote() -> None:
    """docs/figures.md is generated from benchmarks/results/*.json (scripts/gen_figures.py);
    an edit by hand, or a result not rendered again, fails here as in CI."""
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "gen_figures.py"), "--check"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert len((ROOT / "docs" / "figures.md").read_bytes()) <= 30_000


def test_the_figures_check_fails_on_a_page_that_differs(tmp_path: Path) -> None:
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import gen_figures
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    page = tmp_path / "figures.md"
    page.write_text(gen_figures.render(gen_figures.load_results()))
    original = gen_figures.PAGE
    try:
        gen_figures.PAGE = page
        assert gen_figures.main(["--check"]) == 0
        page.write_text(page.read_text().replace("Python", "Pyth0n", 1))
        assert gen_figures.main(["--check"]) == 1
    finally:
        gen_figures.PAGE = original


HISTORY_PAGES = [*sorted((ROOT / "docs" / "reference").glob("*.md")), *sorted((ROOT / "docs" / "guides").glob("*.md")),
                 ROOT / "docs" / "architecture.md", ROOT / "docs" / "methods.md"]
HISTORY = re.compile(r"\b20\d\d-\d\d-\d\d\b|\b[Ii]ssues? \d+\b|\b(?=[0-9a-f]*\d)(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b")


def _prose_lines(page: Path) -> list[tuple[int, str]]:
    """A page's lines outside fenced code blocks (a command's example output may hold its dates)."""
    out, fenced = [], False
    for k, line in enumerate(page.read_text().splitlines(), 1):
        if line.lstrip().startswith("```"):
            fenced = not fenced
        elif not fenced:
            out.append((k, line))
    return out


def test_the_docs_say_what_is_true_now() -> None:
    """No dated history (a date, "issue NN", a commit hash) in the reference, the guides, the
    architecture and the methods, and no path under /tmp anywhere in the README or docs/:
    history goes to CHANGELOG.md."""
    dated = [f"{page.relative_to(ROOT)}:{k}: {line.strip()[:120]}" for page in HISTORY_PAGES for k, line in _prose_lines(page)
             if HISTORY.search(line)]
    assert not dated, "history in the docs (it goes to CHANGELOG.md):\n" + "\n".join(dated)
    tmp = [f"{page.relative_to(ROOT)}:{k}" for page in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
           for k, line in enumerate(page.read_text().splitlines(), 1) if "/tmp/" in line]
    assert not tmp, "paths under /tmp (a developer's machine) in the docs:\n" + "\n".join(tmp)


def test_every_shell_block_is_marked() -> None:
    unmarked = [b.where for page in PAGES for b in blocks(page) if not b.mode]
    assert not unmarked, "shell blocks without a docs-test marker (run, run slow, or skip REASON):\n" + "\n".join(unmarked)
    unexplained = [b.where for page in PAGES for b in blocks(page) if b.mode == "skip" and not b.reason]
    assert not unexplained, "skipped blocks must say why:\n" + "\n".join(unexplained)


def _table_commands(page: Path) -> list[tuple[int, str]]:
    """The commands in the "command" column of a page's tables (code spans), with their line."""
    out, column = [], None
    for k, line in enumerate(page.read_text().splitlines(), 1):
        if not line.startswith("|"):
            column = None
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if column is None:
            column = cells.index("command") if "command" in cells else -1
            continue
        if column >= 0 and column < len(cells):
            out += [(k, m) for m in re.findall(r"`([^`]+)`", cells[column])]
    return out


def test_the_readme_table_commands_are_valid() -> None:
    """The README's table names long runs (benchmarks, sweeps, the demo): they are not run here,
    but each parses as armid's parser would take it, and names files that exist."""
    from armid.cli import build_parser

    commands = _table_commands(ROOT / "README.md")
    assert len(commands) >= 10
    problems = []
    for line, command in commands:
        argv = shlex.split(command)
        if argv[:3] == ["python", "-m", "pytest"]:
            argv = argv[3:]
        elif argv[0] == "python":
            argv = argv[1:]
        elif argv[0] == "armid":
            try:
                build_parser().parse_args(argv[1:])
            except SystemExit:
                problems.append(f"README.md:{line}: {command}: armid's parser refuses it")
            argv = argv[2:]
        for word in argv:
            if word.startswith(("config/", "examples/", "benchmarks/", "tests/")):
                if not (ROOT / word.split("::")[0]).exists():
                    problems.append(f"README.md:{line}: {command}: no {word}")
            elif word.startswith("../shared/") and SHARED.is_dir() and not (ROOT / word).exists():
                problems.append(f"README.md:{line}: {command}: no {word}")
    assert not problems, "\n".join(problems)


def _pages_with(mode: str) -> list[Path]:
    return [page for page in PAGES if any(b.mode == mode for b in blocks(page))]


@pytest.mark.parametrize("page", _pages_with("run"), ids=lambda p: str(p.relative_to(ROOT)))
def test_the_commands_of_a_page_run_as_written(page: Path, tmp_path: Path) -> None:
    clone = fresh_clone(tmp_path)
    for block in blocks(page):
        if block.mode == "run":
            run_block(block, clone)


SLOW_BLOCKS = [b for page in PAGES for b in blocks(page) if b.mode == "run slow"]


@pytest.mark.slow
@pytest.mark.skipif(os.environ.get("ARMID_DOCS_FULL") != "1",
                    reason="minutes of commands (the KUKA tour, live sessions): ARMID_DOCS_FULL=1 runs them, as CI's docs step does")
@pytest.mark.parametrize("block", SLOW_BLOCKS, ids=lambda b: b.where)
def test_the_longer_commands_run_as_written(block: Block, tmp_path: Path) -> None:
    run_block(block, fresh_clone(tmp_path))

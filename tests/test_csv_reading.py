"""A CSV read whole in C (issue 65) gives what the cell-by-cell reading gives, on every file:
plain numbers take the fast path, anything else (a blank line, a quote, a field that is not a
number, a row of another length) the cell-by-cell one, which reports such rows as garbage."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from armid.io import recordings
from armid.io.robot_file import load_robot

ROOT = Path(__file__).resolve().parent.parent
HEAD = "t,q1,q2,tau1,tau2"
CASES = {  # name: (the rows after the header, whether the fast path reads them)
    "plain": ("0,1,2,3,4\n0.1,1.5,2.5,3.5,4.5\n", True),
    "crlf": ("0,1,2,3,4\r\n0.1,1.5,2.5,3.5,4.5\r\n", True),
    "no final newline": ("0,1,2,3,4\n0.1,1.5,2.5,3.5,4.5", True),
    "not finite": ("0,nan,2,inf,-Infinity\n0.1,1e400,2.5,3.5,4.5\n", True),
    "signs and exponents": ("0,+1.,.2,3E-2,4\n0.1,-1.5, 2.5 ,3.5,4.5\n", True),
    "an unused column": ("0,1,2,3,4\n0.1,1.5,2.5,3.5,4.5\n", True),
    "one row": ("0,1,2,3,4\n", True),
    "blank line": ("0,1,2,3,4\n  \n\n0.1,1.5,2.5,3.5,4.5\n", False),
    "underscore": ("0,1_0,2,3,4\n0.1,1.5,2.5,3.5,4.5\n", False),
    "empty field": ("0,,2,3,4\n0.1,1.5,2.5,3.5,4.5\n", False),
    "short row": ("0,1,2,3\n0.1,1.5,2.5,3.5,4.5\n", False),
    "long row": ("0,1,2,3,4,5\n0.1,1.5,2.5,3.5,4.5\n", False),
    "comment sign": ("0,1,2,3,4 # c\n0.1,1.5,2.5,3.5,4.5\n", False),
    "quoted": ('0,"1",2,3,4\n0.1,1.5,2.5,3.5,4.5\n', False),
    "hexadecimal": ("0,0x10,2,3,4\n0.1,1.5,2.5,3.5,4.5\n", False),
}


def _read(path: Path) -> tuple:
    rec = recordings.read_recording(path, load_robot(ROOT / "config" / "robots" / "planar2.yaml"))
    return tuple(np.asarray(a).tobytes() for a in (rec.t, rec.q, rec.tau, rec.lines)) + (tuple(rec.notes),)


@pytest.mark.parametrize("name", list(CASES))
def test_fast_csv_reading_is_the_cell_by_cell_reading(name: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rows, fast = CASES[name]
    head = HEAD + (",x" if name == "an unused column" else "")
    rows = rows.replace("3,4\n", "3,4,9\n").replace("4.5\n", "4.5,9\n") if name == "an unused column" else rows
    path = tmp_path / "run.csv"
    path.write_bytes(f"{head}{chr(13) if name == 'crlf' else ''}\n{rows}".encode())
    assert (recordings._plain_numbers(path.read_text(), len(head.split(","))) is not None) == fast
    got = _read(path)
    monkeypatch.setattr(recordings, "_plain_numbers", lambda text, n_columns: None)
    assert got == _read(path)

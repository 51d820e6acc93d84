"""What a command writes: strict JSON (``null``, never ``NaN``), and warnings held while it
reads its inputs (bad input then ends in its one error line alone), one line each."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..schema.json_text import strict_json


def show_warnings(found: list[str]) -> None:
    """Warnings from the pipeline's checks, held until every input is read (:class:`HeldWarnings`)."""
    for warning in found:
        HELD_WARNINGS.show(warning, None, "", 0)


class HeldWarnings:
    """Warnings are held while a command reads its inputs: bad input then ends in its one
    error line alone. Once the inputs are read (:meth:`release`) and at a successful end,
    they are printed, one line each."""

    def __init__(self) -> None:
        self.command = ""
        self.held: list[str] | None = []

    def show(self, message: Any, category: Any, filename: str, lineno: int, file: Any = None, line: Any = None) -> None:
        text = f"armid {self.command}: warning: {one_line(str(message))}"
        if self.held is None:
            print(text, file=sys.stderr)
        elif text not in self.held:
            self.held.append(text)

    def release(self) -> None:
        for text in self.held or []:
            print(text, file=sys.stderr)
        self.held = None


HELD_WARNINGS = HeldWarnings()


def inputs_read() -> None:
    """The command has read and checked its inputs: print what they warned about."""
    HELD_WARNINGS.release()


def one_line(text: str, most: int = 600) -> str:
    line = " ".join(str(text).split())
    return line if len(line) <= most else line[: most - 3] + "..."


def write_json_and_predictions(json_out: str | None, doc: Any, predictions_out: str | None, predictions: Callable[[], tuple[Any, Any]]) -> None:
    """``--json OUT`` (strict) and ``--predictions CSV`` (``t``, ``tau_hat1..n`` from
    ``predictions()``, called only when asked), their folders made: one place for the commands."""
    from armid.io.recordings import write_csv

    for out in (json_out, predictions_out):
        if out:
            Path(out).parent.mkdir(parents=True, exist_ok=True)
    if json_out:
        Path(json_out).write_text(strict_json(doc, indent=1) + "\n")
    if predictions_out:
        t, tau_hat = predictions()
        write_csv(predictions_out, t, {"tau_hat": tau_hat})


def check_writable(*paths: str | None) -> None:
    """Refuse, before any work, an output file that cannot be written: a folder on its way that
    is a file, or the nearest existing folder not writable (``OSError`` naming the path: exit 2).
    The folders missing are made when the file is written."""
    import errno
    import os

    for given in paths:
        if not given:
            continue
        path = Path(given)
        if path.is_dir():
            raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), given)
        folder = path.parent
        while not folder.exists() and folder != folder.parent:
            folder = folder.parent
        if not folder.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(folder))
        if not os.access(folder, os.W_OK | os.X_OK) or (path.exists() and not os.access(path, os.W_OK)):
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), given)

"""The ``armid`` command line (docs/reference/interfaces.md). Exit 0 on success, 2 on bad usage or bad
input (one line on stderr naming the file and what is wrong), 1 on a runtime fault."""

from __future__ import annotations

import argparse
import gc
import os
import sys
import warnings

from armid import __version__, extras
from armid.schema.errors import ArmidError, InputError

from .commands import check, demo, diagnose, estimate, excite, identify, record, serve, sim, watch
from .commands.arguments import ROBOT_HELP, load_robot_argument
from .commands.excite import load_trajectory
from .commands.output import HELD_WARNINGS, one_line
from .commands.session import open_zenoh
from .fleet import command as fleet
from .schema.json_text import strict_json

__all__ = ["ROBOT_HELP", "build_parser", "load_robot_argument", "load_trajectory", "main", "open_zenoh", "strict_json"]
"""The command line's names; each command lives in ``armid/commands/`` (its options and what it runs)."""

COMMANDS = (identify, diagnose, check, record, excite, serve, watch, estimate, demo, sim, fleet)
"""The commands in the order ``armid --help`` lists them."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        """One line, as every other bad input gets (the usage is one ``--help`` away)."""
        print(f"{self.prog}: error: {message} (see {self.prog} --help)", file=sys.stderr)
        raise SystemExit(2)


def build_parser() -> argparse.ArgumentParser:
    """``armid`` and its commands (each module of :data:`COMMANDS` adds its own)."""
    parser = _Parser(prog="armid", description="Robot dynamics identification (Khosla 1987) from servo data.")
    parser.add_argument("--version", action="version", version=f"armid {__version__}")  # the installed metadata
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for command in COMMANDS:
        command.add_parser(sub)
    return parser


def _exit_code(err: BaseException, command: str = "") -> tuple[int, str]:
    """(exit code, message) for an error that reached the command line, by type: 2 for bad
    input (an :class:`InputError`: files, recordings, options, data that cannot give an
    estimate, refused plans), 1 for a runtime fault (any other :class:`ArmidError`: a drive,
    the bus, the simulated hardware) or a bug. A ``ValueError`` from elsewhere is a bug, not
    bad input. A third-party module that cannot be imported names the extra that installs it
    (:mod:`armid.extras`). The tree is drawn in :mod:`armid.schema.errors`."""
    if isinstance(err, ArmidError):
        return (2 if isinstance(err, InputError) else 1), str(err)
    if isinstance(err, OSError):
        # a named file that cannot be opened or written is the user's to fix; a socket or a
        # device failing under a running command is a runtime fault
        if err.filename is not None:
            return 2, f"{err.filename}: {err.strerror or err}"
        return 1, f"{type(err).__name__}: {err}"
    if isinstance(err, RecursionError):
        return 2, "an input is nested too deeply to be read"
    if isinstance(err, ModuleNotFoundError) and (lacking := extras.missing_module(command, err)) is not None:
        return 2, str(lacking)
    return 1, f"internal error ({type(err).__name__}: {err}); ARMID_DEBUG=1 shows where"


def main(argv: list[str] | None = None) -> int:
    """Run one command. The one boundary: whatever a command raises ends as one line on
    stderr and an exit code; a traceback only with ``ARMID_DEBUG=1``."""
    args = build_parser().parse_args(argv)
    HELD_WARNINGS.command, HELD_WARNINGS.held = args.command, []
    try:
        with warnings.catch_warnings():
            warnings.showwarning = HELD_WARNINGS.show
            extras.require(args.command, [k for k, v in vars(args).items() if v not in (None, False)])  # one line naming the extra before anything starts
            if args.command in extras.NEEDS:  # the commands that compute (the others need no extra)
                from .kernels import announce_compilation

                announce_compilation()
            code = int(args.run(args))
        HELD_WARNINGS.release()
        return code
    except KeyboardInterrupt:
        print(f"armid {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as err:
        if os.environ.get("ARMID_DEBUG", "") not in ("", "0"):
            import traceback

            traceback.print_exc()
        code, message = _exit_code(err, args.command)
        print(f"armid {args.command}: error: {one_line(message)}", file=sys.stderr)
        return code


def run() -> None:
    """The ``armid`` executable: :func:`main`, then the process ends. Where Zenoh was loaded,
    without the interpreter's finalization: Zenoh's runtime threads outlive its sessions, and
    one that calls into the interpreter while it finalizes (a callback's last reference
    dropped) is unwound by force through Rust's frames, which aborts the process (SIGABRT,
    "FATAL: exception not rethrown": a stopped ``armid serve`` in 1 of 10 tries beside two
    busy loops, after its last line); so would a worker still inside compiled code. Outputs
    are closed by then; garbage still held in cycles is collected and the standard streams
    flushed first.

    NumPy is told not to ask for transparent huge pages (``NUMPY_MADVISE_HUGEPAGE=0``, unless
    the user set it): where the kernel compacts memory to find one at the first touch (its
    default ``defrag=madvise``), the first touch of a long recording's equations cost 0.75 s of
    system time more than with ordinary pages on the 2-core machine (1.4 s against 0.65 s of an
    ``armid identify`` on 100,000 samples x 6 joints; benchmarks/bench_identify_process.py).
    Set before NumPy is imported: the command line imports it only when a command runs."""
    os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")
    code = main()
    if "zenoh" not in sys.modules:
        raise SystemExit(code)
    gc.collect()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more can reach it
            pass
    os._exit(code)


if __name__ == "__main__":
    run()

"""``armid fleet ROOT --out DIR``: every recording of every arm identified, changes found.

The command's arguments and its run; ``armid/cli.py`` only registers it (:func:`add_parser`).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..commands.arguments import add_topic_argument, whole_count
from . import engine

if TYPE_CHECKING:
    from .task import Result


def add_parser(sub: Any) -> argparse.ArgumentParser:
    """Register ``armid fleet`` on the command line's sub-parsers."""
    p: argparse.ArgumentParser = sub.add_parser(
        "fleet", help="a lab's arms: every recording identified (Ray tasks), parameters tracked over time, changes found")
    p.add_argument("root", metavar="ROOT", help="one folder per arm: ROOT/<arm>/robot.yaml and the arm's recordings (CSV, MCAP, NPZ, rosbag2 bags; any sub-folder)")
    p.add_argument("--out", required=True, metavar="DIR", help="where parameters.csv, changes.json and report.md (with its PNGs) go")
    p.add_argument("--workers", type=whole_count, metavar="N",
                   help="recordings identified at once (default: this machine's CPUs, or the cluster's with --address)")
    p.add_argument("--address", metavar="RAY_ADDRESS", help="join this Ray cluster (ROOT at the same path on every node) instead of starting one here")
    p.add_argument("--engine", choices=engine.ENGINES, default="ray",
                   help=f"ray (default; {engine.EXTRA}), or local: in this process, one recording at a time (--workers 1)")
    add_topic_argument(p)
    p.set_defaults(run=run)
    return p


def _stream_line(r: Result) -> str:
    if not r.ok:
        return f"{r.recording}: FAILED: {r.error}"
    cv = f", cross-validation {100 * r.cv_error:.3g} %" if r.cv_error is not None else ""
    fit = f"{100 * r.fit_error:.3g} %" if r.fit_error is not None else "-"
    return f"{r.recording}: fit {fit}{cv}, {len(r.quantities)} quantities ({r.seconds:.2f} s)"


def _identify_all(args: argparse.Namespace, jobs: list[Any]) -> tuple[list[Result], str]:
    """Run the jobs with a progress bar on standard error; each result is printed as it comes."""
    from rich.console import Console
    from rich.markup import escape
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    results: list[Result] = []
    console = Console(stderr=True, highlight=False)
    columns = (TextColumn("identifying"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[failed]} failed"),
               TimeElapsedColumn(), TimeRemainingColumn())
    with Progress(*columns, console=console, transient=False) as progress:
        bar = progress.add_task("fleet", total=len(jobs), failed=0)

        def on_result(r: Result) -> None:
            results.append(r)
            progress.console.print(escape(_stream_line(r)), soft_wrap=True)
            for w in r.warnings:
                progress.console.print(escape(f"  warning: {w}"), soft_wrap=True)
            progress.update(bar, advance=1, failed=sum(not x.ok for x in results))

        where = engine.run(args.engine, jobs, on_result, args.workers, args.address)
    return results, where


def run(args: argparse.Namespace) -> int:
    """``armid fleet``: discover, identify (streamed), write the tables, find the changes, report."""
    from .discover import find_arms, jobs_of
    from .outputs import detect, in_order, write_changes, write_parameters
    from .report import load_sentence, scatter_sentence, significance, when, write_report

    root, out = Path(args.root), Path(args.out)
    engine.check(args.engine, args.workers, args.address)  # one line before anything starts (a missing extra included)
    arms, notes = find_arms(root, skip=out)
    for note in notes:
        print(f"armid fleet: warning: {note}", file=sys.stderr)
    jobs = jobs_of(arms, root, args.topic)
    out.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    results, where = _identify_all(args, jobs)
    seconds = time.monotonic() - start
    ordered = in_order(results)
    write_parameters(out / "parameters.csv", ordered)
    detection = detect(ordered)
    write_changes(out / "changes.json", detection)
    failed = sum(not r.ok for r in results)
    summary = (f"{len(arms)} arm{'s' * (len(arms) != 1)}, {len(results)} recordings ({len(results) - failed} identified, "
               f"{failed} failed) on {where} in {seconds:.1f} s")
    write_report(out, ordered, detection, [f"`{root}`: {summary}."])
    print(f"fleet: {summary}")
    for arm, info in detection.arms.items():
        print(f"{arm}: {info['recordings']} recordings identified{scatter_sentence(info, brief=True)}")
    for c in detection.changes:
        joint = f" joint {c.joint}" if c.joint is not None else ""
        unit = f" {c.unit}" if c.unit not in ("", "1") else ""
        if c.quantity == "load":
            print(f"{c.arm}: {load_sentence(c)[:-1]}, significance {significance(c.significance)}")
            continue
        print(f"{c.arm}:{joint} {c.parameter}: {c.kind} {c.before:.5g} -> {c.after:.5g}{unit} from {c.recording} "
              f"({when(c.start_time)}), significance {significance(c.significance)}")
    print(f"{len(detection.changes)} change(s) at a family-wise false-alarm rate of {detection.alpha:g}; "
          f"wrote {out / 'parameters.csv'}, {out / 'changes.json'}, {out / 'report.md'}")
    return 0

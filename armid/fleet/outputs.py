"""A fleet run's tables: ``parameters.csv`` (every recording's quantities, or its error) and
``changes.json`` (what changed on which arm, from which recording), docs/reference/interfaces.md.

Each arm's recordings are put in the order of their start time (their first time stamp; the
path relative to ROOT breaks ties, so recordings stamped from 0 fall back to their names).
Change detection runs over each arm's recordings that were identified, by
:mod:`armid.identify.changes`, with one family-wise false-alarm rate for the whole run.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from armid.identify import changes as detector

from .task import Result

CSV_COLUMNS = ("arm", "recording", "start_time", "status", "quantity", "parameter", "joint", "unit", "value", "std",
               "fit_error", "cv_error", "samples", "error")


def in_order(results: list[Result]) -> dict[str, list[Result]]:
    """Per arm (by name), its results by start time then path; the failed ones without a
    start time last, by path."""
    arms: dict[str, list[Result]] = {}
    for r in results:
        arms.setdefault(r.arm, []).append(r)

    def key(r: Result) -> tuple[bool, float, str]:
        return r.start_time is None, r.start_time if r.start_time is not None else 0.0, r.recording

    return {arm: sorted(rows, key=key) for arm, rows in sorted(arms.items())}


def _cell(x: Any) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return ""
    return repr(float(x)) if isinstance(x, float) else str(x)  # the shortest text that reads back the same number


def write_parameters(path: Path, ordered: dict[str, list[Result]]) -> None:
    """One row per recording and quantity; one row with the error for a recording that failed."""
    with path.open("w", newline="") as handle:
        out = csv.writer(handle)
        out.writerow(CSV_COLUMNS)
        for rows in ordered.values():
            for r in rows:
                head = [r.arm, r.recording, _cell(r.start_time)]
                tail = [_cell(r.fit_error), _cell(r.cv_error), str(r.samples) if r.ok else "", r.error or ""]
                if not r.ok:
                    out.writerow(head + ["failed"] + [""] * 6 + tail)
                for q in r.quantities:
                    out.writerow(head + ["ok", q.kind, q.parameter, _cell(q.joint), q.unit, _cell(q.value), _cell(q.std)] + tail)


@dataclass(frozen=True)
class Change:
    """One change of one quantity of one arm (a ``changes.json`` object)."""

    arm: str
    recording: str  # the first recording after the change, relative to ROOT
    start_time: float  # that recording's first time stamp, s
    joint: int | None
    parameter: str
    quantity: str  # base, effect or gain
    unit: str
    kind: str  # step or drift
    before: float
    after: float  # a drift's: at the arm's last recording
    significance: float  # family-wise p-value: the chance of so strong a change anywhere in the fleet if nothing changed
    statistic: float  # the moderated t
    recordings_before: int
    recordings_after: int


@dataclass
class Detection:
    """The changes found and what the test was: per arm (s0^2, d0, quantities, recordings and
    the most scattered quantities), the candidates tried, alpha."""

    changes: list[Change]
    arms: dict[str, dict[str, Any]]
    candidates: int
    alpha: float
    series: dict[str, tuple[list[tuple[str, str, int | None, str]], np.ndarray, np.ndarray, np.ndarray, list[str]]]


def arm_series(rows: list[Result]) -> tuple[list[tuple[str, str, int | None, str]], np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """(keys (quantity, parameter, joint, unit), values (n, Q), stds (n, Q), start times (n,),
    recordings (n,)) of an arm's identified recordings in order."""
    done = [r for r in rows if r.ok]
    keys: dict[tuple[str, str, int | None, str], int] = {}
    for r in done:
        for q in r.quantities:
            keys.setdefault((q.kind, q.parameter, q.joint, q.unit), len(keys))
    values = np.full((len(done), len(keys)), np.nan)
    stds = np.full_like(values, np.nan)
    for i, r in enumerate(done):
        for q in r.quantities:
            c = keys[(q.kind, q.parameter, q.joint, q.unit)]
            values[i, c], stds[i, c] = q.value, q.std
    times = np.array([np.nan if r.start_time is None else r.start_time for r in done])
    return list(keys), values, stds, times, [r.recording for r in done]


def detect(ordered: dict[str, list[Result]], alpha: float = detector.ALPHA) -> Detection:
    """Each arm's quantities scanned for a step or a drift; the family-wise correction over
    every candidate of every quantity of every arm; the changes below ``alpha``."""
    scans, series = {}, {}
    for arm, rows in ordered.items():
        series[arm] = arm_series(rows)
        keys, values, stds, times, _ = series[arm]
        if values.shape[0] and values.shape[1]:
            scans[arm] = detector.scan(values, stds, times)
    total = int(sum(int(s.candidates.sum()) for s in scans.values()))
    found, arms = [], {}
    for arm, scan in scans.items():
        keys, values, _, times, recordings = series[arm]
        worst = [int(c) for c in np.argsort(-np.nan_to_num(scan.scatter, nan=-1.0))[:3] if np.isfinite(scan.scatter[c])]
        arms[arm] = {"prior_variance": scan.prior_variance, "prior_df": scan.prior_df, "quantities": len(keys),
                     "recordings": values.shape[0], "candidates": int(scan.candidates.sum()),
                     "most_scattered": [(keys[c][1], keys[c][2], float(scan.scatter[c])) for c in worst]}
        adjusted = detector.family_wise(scan.p, np.array([total]))
        for c in np.flatnonzero(np.nan_to_num(adjusted, nan=1.0) < alpha):
            k = int(scan.first[c])
            kind, parameter, joint, unit = keys[c]
            found.append(Change(arm, recordings[k], float(times[k]), joint, parameter, kind, unit, detector.KINDS[int(scan.kind[c])],
                                float(scan.before[c]), float(scan.after[c]), float(adjusted[c]), float(scan.statistic[c]),
                                int(np.isfinite(values[:k, c]).sum()), int(np.isfinite(values[k:, c]).sum())))
    found.sort(key=lambda ch: (ch.arm, ch.start_time, -abs(ch.statistic)))
    return Detection(found, arms, total, alpha, series)


def _finite(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


def write_changes(path: Path, detection: Detection) -> None:
    """``changes.json``: a JSON list, one object per change (:class:`Change`'s fields)."""
    path.write_text(json.dumps(_finite([asdict(c) for c in detection.changes]), indent=1, allow_nan=False) + "\n")

"""A fleet run's tables: ``parameters.csv`` (every recording's quantities, or its error) and
``changes.json`` (what changed on which arm, from which recording), docs/reference/interfaces.md.

Each arm's recordings are put in the order of their start time (their first time stamp; the
path relative to ROOT breaks ties, so recordings stamped from 0 fall back to their names).
Change detection runs over each arm's recordings that were identified, by
:mod:`armid.identify.changes`, with one family-wise false-alarm rate for the whole run. The
base parameters that stepped at one recording of one arm and that one load on the last link
explains (:mod:`armid.identify.payload.load_change`) become one change, the load's mass in kg
(``parameter`` ``load_mass``, ``quantity`` ``load``); ``parameters.csv`` keeps every base
parameter as it is.
"""

from __future__ import annotations

import csv
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from armid.identify import changes as detector
from armid.identify.payload import load_change
from armid.schema.json_text import strict_json

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
    # a load on the last link (quantity "load"), None for the others and left out of changes.json:
    load_mass_std: float | None = None  # kg
    load_com: list[float | None] | None = None  # m, in the last link's frame; None where not determined (note says why)
    load_com_std: list[float | None] | None = None
    load_model: str | None = None  # "rigid body" or "point mass" (identify.load_change)
    load_fit: dict[str, float] | None = None  # chi2, dof, dispersion, p_value of the load's fit to every base parameter's step
    explains: list[str] | None = None  # the base parameters' changes it replaces, strongest first
    note: str | None = None

    LOAD_KEYS = ("load_mass_std", "load_com", "load_com_std", "load_model", "load_fit", "explains", "note")


@dataclass
class Detection:
    """The changes found and what the test was: per arm (s0^2, d0, quantities, recordings and
    the most scattered quantities), the candidates tried, alpha."""

    changes: list[Change]
    arms: dict[str, dict[str, Any]]
    candidates: int
    alpha: float
    series: dict[str, tuple[list[tuple[str, str, int | None, str]], np.ndarray, np.ndarray, np.ndarray, list[str]]]
    explained: dict[tuple[str, str], list[Change]] = field(default_factory=dict)  # per load change (arm, recording): the changes it replaced
    notes: dict[str, list[str]] = field(default_factory=dict)  # per arm: steps of the last link that no load explains, and why


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
    scans, series, load_rows, links = {}, {}, {}, {}
    for arm, rows in ordered.items():
        load_rows[arm] = {x: row for r in rows if r.ok for x, row in r.load_rows.items()}
        links[arm] = max((r.n_joints for r in rows if r.ok), default=0)
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
    detection = Detection(found, arms, total, alpha, series)
    for arm, scan in scans.items():
        _name_loads(detection, arm, scan, load_rows[arm], links[arm])
    detection.changes.sort(key=lambda ch: (ch.arm, ch.start_time, -abs(ch.statistic)))
    return detection


def _name_loads(detection: Detection, arm: str, scan: detector.Scan, rows_of: dict[str, list[float]], n_links: int) -> None:
    """The base parameters' steps of ``arm`` at one recording that one load on its last link
    explains, replaced by that load (a :class:`Change` of ``load_mass``, in kg): at each
    recording where base parameters containing the last link's parameters stepped, every base
    parameter's step there (:func:`armid.identify.changes.step_at`) fitted by a load
    (:func:`armid.identify.payload.load_change.fit_load`). A fit that does not explain them leaves them
    as they are, with a note."""
    keys, values, stds, times, recordings = detection.series[arm]
    base = [c for c, key in enumerate(keys) if key[0] == "base"]
    if not n_links or not base or any(keys[c][1] not in rows_of for c in base):
        return
    rows = np.array([rows_of[keys[c][1]] for c in base], float)
    moved = {keys[c][1] for c, row in zip(base, rows) if np.abs(row).max() > 0}
    steps = [c for c in detection.changes if c.arm == arm and c.quantity == "base" and c.kind == "step" and c.parameter in moved]
    previous = 0.0
    for recording in sorted({c.recording for c in steps}, key=recordings.index):
        k = recordings.index(recording)
        here = sorted((c for c in steps if c.recording == recording), key=lambda c: -abs(c.statistic))
        flagged = {c.parameter for c in detection.changes if c.arm == arm and c.recording == recording}
        b, se, _ = detector.step_at(values[:, base], stds[:, base], k, scan.prior_variance, scan.prior_df, scan.wanders[base])
        fit = load_change.fit_load(rows, b, se, np.array([keys[c][1] in flagged for c in base]))
        fitted = (f"chi-square {fit.chi2:.3g} on {fit.dof} degrees of freedom against the arm's scatter {fit.dispersion:.3g}, "
                  f"p {fit.p_value:.2g}")
        if not fit.explains or not np.isfinite(fit.mass):
            detection.notes.setdefault(arm, []).append(
                f"the {len(here)} base parameters with the last link's parameters that changed from `{recording}` on are not one "
                f"load on link {n_links} ({fit.model}: {fitted}; {fit.note or 'the steps are something else'})")
            continue

        def entries(x: np.ndarray) -> list[float | None]:
            return [float(v) if np.isfinite(v) else None for v in x]

        load = Change(arm, recording, float(times[k]), n_links, "load_mass", "load", "kg", "step", previous, previous + fit.mass,
                      min(c.significance for c in here), fit.mass / fit.mass_std if fit.mass_std > 0 else float("inf"),
                      int(k), len(recordings) - k, fit.mass_std, entries(fit.com), entries(fit.com_std), fit.model,
                      {"chi2": fit.chi2, "dof": fit.dof, "dispersion": fit.dispersion, "p_value": fit.p_value},
                      [c.parameter for c in here], "; ".join(x for x in (fit.note, fitted) if x))
        previous += fit.mass
        detection.changes = [c for c in detection.changes if c not in here] + [load]
        detection.explained[(arm, recording)] = here


def write_changes(path: Path, detection: Detection) -> None:
    """``changes.json``: a JSON list, one object per change (:class:`Change`'s fields; the load's
    own fields only on a load)."""
    docs = [{k: v for k, v in asdict(c).items() if c.quantity == "load" or k not in Change.LOAD_KEYS} for c in detection.changes]
    path.write_text(strict_json(docs, indent=1) + "\n")

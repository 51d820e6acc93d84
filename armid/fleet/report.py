"""``report.md`` of a fleet run: what changed, one trend plot per arm and parameter that
changed (PNG beside it), each arm's recordings, the recordings that failed and why."""

from __future__ import annotations

import datetime
from pathlib import Path
from typing import Any

import numpy as np

from armid.identify.changes import MIN_SEGMENT

from .outputs import Change, Detection
from .task import Result

EPOCH_LIKE_S = 1e8
"""A first time stamp above this is seconds since 1970 (1973 on): shown as a UTC date."""


def when(t: float | None) -> str:
    """A start time as a UTC date when it is one, else in seconds."""
    if t is None or not np.isfinite(t):
        return "—"
    if t > EPOCH_LIKE_S:
        return datetime.datetime.fromtimestamp(t, datetime.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    return f"{t:.6g} s"


def significance(p: float) -> str:
    """A p-value as text; one that underflowed is below the smallest double, not 0."""
    return f"{p:.2g}" if p > 0 else "< 1e-300"


def _pct(x: float | None) -> str:
    return "—" if x is None else f"{100 * x:.3g} %"


def plot_change(change: Change, k: int, times: np.ndarray, values: np.ndarray, stds: np.ndarray, path: Path) -> None:
    """The quantity over the arm's recordings (value +- std against start time), the fitted
    change, and a line at recording ``k`` (0-based), the first it affects. Recordings whose
    start times do not increase (stamped from 0) are plotted by their place in the order."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.dates as mdates
    import matplotlib.pyplot as plt

    timed = bool(np.all(np.isfinite(times)) and np.all(np.diff(times) > 0))
    dated = timed and bool(np.min(times) > EPOCH_LIKE_S)
    if not timed:
        times = np.arange(1.0, times.size + 1.0)
    x = np.asarray(mdates.date2num([datetime.datetime.fromtimestamp(t, datetime.UTC) for t in times]) if dated else times, float)
    ok = np.isfinite(values)
    fig, ax = plt.subplots(figsize=(8, 3.6))
    ax.errorbar(x[ok], values[ok], yerr=np.nan_to_num(stds[ok]), fmt="o", ms=4, capsize=3, label="estimate ± std")
    if change.kind == "step":
        ax.plot(x[:k], [change.before] * k, color="tab:green", lw=1.5, label="before")
        ax.plot(x[k:], [change.after] * (len(x) - k), color="tab:red", lw=1.5, label="after")
    else:
        ramp = np.maximum(times - times[k - 1], 0.0) / max(times[-1] - times[k - 1], 1e-300)
        ax.plot(x, change.before + (change.after - change.before) * ramp, color="tab:red", lw=1.5, label="drift")
    ax.axvline(float(x[k]), color="0.5", ls="--", lw=1)
    label = change.parameter if len(change.parameter) <= 40 else change.parameter[:37] + "..."
    ax.set_ylabel(f"{label} [{change.unit or '-'}]")
    ax.set_xlabel("recording start time (UTC)" if dated else "recording start time [s]" if timed else "recording (by start time, then name)")
    if dated:
        ax.xaxis_date()
        ax.xaxis.set_major_formatter(mdates.DateFormatter("%m-%d"))
    joint = f", joint {change.joint}" if change.joint is not None else ""
    ax.set_title(f"{change.arm}: {label}{joint}: {change.kind} from {Path(change.recording).name}", fontsize=10)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _change_lines(detection: Detection, out_dir: Path) -> list[str]:
    lines = ["## Changes", ""]
    if not detection.candidates:
        return lines + [f"None could be tested: a change needs {2 * MIN_SEGMENT} identified recordings of an arm "
                        f"({MIN_SEGMENT} before it and {MIN_SEGMENT} after).", ""]
    if not detection.changes:
        return lines + ["None: no quantity of any arm stepped or drifted beyond its arm's run-to-run scatter.", ""]
    lines += ["| arm | first recording after it | start time | joint | parameter | kind | before | after | unit | significance |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for c in detection.changes:
        lines.append(f"| {c.arm} | `{c.recording}` | {when(c.start_time)} | {c.joint if c.joint is not None else '—'} | `{c.parameter}` | "
                     f"{c.kind} | {c.before:.5g} | {c.after:.5g} | {c.unit} | {significance(c.significance)} |")
    lines.append("")
    counts: dict[str, int] = {}
    for c in detection.changes:
        keys, values, stds, times, recordings = detection.series[c.arm]
        # a load is plotted by the strongest base parameter's step it explains
        shown = detection.explained[(c.arm, c.recording)][0] if c.quantity == "load" else c
        column = next(i for i, key in enumerate(keys) if key[:3] == (shown.quantity, shown.parameter, shown.joint))
        counts[c.arm] = counts.get(c.arm, 0) + 1
        name = f"{c.arm}_{counts[c.arm]:02d}.png"
        plot_change(shown, recordings.index(c.recording), times, values[:, column], stds[:, column], out_dir / name)
        lines += [f"![{c.arm}: {c.parameter}" + (f" (its step of `{shown.parameter}`)" if shown is not c else "") + f"]({name})", ""]
    return lines


def _cm(x: float | None, digits: str = ".1f") -> str:
    return "?" if x is None else format(100 * x, digits)


def load_sentence(c: Change) -> str:
    """A load on the last link in kilograms and centimetres."""
    mass = c.after - c.before
    what = "a load of" if mass >= 0 else "a load removed, of"
    text = (f"{what} {abs(mass):.2f} ± {c.load_mass_std or 0.0:.2f} kg on link {c.joint} (the last) from `{c.recording}` "
            f"({when(c.start_time)}) on")
    com = c.load_com or [None] * 3
    if any(x is not None for x in com):
        std = c.load_com_std or [None] * 3
        text += (f", centre of mass [{', '.join(_cm(x) for x in com)}] ± [{', '.join(_cm(x, '.2g') for x in std)}] cm "
                 "in the link's frame")
    if c.before:
        text += f" ({c.before:.2f} kg before, {c.after:.2f} kg after)"
    model = "; taken as a compact load (a point mass at its centre): the base parameters leave the mass open on this arm" \
        if c.load_model == "point mass" else ""
    return (f"{text}{model}; it explains the steps of {len(c.explains or [])} base parameters "
            f"({', '.join(f'`{x}`' for x in (c.explains or [])[:3])}{', ...' if len(c.explains or []) > 3 else ''}).")


def _what_they_say(detection: Detection) -> list[str]:
    """A sentence per load on a last link (in kg and cm), per friction or gain change (its factor
    after/before), and per set of last-link steps that no load explains."""
    out = []
    for c in detection.changes:
        if c.quantity == "load":
            out.append(f"- {c.arm}: {load_sentence(c)}")
        elif c.quantity in ("effect", "gain") and c.before and ("friction" in c.parameter or c.quantity == "gain"):
            what = f"drive gain of joint {c.joint}" if c.quantity == "gain" else f"`{c.parameter}` of joint {c.joint}"
            at = " by the last recording" if c.kind == "drift" else ""
            out.append(f"- {c.arm}: the {what} {c.kind}s from `{c.recording}` on: {c.after / c.before:.3g} times what it was "
                       f"before{at} (after/before).")
    for arm, notes in sorted(detection.notes.items()):
        out += [f"- {arm}: {n}." for n in notes]
    return out


def scatter_sentence(info: dict[str, Any] | None, brief: bool = False) -> str:
    """What an arm's quantities showed from run to run (and why no change could be tested);
    ``brief``: without the prior's degrees of freedom and the most scattered quantities."""
    if not info:
        return "."
    worst = ", ".join(f"`{p}`" + (f" (joint {j})" if j is not None else "") + f" {np.sqrt(v):.3g}x" for p, j, v in info["most_scattered"])
    text = (f"; {int(info['quantities'])} quantities, whose estimates scatter from run to run by typically "
            f"{np.sqrt(info['prior_variance']):.3g} times their std")
    if not brief:
        text += f" (prior degrees of freedom {info['prior_df']:.3g}); the most: {worst}"
    if not info["candidates"]:
        text += f"; too few recordings to test a change ({2 * MIN_SEGMENT} needed)"
    return text + "."


def write_report(out_dir: Path, ordered: dict[str, list[Result]], detection: Detection, header: list[str]) -> Path:
    """``report.md`` and its PNGs in ``out_dir``; ``header``: lines on the run (what, where, how long)."""
    lines = ["# Fleet report", "", *header, ""]
    lines += [f"Change test: a step or a drift per quantity against its estimates' std and the arm's own run-to-run scatter "
              f"(moderated t, identify/changes.py); designed family-wise false-alarm rate {detection.alpha:g} over all "
              f"{detection.candidates} candidates (quantities x places x kinds) of this run.", ""]
    lines += _change_lines(detection, out_dir)
    notes = _what_they_say(detection)
    if notes:
        lines += ["What they say together:", "", *notes, ""]
    lines += ["## Arms", ""]
    for arm, rows in ordered.items():
        lines += [f"### {arm}", "", f"{sum(r.ok for r in rows)} of {len(rows)} recordings identified{scatter_sentence(detection.arms.get(arm))}", "",
                  "| recording | start time | fit error | cross-validation error | status |", "|---|---|---|---|---|"]
        for r in rows:
            lines.append(f"| `{r.recording}` | {when(r.start_time)} | {_pct(r.fit_error)} | {_pct(r.cv_error)} | "
                         f"{'ok' if r.ok else 'failed: ' + (r.error or '').replace('|', '/')} |")
        lines.append("")
    path = out_dir / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path

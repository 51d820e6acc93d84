"""``armid check --report DIR``: check.md, each joint's error on the new data against the
model's own and the floor, what changed, and a plot of each joint's residual before and after."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from armid.identify.diagnosis.check import CheckResult


def _pct(x: float | None) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{100 * x:.3g} %"


def write_check_report(result: CheckResult, robot: Any, out_dir: Path) -> Path:
    """check.md in ``out_dir`` (made): the verdict, the per-joint table, the changes."""
    out_dir.mkdir(parents=True, exist_ok=True)
    ref = result.reference
    lines = [f"# Check of {robot.name}'s model on new data", ""]
    lines += [f"- {line}" for line in verdict_lines(robot.name, result)]
    lines += ["", f"Errors are relative (||tau - tau_hat|| / ||tau||) at the recordings' own samples; the model's own error is its "
              f"error {OWN_ERROR[ref.kind]} as `armid identify` reported it.", "",
              "| joint | error on these data | with what changed | the model's own | unit of rms | rms before | rms after |",
              "|---|---|---|---|---|---|---|"]
    for j in range(robot.n_joints):
        unit = "N*m" if robot.joints[j].revolute else "N"
        lines.append(f"| {j + 1} | {_pct(result.before['relative'][j])} | {_pct(result.after['relative'][j])} | "
                     f"{_pct(float(ref.relative[j]))} | {unit} | {result.before['rms'][j]:.4g} | {result.after['rms'][j]:.4g} |")
    lines += ["", f"Noise floor of these data: {_pct(result.noise_floor['relative_error'])}."]
    path = out_dir / "check.md"
    path.write_text("\n".join(lines) + "\n")
    return path


OWN_ERROR = {"validation": "on its own validation data", "held_out": "on its own data held out of its fit",
             "fit": "on its own identification data (its fit)"}
"""The model's own error, by which figure of ``armid identify --json`` it is."""


def verdict_lines(name: str, result: CheckResult) -> list[str]:
    """What ``check`` prints (and check.md lists): the verdict with its figures, what changed, and the errors."""
    ref, floor = result.reference, result.noise_floor["relative_error"]
    own = f"{100 * ref.relative_error:.3g} % {OWN_ERROR[ref.kind]}"
    floor_text = "no noise floor" if floor is None else f"a noise floor of {100 * floor:.3g} %"
    e = result.before["relative_error"]
    lines = []
    if result.holds:
        lines.append(f"{name}: the model holds on these data: error {100 * e:.3g} % against {own} and {floor_text}")
        if floor is not None and ref.relative_error**2 > 1.5 * floor**2:
            lines.append(f"note: its own error ({100 * ref.relative_error:.3g} %) stands above the noise floor: a misfit the model "
                         "already had on its own data, not a change (armid diagnose looks for what it lacks)")
        return lines
    where = "" if not result.joints_beyond else "; joints " + ", ".join(str(j + 1) for j in result.joints_beyond) + " beyond their own"
    lines.append(f"{name}: the model does NOT hold on these data: error {100 * e:.3g} % against {own} and {floor_text}{where}")
    if ref.kind == "fit":
        lines.append("note: the model's own figure is its fit on the data it was identified on, which is optimistic for a new trajectory: "
                     "identify with --validate on a run of its own for a fairer reference")
    if result.beyond_motion:
        lines.append("these data move beyond the model's identification data (" + "; ".join(result.beyond_motion) + "): part of the "
                     "rise may be the model's extrapolation there, not a change of the arm")
    lines += [c.sentence(bool(result.beyond_motion)) for c in result.found]
    lines += result.notes
    if not result.found:
        lines.append("nothing in the catalogue nor a load on the last link explains the rise: re-identify on these data, "
                     "or run armid diagnose on them")
    lines.append(f"{name}: error {100 * e:.3g} % -> {100 * result.after['relative_error']:.3g} % with what changed "
                 "(each sample predicted by the fit on the other tenths)")
    return lines

"""``armid check --report DIR``: check.md, each joint's error on the new data against the
model's own and the floor, what changed, and a plot of each joint's residual before and after."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def _pct(x: float | None) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{100 * x:.3g} %"


def write_check_report(result: Any, robot: Any, out_dir: Path) -> Path:
    """check.md in ``out_dir`` (made): the verdict, the per-joint table, the changes."""
    from .commands.check import verdict_lines

    out_dir.mkdir(parents=True, exist_ok=True)
    ref = result.reference
    lines = [f"# Check of {robot.name}'s model on new data", ""]
    lines += [f"- {line}" for line in verdict_lines(robot.name, result)]
    lines += ["", f"Errors are relative (||tau - tau_hat|| / ||tau||) at the recordings' own samples; the model's own error is its "
              f"{ref.kind} error as `armid identify` reported it.", "",
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

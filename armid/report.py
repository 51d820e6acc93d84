"""The identification report: a markdown page with the parameter table and PNG plots."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from identify.identification import IdentificationResult
from identify.preprocess import Segment


def _fmt(x: float | None, digits: int = 5) -> str:
    return "—" if x is None else f"{x:.{digits}g}"


def write_report(result: IdentificationResult, doc: dict[str, Any], segments: list[Segment], out_dir: Path, title: str) -> Path:
    """Write ``report.md`` and one PNG per joint (measured vs predicted, residual)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    t = np.concatenate([s.t for s in segments])
    tau = np.concatenate([s.tau for s in segments])
    tau_hat = np.concatenate([result.predict(s) for s in segments])
    plots = []
    for j in range(result.robot.n_joints):
        fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
        ax1.plot(t, tau[:, j], lw=0.8, label="measured")
        ax1.plot(t, tau_hat[:, j], lw=0.8, label="predicted")
        ax1.set_ylabel(f"tau{j + 1} [N*m or N]")
        ax1.legend(loc="upper right")
        ax2.plot(t, tau[:, j] - tau_hat[:, j], lw=0.6, color="tab:red")
        ax2.set_ylabel("residual")
        ax2.set_xlabel("t [s]")
        fig.suptitle(f"{result.robot.name} joint {j + 1}: {title}")
        fig.tight_layout()
        name = f"joint{j + 1}.png"
        fig.savefig(out_dir / name, dpi=90)
        plt.close(fig)
        plots.append(name)
    lines = [f"# Identification of {doc['robot']}", ""]
    lines.append(f"{doc['samples']} samples, {doc['weighting'].upper()}, condition number {doc['condition_number']:.4g}, rank {doc['rank']}.")
    lines.append("")
    lines.append("| | relative error | rms per joint |")
    lines.append("|---|---|---|")
    lines.append(f"| fit | {doc['fit']['relative_error']:.4g} | {', '.join(f'{x:.3g}' for x in doc['fit']['rms'])} |")
    if doc.get("validation"):
        v = doc["validation"]
        lines.append(f"| validation | {v['relative_error']:.4g} | {', '.join(f'{x:.3g}' for x in v['rms'])} |")
    lines += ["", "## Base parameters (Khosla Tables 2-4)", "", "| expression | modeled | estimate | std | rel. std % |", "|---|---|---|---|---|"]
    for b in doc["base_parameters"]:
        lines.append(f"| `{b['expression']}` | {_fmt(b['modeled'])} | {_fmt(b['value'])} | {_fmt(b['std'], 3)} | {_fmt(b['relative_std_percent'], 3)} |")
    lines += ["", "## Standard parameters", "", "| link | parameter | modeled | estimate | std | class |", "|---|---|---|---|---|---|"]
    for p in doc["parameters"]:
        lines.append(f"| {p['link']} | {p['name']} | {_fmt(p['modeled'])} | {_fmt(p['value'])} | {_fmt(p['std'], 3)} | {p['identifiability']} |")
    if doc["effects"]:
        lines += ["", "## Declared effects", "", "| effect | joint | parameters |", "|---|---|---|"]
        for e in doc["effects"]:
            params = ", ".join(f"{k} = {_fmt(v)} ± {_fmt(e['std'][k], 3)}" for k, v in e["parameters"].items())
            lines.append(f"| {e['effect']} | {e['joint']} | {params} |")
    if doc["preprocessing"]:
        lines += ["", "## What was done to the data", ""] + [f"- {n}" for n in doc["preprocessing"]]
    lines += ["", f"## Torques ({title})", ""] + [f"![joint {k + 1}]({p})" for k, p in enumerate(plots)]
    path = out_dir / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path

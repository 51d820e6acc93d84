"""The identification report: a markdown page with the parameter table and PNG plots."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from armid.identify.identification import IdentificationResult
from armid.identify.preprocess import Segment


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


def write_diagnosis_report(diag: Any, robot_name: str, out_dir: Path) -> Path:
    """``diagnosis.md``: one sentence per finding, before/after errors, and per joint the
    held-out residual against velocity (friction), position (cogging, spring, tilt),
    acceleration (rotor inertia) and time (drift), before and after."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    tau, before = diag.residual_before
    _, after = diag.residual_after
    t, q, qd, qdd = diag.validation_motion
    used = diag.used if diag.used is not None else np.ones_like(tau, bool)
    plots = []
    for j in range(tau.shape[1]):
        u = used[:, j]
        fig, axes = plt.subplots(1, 4, figsize=(15, 3.4), sharey=True)
        for ax, x, label in zip(axes, (qd[:, j], q[:, j], qdd[:, j], t), ("velocity", "position", "acceleration", "time [s]")):
            ax.plot(x[u], (tau - before)[u, j], ".", ms=1.5, alpha=0.4, color="tab:red", label="before")
            ax.plot(x[u], (tau - after)[u, j], ".", ms=1.5, alpha=0.4, color="tab:blue", label="after")
            ax.set_xlabel(label)
        axes[0].set_ylabel(f"residual, joint {j + 1}")
        axes[0].legend(loc="upper right", markerscale=6)
        fig.suptitle(f"{robot_name} joint {j + 1}: held-out residual before (red) and after (blue) the findings")
        fig.tight_layout()
        name = f"diagnosis_joint{j + 1}.png"
        fig.savefig(out_dir / name, dpi=90)
        plt.close(fig)
        plots.append(name)
    b, a = diag.before, diag.after
    lines = [f"# Diagnosis: {robot_name}", "",
             f"Held-out (validation) relative error **{100 * b['relative_error']:.3g} % -> {100 * a['relative_error']:.3g} %** "
             f"over {b.get('equations', '?')} joint equations (a joint's equation is left out while it is at rest or reversing).", ""]
    lines += ["## Findings", ""]
    lines += [f"- {f.sentence()}" for f in diag.found] or ["- nothing significant: the declared model explains the data to its noise"]
    if diag.absorbed:
        lines += ["", "## Absorbed by the rigid-body model (not findings)", ""]
        lines += [f"- {x['effect'].replace('_', ' ')} on joint {x['joint']}: its columns lie in the model's span; it joins `{x['into']}`" for x in diag.absorbed]
    lines += ["", f"Declared in the robot file (part of the base model): {', '.join(diag.base_effects) or 'nothing'}.", "",
              "## Error per joint", "", "| joint | RMS before | RMS after | relative before | relative after |", "|---|---|---|---|---|"]
    for j in range(tau.shape[1]):
        lines.append(f"| {j + 1} | {b['rms'][j]:.4g} | {a['rms'][j]:.4g} | {100 * b['relative'][j]:.3g} % | {100 * a['relative'][j]:.3g} % |")
    lines += ["", "## Residual against velocity, position, acceleration and time", ""]
    lines += [f"![joint {k + 1}]({p})" for k, p in enumerate(plots)]
    path = out_dir / "diagnosis.md"
    path.write_text("\n".join(lines) + "\n")
    return path

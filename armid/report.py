"""The identification report: a markdown page with the parameter table and PNG plots."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from armid.identify.diagnosis import extrapolation_sentence, negligible_sentence, set_aside_sentence
from armid.identify.feasible import link_list
from armid.identify.identification import IdentificationResult
from armid.identify.preprocess import Segment


def _fmt(x: float | None, digits: int = 5) -> str:
    return "—" if x is None else f"{x:.{digits}g}"


def _percent(x: float | None) -> str:
    return "—" if x is None else f"{100 * x:.4g} %"


def feasible_section(feasible: dict[str, Any]) -> list[str]:
    """The consistency report (markdown lines) of ``FeasibleResult.to_json()``: which links of
    the least-squares estimate break which condition of a rigid body and by how much, and the
    physically consistent estimate's errors beside the unconstrained one's."""
    ls, fe = feasible["least_squares"], feasible["feasible"]
    lines = ["## Physical consistency", ""]
    bad = [link for link in ls["links"] if not link["consistent"]]
    lines.append("Least squares (its base estimate completed with the modeled values by the least change): "
                 + (f"**{link_list([link['link'] for link in bad])} {'is' if len(bad) == 1 else 'are'} not a physical body.**" if bad
                    else "every link is a physical body.")
                 + " Feasible estimate: " + ("every link is a physical body" if fe["consistent"] else "**NOT every link is a physical body**")
                 + f" (pseudo-inertia positive semidefinite); {feasible['distance_from_least_squares']:.3g} sigma from least squares "
                 f"in the data's metric; solver {feasible['status']} in {feasible['iterations']} iterations, {feasible['seconds']:.2f} s.")
    lines += ["", "| link | least squares: mass kg | smallest pseudo-inertia eigenvalue kg m^2 | what it breaks, by how much | "
                  "feasible: mass kg | smallest eigenvalue kg m^2 | divergence from modeled |", "|---|---|---|---|---|---|---|"]
    for a, b, d in zip(ls["links"], fe["links"], feasible["divergence"]):
        broken = "; ".join(a["violations"]) or "nothing"
        lines.append(f"| {a['link']} | {_fmt(a['mass'], 4)} | {_fmt(a['pseudo_inertia_min_eigenvalue'], 3)} | {broken} | "
                     f"{_fmt(b['mass'], 4)} | {_fmt(b['pseudo_inertia_min_eigenvalue'], 3)} | {_fmt(d, 3)} |")
    lines += ["", "| relative error | least squares | feasible | feasible / least squares |", "|---|---|---|---|"]
    for key, label in (("fit", "identification data (the equations as fitted)"), ("validation", "held-out (validation) data")):
        x, y = ls.get(key), fe.get(key)
        if x and y:
            lines.append(f"| {label} | {_percent(x['relative_error'])} | {_percent(y['relative_error'])} | {y['relative_error'] / x['relative_error']:.3f} |")
    if not ls.get("validation"):
        lines.append("| held-out (validation) data | — | — | no `--validate` data |")
    if feasible["prior_notes"]:
        lines += [""] + [f"- prior: {n}" for n in feasible["prior_notes"]]
    boxes = feasible.get("bounding_boxes")
    if boxes:
        held = [f"{i + 1} ({', '.join(f'{a:.3g}..{b:.3g}' for a, b in zip(box['lower'], box['upper']))} m)" for i, box in enumerate(boxes) if box]
        lines += ["", f"Each link's mass kept in the box of its URDF collision geometry (x, y, z in the link frame): links {'; '.join(held)}; "
                      f"links {', '.join(str(i + 1) for i, box in enumerate(boxes) if not box) or 'none'} without a box."]
    lines += ["", f"Regulariser: {feasible['regularization']['kind']}, weight {feasible['regularization']['weight']:g}."]
    return lines


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
    if doc.get("feasible"):
        lines += [""] + feasible_section(doc["feasible"])
    lines += ["", f"## Torques ({title})", ""] + [f"![joint {k + 1}]({p})" for k, p in enumerate(plots)]
    path = out_dir / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def write_diagnosis_report(diag: Any, robot_name: str, out_dir: Path, feasible: dict[str, Any] | None = None) -> Path:
    """``diagnosis.md``: one sentence per finding, before/after errors, and per joint the
    held-out residual against velocity (friction), position (cogging, spring, tilt),
    acceleration (rotor inertia) and time (drift), before and after; with ``feasible``
    (``diagnose --feasible``), the consistency report of the model with the findings."""
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
             + (f"at all {len(diag.predictions[0])} validation samples, each at its own time stamp, " if diag.predictions is not None else "")
             + "against the raw measured torque.", ""]
    lines += ["## Findings", ""]
    lines += [f"- {f.sentence()}" for f in diag.found] or ["- nothing significant: the declared model explains the data to its noise"]
    if diag.negligible:
        lines += ["", "## Negligible (below the materiality; not findings)", ""]
        lines += [f"- {negligible_sentence(x)}" for x in diag.negligible]
    lines += [f"- {note}" for note in diag.notes]
    if diag.absorbed:
        lines += ["", "## Absorbed by the rigid-body model (not findings)", ""]
        lines += [f"- {x['effect'].replace('_', ' ')} on joint {x['joint']}: its columns lie in the model's span; it joins `{x['into']}`" for x in diag.absorbed]
    if diag.conflicting:
        lines += ["", "## Set aside (not findings)", ""]
        lines += [f"- {set_aside_sentence(c)}" for c in diag.conflicting]
    if diag.extrapolated:
        lines += ["", "## Extrapolated by the validation", ""]
        lines += [f"- {extrapolation_sentence(x)}" for x in diag.extrapolated]
    lines += ["", f"Declared in the robot file (part of the base model): {', '.join(diag.base_effects) or 'nothing'}.", "",
              "## Error per joint", "", "| joint | RMS before | RMS after | relative before | relative after |", "|---|---|---|---|---|"]
    for j in range(tau.shape[1]):
        lines.append(f"| {j + 1} | {b['rms'][j]:.4g} | {a['rms'][j]:.4g} | {100 * b['relative'][j]:.3g} % | {100 * a['relative'][j]:.3g} % |")
    if feasible:
        lines += [""] + feasible_section(feasible)
    lines += ["", "## Residual against velocity, position, acceleration and time", ""]
    lines += [f"![joint {k + 1}]({p})" for k, p in enumerate(plots)]
    path = out_dir / "diagnosis.md"
    path.write_text("\n".join(lines) + "\n")
    return path

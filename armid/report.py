"""The identification and diagnosis reports: markdown pages with their tables and PNG plots.

Every error a report states is named for what it measures: which model (identified on which
data) on which data, and how (each sample at its own stamp against the raw measured torque,
or the equations as least squares saw them). Errors are percent, one format throughout
(:func:`percent`); axes carry the joint's units (:func:`joint_units`) and time runs from the
first sample shown (:func:`elapsed`)."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from armid.identify.diagnosis.search import extrapolation_sentence, negligible_sentence, set_aside_sentence
from armid.identify.feasible import link_list
from armid.identify.identification import IdentificationResult
from armid.identify.metrics import summary
from armid.identify.preprocess import Segment
from armid.identify.robot import Robot

RECORDING_GAP_S = 60.0
"""A step of time stamps larger than this (or backwards) joins two recordings: the time axes
lay them end to end instead of plotting the hours between them."""

MAX_POINTS = 20_000
"""Points per panel of a scatter plot; more are thinned to every k-th, and the plot says so."""


def _fmt(x: float | None, digits: int = 5) -> str:
    return "—" if x is None else f"{x:.{digits}g}"


def percent(x: float | None, digits: int = 3) -> str:
    """A relative error (a fraction) as every report writes it: ``0.02241`` -> ``"2.24 %"``
    (``digits`` significant digits: 4 where two estimates' errors stand side by side)."""
    return "—" if x is None or not math.isfinite(x) else f"{100 * x:.{digits}g} %"



REVOLUTE_UNITS = {"q": "rad", "qd": "rad/s", "qdd": "rad/s^2", "tau": "N*m"}
PRISMATIC_UNITS = {"q": "m", "qd": "m/s", "qdd": "m/s^2", "tau": "N"}
UNKNOWN_UNITS = {"q": "rad or m", "qd": "rad/s or m/s", "qdd": "rad/s^2 or m/s^2", "tau": "N*m or N"}
"""Only where the robot is not given (``write_diagnosis_report`` called with its name alone)."""


def joint_units(robot: Robot | None, j: int) -> dict[str, str]:
    """The units of joint ``j``'s position, velocity, acceleration and torque (``q``, ``qd``,
    ``qdd``, ``tau``): rad and N*m for a revolute joint, m and N for a prismatic one."""
    if robot is None:
        return UNKNOWN_UNITS
    return REVOLUTE_UNITS if robot.joints[j].revolute else PRISMATIC_UNITS


def _torque_units(robot: Robot | None, n: int) -> str:
    """The torque unit of ``n`` joints in one phrase: "N*m", or "N*m; N on joint 3"."""
    units = [joint_units(robot, j)["tau"] for j in range(n)]
    if len(set(units)) == 1:
        return units[0]
    prismatic = [str(j + 1) for j, u in enumerate(units) if u == "N"]
    return f"N*m; N on joint{'s' if len(prismatic) > 1 else ''} {', '.join(prismatic)}"


def elapsed(t: np.ndarray) -> tuple[np.ndarray, list[float]]:
    """Seconds (n,) from the first of the time stamps ``t`` (epoch or not), and where one
    recording joins the next: a step back in time or longer than :data:`RECORDING_GAP_S`
    becomes one median step, so recordings lie end to end."""
    t = np.asarray(t, float)
    if t.size < 2:
        return np.zeros(t.size), []
    dt = np.diff(t)
    forward = dt[dt > 0]
    step = float(np.median(forward)) if forward.size else 0.0
    joins = (dt <= 0) | (dt > RECORDING_GAP_S)
    x = np.concatenate([[0.0], np.cumsum(np.where(joins, step, dt))])
    return x, [float(v) for v in x[1:][joins]]


def _time_label(joins: list[float], what: str) -> str:
    if joins:
        return f"time from the first sample of each recording of {what}, laid end to end [s]"
    return f"time from the first sample of {what} [s]"


def _ordinal(k: int) -> str:
    return f"{k}{'th' if 10 <= k % 100 <= 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(k % 10, 'th')}"


def _data_name(segments: list[Segment] | None, default: str) -> str:
    """The recordings the segments came from, by file name (``default`` without segments)."""
    if not segments:
        return default
    names = list(dict.fromkeys(Path(s.source).name for s in segments))
    return ", ".join(names) if names and all(names) else default


def feasible_at_stamps(result: IdentificationResult, feasible: dict[str, Any], segments: list[Segment]) -> dict[str, Any] | None:
    """The errors of the physically consistent estimate (``feasible``: ``FeasibleResult.to_json()``)
    measured as the least-squares ones are: the same model, its base parameters replaced, at
    every sample's own stamp of ``segments`` against the raw torque (``metrics.summary``).
    None where its base parameters are not the result's."""
    beta = np.array([b["value"] for b in feasible.get("base_parameters", [])], float)
    if beta.shape != result.estimate.beta.shape or not segments:
        return None
    model = replace(result, estimate=replace(result.estimate, beta=beta), _at_stamps={})
    _, tau, tau_hat = model.predict_stamps(segments)
    out = summary(tau, tau_hat)
    out["samples"] = int(tau.shape[0])
    return out


def feasible_section(feasible: dict[str, Any], errors: bool = True, model: str = "least squares") -> list[str]:
    """The consistency report (markdown lines) of ``FeasibleResult.to_json()``: which links of
    the least-squares estimate break which condition of a rigid body and by how much, and
    (``errors``) the physically consistent estimate's errors beside the unconstrained one's,
    as ``FeasibleResult`` measures them (on the fitted equations and on the validation data's
    prepared grid, not at the stamps: named so). ``errors=False`` where the page states both
    models' errors at the stamps already (:func:`write_report` given both data sets).
    ``model``: what the unconstrained estimate is (the diagnosis's: the declared model with
    its findings)."""
    ls, fe = feasible["least_squares"], feasible["feasible"]
    lines = ["## Physical consistency", ""]
    bad = [link for link in ls["links"] if not link["consistent"]]
    lines.append(f"{model[0].upper()}{model[1:]} (its base estimate completed with the modeled values by the least change): "
                 + (f"**{link_list([link['link'] for link in bad])} {'is' if len(bad) == 1 else 'are'} not a physical body.**" if bad
                    else "every link is a physical body.")
                 + " Feasible estimate: " + ("every link is a physical body" if fe["consistent"] else "**NOT every link is a physical body**")
                 + f" (pseudo-inertia positive semidefinite); {feasible['distance_from_least_squares']:.3g} sigma from {model} "
                 f"in the data's metric; solver {feasible['status']} in {feasible['iterations']} iterations, {feasible['seconds']:.2f} s.")
    lines += ["", f"| link | {model}: mass kg | smallest pseudo-inertia eigenvalue kg m^2 | what it breaks, by how much | "
                  "feasible: mass kg | smallest eigenvalue kg m^2 | divergence from modeled |", "|---|---|---|---|---|---|---|"]
    for a, b, d in zip(ls["links"], fe["links"], feasible["divergence"]):
        broken = "; ".join(a["violations"]) or "nothing"
        lines.append(f"| {a['link']} | {_fmt(a['mass'], 4)} | {_fmt(a['pseudo_inertia_min_eigenvalue'], 3)} | {broken} | "
                     f"{_fmt(b['mass'], 4)} | {_fmt(b['pseudo_inertia_min_eigenvalue'], 3)} | {_fmt(d, 3)} |")
    if errors:
        lines += ["", "Relative errors as the consistency check measures them, not at the samples' stamps: on the identification data, "
                      "the equations least squares fitted (filtered as fitted, unweighted, without any samples it left out); on the held-out data, "
                      "its prepared samples on the regular grid against the prepared torque.", "",
                  f"| relative error (not at the stamps) | {model} | feasible | feasible / {model} |", "|---|---|---|---|"]
        for key, label in (("fit", "identification data (the equations as fitted)"), ("validation", "held-out (validation) data")):
            x, y = ls.get(key), fe.get(key)
            if x and y:
                lines.append(f"| {label} | {percent(x['relative_error'], 4)} | {percent(y['relative_error'], 4)} | "
                             f"{y['relative_error'] / x['relative_error']:.3f} |")
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


def _error_rows(result: IdentificationResult, doc: dict[str, Any], identification: list[Segment] | None,
                validation: list[Segment] | None, identified_on: str, validated_on: str) -> tuple[list[str], dict[str, Any]]:
    """The errors table of :func:`write_report`: one fit error and (with validation data) one
    validation error per model, least squares and (with ``doc["feasible"]``) the physically
    consistent estimate, each at every sample's stamp against the raw torque. Returns the
    lines and the feasible estimate's errors at the stamps (``fit``, ``validation``, either None)."""
    fit, val = doc["fit"], doc.get("validation")
    n = result.robot.n_joints
    lines = [f"Relative error |tau - tau_hat| / |tau| over every joint, each sample at its own time stamp against the raw measured "
             f"torque: fit on {identified_on} ({result.samples} samples)"
             + (f", validation on {validated_on} ({doc.get('validation_samples') or val.get('samples')} samples)." if val else
                "; no validation data (`--validate`)."), ""]
    header = f"| model (identified on {identified_on}) | fit error (on {identified_on}) |" + (f" validation error (on {validated_on}) |" if val else "")
    lines += [header, "|---|---|" + ("---|" if val else "")]
    lines.append(f"| least squares ({doc['weighting'].upper()}), the estimate below | {percent(fit['relative_error'])} |"
                 + (f" {percent(val['relative_error'])} |" if val else ""))
    stamps: dict[str, Any] = {"fit": None, "validation": None}
    feasible = doc.get("feasible")
    if feasible:
        stamps = dict(feasible.get("at_stamps") or stamps)
        if stamps.get("fit") is None and identification:
            stamps["fit"] = feasible_at_stamps(result, feasible, identification)
        if stamps.get("validation") is None and validation and val:
            stamps["validation"] = feasible_at_stamps(result, feasible, validation)
        # without the identification samples here (identify --report with --validate): on the fitted equations, below
        fit_cell = percent(stamps["fit"]["relative_error"]) if stamps["fit"] is not None else "— (on the fitted equations: below)"
        val_cell = ""
        if val:
            val_cell = f" {percent(stamps['validation']['relative_error'])} |" if stamps.get("validation") else " — |"
        lines.append(f"| physically consistent (from the same fit; Physical consistency below) | {fit_cell} |{val_cell}")
    lines += ["", "| joint | torque unit | fit rms (least squares) |" + (" validation rms (least squares) |" if val else ""),
              "|---|---|---|" + ("---|" if val else "")]
    for j in range(n):
        lines.append(f"| {j + 1} | {joint_units(result.robot, j)['tau']} | {fit['rms'][j]:.3g} |" + (f" {val['rms'][j]:.3g} |" if val else ""))
    return lines, stamps


def write_report(result: IdentificationResult, doc: dict[str, Any], segments: list[Segment], out_dir: Path, title: str,
                 identification: list[Segment] | None = None, identified_on: str | None = None,
                 validated_on: str | None = None) -> Path:
    """Write ``report.md`` and one PNG per joint (measured and predicted torque, residual).

    ``segments``: the data plotted, the validation data when ``doc`` has a validation (else
    the identification data); ``identification``: the identification data's segments, if
    another than ``segments`` (the physically consistent estimate's fit error is then measured
    at their stamps too); ``identified_on``, ``validated_on``: the data's names (by default
    the recordings' file names)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    has_validation = bool(doc.get("validation"))
    validation = segments if has_validation else None
    identification = identification if identification is not None else (None if has_validation else segments)
    identified_on = identified_on or _data_name(identification, "the identification data")
    validated_on = validated_on or _data_name(validation, "the validation data")
    shown = validated_on if has_validation else identified_on
    robot = result.robot
    # what the error figures measure: the model at every sample's own stamp against the raw torque
    t, tau, tau_hat = result.predict_stamps(list(segments))
    x, joins = elapsed(t)
    plots = []
    for j in range(robot.n_joints):
        unit = joint_units(robot, j)["tau"]
        fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
        ax1.plot(x, tau[:, j], lw=0.8, label="measured")
        ax1.plot(x, tau_hat[:, j], lw=0.8, label="predicted")
        ax1.set_ylabel(f"tau{j + 1} [{unit}]")
        ax1.legend(loc="upper right")
        ax2.plot(x, tau[:, j] - tau_hat[:, j], lw=0.6, color="tab:red")
        ax2.set_ylabel(f"residual [{unit}]")
        for ax in (ax1, ax2):
            for at in joins:
                ax.axvline(at, color="k", lw=0.6, ls="--")
        ax2.set_xlabel(_time_label(joins, shown))
        fig.suptitle(f"{robot.name} joint {j + 1}: {title} ({shown}), all {len(t):,} samples at their stamps")
        fig.tight_layout()
        name = f"joint{j + 1}.png"
        fig.savefig(out_dir / name, dpi=90)
        plt.close(fig)
        plots.append(name)
    lines = [f"# Identification of {doc['robot']}", ""]
    equations = doc["fit"].get("equations")
    lines.append(f"Identified on {identified_on}: {doc['samples']} samples" + (f" ({equations} of them in the equations as fitted)" if equations else "")
                 + f", {doc['weighting'].upper()}, {len(doc['base_parameters'])} base parameters, rank {doc['rank']}; condition number "
                 f"{doc['condition_number']:.3g} (of {identified_on}'s base regressor as weighted, its columns scaled to unit norm).")
    lines += ["", "## Errors", ""]
    error_lines, stamps = _error_rows(result, doc, identification, validation, identified_on, validated_on)
    lines += error_lines
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
        # the consistency check's own figures only where the page cannot give both models' at the stamps
        at_stamps = stamps["fit"] is not None and (stamps["validation"] is not None or not has_validation)
        lines += [""] + feasible_section(doc["feasible"], errors=not at_stamps)
        if at_stamps:
            lines += ["", "Its errors: the table under Errors."]
    lines += ["", f"## Torques ({title}: {shown})", "",
              f"Measured and predicted at each of the {len(t):,} samples' own stamps, as the errors above measure them; "
              f"time from the first sample of {shown}" + (" (recordings laid end to end, joined at the dashed lines)" if joins else "") + ".", ""]
    lines += [f"![joint {k + 1}]({p})" for k, p in enumerate(plots)]
    path = out_dir / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _shown(used: np.ndarray) -> tuple[np.ndarray, str]:
    """The samples a diagnosis panel plots (the ``used`` ones, thinned to at most
    :data:`MAX_POINTS`) and the phrase that says which."""
    index = np.flatnonzero(used)
    k = max(1, math.ceil(index.size / MAX_POINTS))
    text = (f"the {index.size:,} of {used.size:,} validation samples where the joint moves (clear of rest and of a velocity reversal: "
            "the samples the diagnosis scores)" if index.size < used.size else f"all {used.size:,} validation samples")
    if k > 1:
        text += f", every {_ordinal(k)} of them ({index[::k].size:,} shown)"
    return index[::k], text


def write_diagnosis_report(diag: Any, robot: Robot | str, out_dir: Path, feasible: dict[str, Any] | None = None,
                           identified_on: str = "the identification data", validated_on: str = "the validation data") -> Path:
    """``diagnosis.md``: one sentence per finding, the declared model's validation error and
    the model's with the findings, per joint the error before and after, and the held-out
    residual against velocity (friction), position (cogging, spring, tilt), acceleration
    (rotor inertia) and time (drift), before and after; with ``feasible`` (``diagnose
    --feasible``), the consistency report of the model with the findings.

    ``robot``: the robot (its joints' units on the axes), or its name alone (axes then say
    "N*m or N"); ``identified_on``, ``validated_on``: the data's names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    model = robot if isinstance(robot, Robot) else None
    robot_name = robot.name if isinstance(robot, Robot) else robot
    out_dir.mkdir(parents=True, exist_ok=True)
    tau, before = diag.residual_before
    _, after = diag.residual_after
    t, q, qd, qdd = diag.validation_motion
    x_t, joins = elapsed(t)
    used = diag.used if diag.used is not None else np.ones_like(tau, bool)
    plots, which = [], []
    for j in range(tau.shape[1]):
        units = joint_units(model, j)
        k, text = _shown(used[:, j])
        which.append(text)
        fig, axes = plt.subplots(1, 4, figsize=(15, 3.6), sharey=True)
        panels = ((qd[:, j], f"velocity qd{j + 1} [{units['qd']}]"), (q[:, j], f"position q{j + 1} [{units['q']}]"),
                  (qdd[:, j], f"acceleration qdd{j + 1} [{units['qdd']}]"), (x_t, _time_label(joins, validated_on)))
        for ax, (x, label) in zip(axes, panels):
            ax.plot(x[k], (tau - before)[k, j], ".", ms=1.5, alpha=0.4, color="tab:red", label="before")
            ax.plot(x[k], (tau - after)[k, j], ".", ms=1.5, alpha=0.4, color="tab:blue", label="after")
            ax.set_xlabel(label)
        axes[0].set_ylabel(f"residual tau{j + 1} [{units['tau']}]")
        axes[0].legend(loc="upper right", markerscale=6)
        fig.suptitle(f"{robot_name} joint {j + 1}: held-out residual before (red) and after (blue) the findings\n{text}", fontsize=10)
        fig.tight_layout()
        name = f"diagnosis_joint{j + 1}.png"
        fig.savefig(out_dir / name, dpi=90)
        plt.close(fig)
        plots.append(name)
    b, a = diag.before, diag.after
    samples = f"all {len(diag.predictions[0]):,} samples of {validated_on}" if diag.predictions is not None else validated_on
    n_found = len(diag.found)
    lines = [f"# Diagnosis: {robot_name}", "",
             f"Relative error |tau - tau_hat| / |tau| at {samples}, each at its own time stamp, against the raw measured torque; "
             f"each model identified on {identified_on}:", "",
             "| model | validation error |", "|---|---|",
             f"| the declared model (the robot file's effects; `armid identify`'s least squares) | {percent(b['relative_error'])} |",
             (f"| with the {n_found} finding{'' if n_found == 1 else 's'} below | **{percent(a['relative_error'])}** |" if n_found
              else f"| with its findings (none: the same model) | {percent(a['relative_error'])} |")]
    floor = (diag.noise_floor or {}).get("relative_error")
    if floor is not None:
        lines += ["", f"Noise floor of {validated_on}: {percent(floor)} (its torque above the low-pass cut-off at its own stamps, "
                      "over its norm: the error no model of the motion goes below)."]
    lines += ["", "## Findings", ""]
    lines += [f"- {f.sentence()}" for f in diag.found] or [f"- {diag.verdict()}"]
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
              f"## Error per joint (validation, {validated_on})", "",
              "| joint | unit | RMS before | RMS after | relative before | relative after |", "|---|---|---|---|---|---|"]
    for j in range(tau.shape[1]):
        lines.append(f"| {j + 1} | {joint_units(model, j)['tau']} | {b['rms'][j]:.4g} | {a['rms'][j]:.4g} | "
                     f"{percent(b['relative'][j])} | {percent(a['relative'][j])} |")
    if feasible:
        lines += [""] + feasible_section(feasible, model="least squares with the findings")
    lines += ["", "## Residual against velocity, position, acceleration and time", "",
              f"Validation data ({validated_on}) as the diagnosis fits it (its samples on the regular grid); time from its first "
              "sample" + (" (recordings laid end to end)" if joins else "") + ". Each plot shows:", ""]
    lines += [f"- joint {j + 1}: {text}" for j, text in enumerate(which)]
    lines += [""] + [f"![joint {k + 1}]({p})" for k, p in enumerate(plots)]
    path = out_dir / "diagnosis.md"
    path.write_text("\n".join(lines) + "\n")
    return path

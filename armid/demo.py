"""``armid demo``: the main job on the embedded default rig, in one process.

The simulated PUMA 560 on a virtual CAN bus (``config/rigs/sim.yaml``: CiA 402 drives,
2 ms SYNC, friction, rotor inertia, quantisation, current noise); Khosla's single-link
experiments from link 6 to link 1 and two whole-arm runs, all designed and checked before
any drive is enabled, run through the CANopen driver and recorded as MCAP; the
single-link sequence and the whole-arm identification, each against the simulator's
known parameters; diagnosis of the residual; on-line payload estimation; a report.
"""

from __future__ import annotations

import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from daq.excite import ExcitationSession
from drivers.rig import Rig, load_rig
from identify.identification import IdentificationResult, IdentifyOptions, identify
from identify.single_link import SequenceResult, single_link_sequence

from .experiments import design_experiments, prepared_runs, run_experiments, write_json

DEFAULT_RIG = Path(__file__).resolve().parent.parent / "config" / "rigs" / "sim.yaml"


def true_parameters(rig: Rig, names: list[str]) -> np.ndarray:
    """The simulated arm's parameters in the order of ``names`` (rigid body, then fv, fc, ia)."""
    from sim_bus.physics import simulation_config

    cfg = simulation_config(rig.simulation, rig.n_joints, rig.source)
    phi = np.zeros(len(names))
    n_std = rig.robot.n_parameters
    phi[:n_std] = np.asarray(cfg.parameters, float) if cfg.parameters is not None else rig.robot.modeled_parameters()
    fields = {"fv": "viscous", "fc": "coulomb", "ia": "rotor_inertia"}
    for k, name in enumerate(names[n_std:], n_std):
        prefix, joint = name.rstrip("0123456789"), int(name[len(name.rstrip("0123456789")):]) - 1
        if prefix in fields:
            phi[k] = getattr(cfg.effects(joint), fields[prefix])
    return phi


def _z_scores(values: np.ndarray, stds: np.ndarray, truth: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        return (values - truth) / stds


def check_against_truth(rig: Rig, seq: SequenceResult, whole: IdentificationResult) -> dict[str, Any]:
    """Every identified combination against its true value: |z| = |estimate - truth| / std."""
    phi_seq = true_parameters(rig, seq.names)
    z_seq = _z_scores(seq.beta, seq.std, np.array([fn.row @ phi_seq for fn in seq.functionals]))
    phi_whole = true_parameters(rig, whole.names)
    z_whole = _z_scores(whole.estimate.beta, whole.estimate.std, whole.base.base_values(phi_whole))
    return {
        "single_link": {"combinations": int(z_seq.size), "within_3_sigma": int(np.sum(np.abs(z_seq) <= 3)), "max_abs_z": float(np.max(np.abs(z_seq))),
                        "z": z_seq.tolist()},
        "whole_arm": {"combinations": int(z_whole.size), "within_3_sigma": int(np.sum(np.abs(z_whole) <= 3)), "max_abs_z": float(np.max(np.abs(z_whole))),
                      "z": z_whole.tolist()},
    }


def run_demo(out: Path, rig_path: Path | None = None, seed: int = 0) -> int:
    from rich.console import Console

    console = Console(stderr=True)
    started = time.monotonic()
    rig = load_rig(rig_path or DEFAULT_RIG)
    rig = rig.with_bus(channel=f"armid-demo-{uuid.uuid4().hex[:8]}") if rig.bus.interface == "virtual" else rig
    robot = rig.robot
    out.mkdir(parents=True, exist_ok=True)
    console.print(f"[bold]armid demo[/]: {rig.name}: {robot.n_joints} CiA 402 drives on {rig.bus.interface}:{rig.bus.channel}, "
                  f"{rig.period_s * 1000:g} ms SYNC; output in {out}")
    start = np.asarray(rig.simulation.get("initial_position", np.zeros(robot.n_joints)), float)
    links = list(range(robot.n_joints - 1, -1, -1))  # Khosla: last link first
    experiments = design_experiments(robot, start, links, [("whole_a", 2), ("whole_b", 1)], rig.period_s, seed=seed,
                                     log=lambda m: console.print(f"  {m}"))
    write_json(out / "designs.json", {e.name: e.design.to_json() for e in experiments})
    console.print(f"designed and checked {len(experiments)} trajectories against every limit in {time.monotonic() - started:.1f} s; running them")
    with ExcitationSession(rig, simulate=True) as session:
        reports = run_experiments(session, experiments, out / "runs", console)
    write_json(out / "runs.json", [r.to_json() for r in reports])
    failed = [r for r in reports if not r.completed]
    if failed:
        console.print(f"[red]run {failed[0].name} stopped: {failed[0].stop_reason}[/]")
        return 1
    console.print("identifying")
    prepared = prepared_runs(reports, robot, rig.period_s)
    seq = single_link_sequence(robot, {e.link: [prepared[e.name]] for e in experiments if e.link is not None})
    whole = identify(robot, [prepared["whole_a"]], [prepared["whole_b"]], IdentifyOptions(exclude_reversals=True))
    truth = check_against_truth(rig, seq, whole)
    comparison = seq.compare(whole)
    console.print("diagnosing the residual")
    from identify.diagnosis import diagnose

    diagnosis = diagnose(robot, [prepared["whole_a"]], [prepared["whole_b"]])
    doc = {"rig": rig.name, "single_link": seq.to_json(), "whole_arm": whole.to_json(), "comparison": comparison, "truth_check": truth,
           "diagnosis": diagnosis.to_json(), "runs": [r.to_json() for r in reports]}
    write_json(out / "demo.json", doc)
    _write_report(out, rig, experiments, reports, seq, whole, comparison, truth, diagnosis, prepared)
    s, w = truth["single_link"], truth["whole_arm"]
    console.print(f"single-link sequence: {s['within_3_sigma']} of {s['combinations']} combinations within 3 sigma of the truth "
                  f"(max |z| {s['max_abs_z']:.2f}); whole arm: {w['within_3_sigma']} of {w['combinations']} (max |z| {w['max_abs_z']:.2f}); "
                  f"validation error {100 * whole.validation['relative_error']:.2f} %")  # type: ignore[index]
    console.print(f"diagnosis: {len(diagnosis.found)} finding(s); validation error {100 * diagnosis.before['relative_error']:.2f} % -> "
                  f"{100 * diagnosis.after['relative_error']:.2f} %")
    console.print(f"[bold]report:[/] {out / 'report.md'} ({time.monotonic() - started:.0f} s)")
    return 0


def _write_report(out: Path, rig: Rig, experiments: list[Any], reports: list[Any], seq: SequenceResult, whole: IdentificationResult,
                  comparison: list[dict[str, Any]], truth: dict[str, Any], diagnosis: Any, prepared: dict[str, Any]) -> None:
    from .report import write_diagnosis_report, write_report

    def f(x: float | None, d: int = 5) -> str:
        return "—" if x is None else f"{x:.{d}g}"

    write_report(whole, whole.to_json(), [s for s in prepared["whole_b"].segments], out / "whole_arm", "validation run whole_b")
    write_diagnosis_report(diagnosis, rig.robot.name, out / "diagnosis")
    lines = [f"# armid demo: {rig.name}", "",
             f"Simulated {rig.robot.name} on a {rig.bus.interface} CAN bus, {len(rig.drives)} CiA 402 drives, {rig.period_s * 1000:g} ms SYNC. "
             "Every trajectory was designed (D-optimal finite Fourier series) and checked against every limit before any drive was enabled.", "",
             "## Runs", "", "| run | moving joints | duration s | records | max tracking error mrad | peak torque % of limit | condition number |",
             "|---|---|---|---|---|---|---|"]
    for e, r in zip(experiments, reports):
        lines.append(f"| {r.name} | {', '.join(str(j + 1) for j in e.design.moving)} | {e.plan.duration_s:.1f} | {r.records} | "
                     f"{1000 * max(r.max_tracking_error):.1f} | {100 * max(r.peak_torque_fraction):.0f} | {e.design.condition_number:.3g} |")
    s, w = truth["single_link"], truth["whole_arm"]
    lines += ["", "## Against the simulator's known parameters", "",
              f"- single-link sequence (links {', '.join(str(st['link']) for st in seq.steps)}): **{s['within_3_sigma']} of {s['combinations']}** "
              f"identified combinations within 3 sigma (max |z| {s['max_abs_z']:.2f})",
              f"- whole-arm run: **{w['within_3_sigma']} of {w['combinations']}** base parameters within 3 sigma (max |z| {w['max_abs_z']:.2f}); "
              f"condition number {whole.excitation.condition_number:.3g}; validation error on whole_b {100 * whole.validation['relative_error']:.2f} %",  # type: ignore[index]
              "", "## Single-link sequence (Khosla Tables 2-4)", "", "| link | parameter | initial (modeled) | estimate | std | z vs truth |", "|---|---|---|---|---|---|"]
    for row, z in zip(seq.table(), s["z"]):
        lines.append(f"| {row['link']} | `{row['parameter']}` | {f(row['modeled'])} | {f(row['estimate'])} | {f(row['std'], 3)} | {z:+.2f} |")
    lines += ["", "## Whole-arm base parameters beside the single-link sequence", "",
              "| base parameter | whole arm | std | single-link sequence | std |", "|---|---|---|---|---|"]
    for c in comparison:
        lines.append(f"| `{c['expression']}` | {f(c['whole_arm'])} | {f(c['whole_arm_std'], 3)} | {f(c['single_link'])} | {f(c['single_link_std'], 3)} |")
    b, a = diagnosis.before, diagnosis.after
    lines += ["", "## Diagnosis of the residual", "", f"Validation error {100 * b['relative_error']:.3g} % -> {100 * a['relative_error']:.3g} %.", ""]
    lines += [f"- {fd.sentence()}" for fd in diagnosis.found] or ["- nothing significant: the declared model explains the data to its noise"]
    lines += ["", "Details: [whole_arm/report.md](whole_arm/report.md), [diagnosis/diagnosis.md](diagnosis/diagnosis.md), `demo.json`, `designs.json`, "
              "recordings in `runs/*/run.mcap` (Foxglove, PlotJuggler, `armid identify`)."]
    (out / "report.md").write_text("\n".join(lines) + "\n")

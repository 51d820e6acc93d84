"""``armid demo``: the main job on the embedded default rig, in one process.

The simulated PUMA 560 on a virtual CAN bus (``config/rigs/sim.yaml``: CiA 402 drives,
2 ms SYNC, friction, rotor inertia, quantisation, current noise); Khosla's single-link
experiments from link 6 to link 1 and two whole-arm runs, the first designed before the
drives start and the others beside the runs, each checked against every limit before it runs,
run through the CANopen driver and recorded as MCAP; the
single-link sequence and the whole-arm identification, each against the simulator's
known parameters; diagnosis of the residual; on-line payload estimation; a report.
"""

from __future__ import annotations

import multiprocessing
import os
import secrets
import time
import uuid
from concurrent.futures import ProcessPoolExecutor
from contextlib import ExitStack, closing
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from rich.markup import escape

from armid.drivers.rig import Rig
from armid.identify import excitation as ex
from armid.identify.identification import IdentificationResult
from armid.identify.preprocess import Prepared
from armid.identify.robot import Robot
from armid.identify.single_link import SequenceResult, single_link_sequence
from armid.io.rig_file import load_rig
from armid.resources import config_file
from armid.schema.errors import DriverError, SimulationError

from .demo_clock import (
    ANALYSIS_CPU_S,
    CORES,
    ESTIMATOR_ABOVE,
    PAYLOAD_OVERHEAD_S,
    PER_RUN_S,
    PHASE_ESTIMATES_S,
    REPORT_S,
    RUNS_START_S,
    IdleCpu,
    Phases,
    Share,
    analysis_share_over_the_payload_run,
)
from .experiments import (
    WHOLE_MARGIN,
    ExperimentsBeside,
    identify_whole_arm,
    prepared_runs,
    run_experiments,
    service_agreement,
)
from .kernels import compiled_ahead
from .peer import Meeting, Peer, PeerLink
from .schema.json_text import write_json
from .simulated import excitation_session

DEFAULT_RIG = config_file("rigs/sim.yaml")  # package data: found in a wheel install too


def true_parameters(rig: Rig[Robot], names: list[str]) -> np.ndarray:
    """The simulated arm's parameters in the order of ``names`` (rigid body, then fv, fc, ia)."""
    from armid.sim_bus.physics import simulation_config

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


def _truth_test(values: np.ndarray, covariance: np.ndarray, truth: np.ndarray, names: list[str], batches: int | None = None) -> dict[str, Any]:
    """Each combination's z = (estimate - truth) / std, and all of them together: the
    Mahalanobis distance ``T^2 = d' C^-1 d``, chi-square with as many degrees of freedom as
    combinations when the covariance is known. A covariance estimated from ``batches`` batch
    means (the whole arm's, :func:`identify.estimation.batch_means_covariance`) is itself
    uncertain, and its inverse weighs the least-determined directions too much: with ``batches``
    their effective count m (:func:`identify.estimation.effective_batches`),
    ``T^2 (m - p) / (p (m - 1))`` is F(p, m - p) (Hotelling), whose mean is 1 where every
    standard deviation is right (``per_dof``). With 28 combinations one beyond 3 sigma comes
    in 7 % of noise draws (1 - 0.9973^28) even so; the joint test's p-value says whether the
    draw as a whole is unusual. ``misses``: the combinations beyond 3 sigma, named, with
    value, truth, std and z, the largest |z| first."""
    from scipy.stats import chi2, f

    d = values - truth
    std = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    z = _z_scores(values, std, truth)
    distance = float(d @ np.linalg.lstsq(covariance, d, rcond=None)[0])
    p = int(z.size)
    misses = [{"name": names[k], "value": float(values[k]), "truth": float(truth[k]), "std": float(std[k]), "z": float(z[k])}
              for k in sorted(np.flatnonzero(~(np.abs(z) <= 3)), key=lambda k: -abs(float(np.nan_to_num(z[k], nan=np.inf))))]
    if batches is not None and batches > p + 1:
        per_dof = distance * (batches - p) / (p * (batches - 1))
        joint = {"per_dof": per_dof, "chi2_p": float(f.sf(per_dof, p, batches - p)), "batches": int(batches),
                 "test": f"Hotelling: T^2 (m - p) / (p (m - 1)) against F({p}, {batches - p}), the covariance from batch means worth m = {batches}"}
    else:
        joint = {"per_dof": distance / p, "chi2_p": float(chi2.sf(distance, p)), "batches": None, "test": f"chi-square on {p} degrees of freedom"}
    return {"combinations": p, "within_3_sigma": int(np.sum(np.abs(z) <= 3)), "max_abs_z": float(np.max(np.abs(z))),
            "chi2": distance, **joint, "z": z.tolist(), "truth": truth.tolist(), "misses": misses}


def check_against_truth(rig: Rig[Robot], seq: SequenceResult, whole: IdentificationResult) -> dict[str, Any]:
    """Every identified combination against its true value, one by one and together."""
    phi_seq = true_parameters(rig, seq.names)
    phi_whole = true_parameters(rig, whole.names)
    return {"single_link": _truth_test(seq.beta, seq.covariance, np.array([fn.row @ phi_seq for fn in seq.functionals]),
                                       [f"link {fn.link + 1}: {fn.expression}" for fn in seq.functionals]),
            "whole_arm": _truth_test(whole.estimate.beta, whole.estimate.covariance, whole.base.base_values(phi_whole),
                                     whole.base.expressions(), whole.covariance_batches)}


def _identify_and_analyse(rig: Rig[Robot], reports: list[Any], links: dict[int, str], out: Path) -> dict[str, Any]:
    """Everything the demo finds in its recordings, made beside the payload run in a process of its
    own: each run's recording through the pipeline, the single-link sequence and the whole arm
    (validated on whole_b) as the estimator service made them, both against the simulator's known
    parameters, then :func:`analyse`. The pipeline's warnings are returned to be said."""
    robot = rig.robot
    warnings: list[str] = []
    prepared = prepared_runs(reports, robot, rig.period_s, warn=warnings.append)
    whole = identify_whole_arm(robot, prepared["whole_a"], [prepared["whole_b"]])
    seq = single_link_sequence(robot, {link: [prepared[name]] for link, name in links.items()})
    truth = check_against_truth(rig, seq, whole)
    diagnosis, feasible_line, whole_doc = analyse(robot, whole, prepared["whole_a"], prepared["whole_b"], out)
    return {"whole": whole, "seq": seq, "truth": truth, "comparison": seq.compare(whole), "diagnosis": diagnosis,
            "feasible_line": feasible_line, "whole_doc": whole_doc, "warnings": warnings}


def _ready_to_analyse() -> int:
    """The analysis's imports, made while the arm moves (the process has little else to do then); its id."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot  # noqa: F401

    from armid.identify.feasible import feasible_estimate  # noqa: F401

    from . import pipeline, report  # noqa: F401

    return os.getpid()


def _at_priority(pid: int, above: int = 0) -> None:
    """A process of the demo's at this process's priority, or ``above`` it (where allowed: as root;
    without the privilege it stays where it is). The analysis comes back from below once no run
    of the drives it could delay is left but the payload run, whose real-time thread outranks it
    anyway; the payload estimator, which must keep up with the live stream, goes above it."""
    try:
        os.setpriority(os.PRIO_PROCESS, pid, os.getpriority(os.PRIO_PROCESS, 0) - above)
    except OSError:
        pass


def _demo_rig(rig_path: Path, arm_seed: int | None) -> tuple[Rig[Robot], int]:
    """The demo's rig on a virtual bus of its own, and the seed of its simulated drives' current noise:
    a draw of its own per demo (``--arm-seed`` repeats one). With the rig file's fixed seed every demo
    measured the same noise, shifted by the few dozen cycles its scheduling moved a run: one draw of
    2-3 sigma errors (fc3 +2.9, Iyy3 -2.6, msz5 + msz6 +2.4) in every run, which looked like a bias
    and failed 8 of 10 demos."""
    rig = load_rig(rig_path)
    rig = rig.with_bus(channel=f"armid-demo-{uuid.uuid4().hex[:8]}") if rig.bus.interface == "virtual" else rig
    arm_seed = secrets.randbits(31) if arm_seed is None else arm_seed
    return replace(rig, simulation={**rig.simulation, "seed": arm_seed}), arm_seed


DESIGN_PHASE = ("designing {n} exciting trajectories (D-optimal finite Fourier series: one per link, last link first, then two "
                "whole-arm): the first here, the others in a process of their own while the drives run the first; each is checked "
                "against every limit before it runs")
PAYLOAD_PHASE = ("payload: the identified arm works through whole_a; a 2 kg payload is attached and removed, estimated on-line from "
                 "the live Zenoh stream by `armid estimate live` in a process of its own; meanwhile, in another, the single-link "
                 "sequence (links 6 to 1) and the whole arm (validated on whole_b) are identified as the estimator service did, both "
                 "checked against the simulator's known parameters, the residual diagnosed and the physically consistent model "
                 "computed; then the report")


def _at_the_runs_pace(phases: Phases, experiments: ExperimentsBeside, idle: IdleCpu) -> None:
    """The runs' and the payload phase's estimates as a plan is handed over to run (the runs
    before it done): the motion left at the pace of the runs so far (a loaded machine stretches
    the arm's clock: 21-43 % short announcements late in the runs when taken at 1.0), and the
    payload phase, once whole_a is designed, as long as its plan at that pace or the analysis
    beside it at the share it will get, whichever is longer (beside two busy loops the payload
    run alone made the announcements 15-23 % short)."""
    done = [e.plan.duration_s for e in experiments.experiments[:-1]]
    elapsed = time.monotonic() - phases.phase_started
    moving = elapsed - experiments.waited_s - RUNS_START_S / 2  # the arm held while a design was awaited: not its pace
    pace = max(1.0, moving / (sum(done) + len(done) * PER_RUN_S)) if done else 1.0
    left = len(experiments) - len(done)
    phases.estimates["runs"] = elapsed + (experiments.motion_s - sum(done)) * pace + left * PER_RUN_S + RUNS_START_S / 2
    whole_a = [e for e in experiments.experiments if e.name == "whole_a"]
    if whole_a:
        analysis_s = ANALYSIS_CPU_S / analysis_share_over_the_payload_run(idle.cores()) + REPORT_S
        phases.estimates["payload"] = max(whole_a[0].plan.duration_s * pace + PAYLOAD_OVERHEAD_S, analysis_s)


def run_demo(out: Path, rig_path: Path | None = None, seed: int = 0, arm_seed: int | None = None) -> int:
    from rich.console import Console
    from threadpoolctl import threadpool_limits

    console = Console(stderr=True)
    started = time.monotonic()
    rig_path = rig_path or DEFAULT_RIG
    rig, arm_seed = _demo_rig(rig_path, arm_seed)
    robot = rig.robot
    out.mkdir(parents=True, exist_ok=True)
    console.print(f"[bold]armid demo[/]: {rig.name}: {robot.n_joints} CiA 402 drives on {rig.bus.interface}:{rig.bus.channel}, "
                  f"{rig.period_s * 1000:g} ms SYNC, arm seed {arm_seed}; output in {out}")
    # the designs compute (the rest is the arm's real time): a machine busy beyond its cores makes them slower
    phases = Phases(console, {**PHASE_ESTIMATES_S, "design": PHASE_ESTIMATES_S["design"] * max(1.0, os.getloadavg()[0] / CORES)})
    start = np.asarray(rig.simulation.get("initial_position", np.zeros(robot.n_joints)), float)
    links = list(range(robot.n_joints - 1, -1, -1))  # Khosla: last link first
    whole_runs = [("whole_a", 2), ("whole_b", 1)]
    # OpenBLAS's threads stall on a loaded 2-core machine, and the demo's products are small; the kernels that the runs
    # and the payload estimator will need compile on the other core while the first design is made, and the estimator
    # service starts meanwhile (``peers``: the processes started ahead, ended with the demo on any error)
    with threadpool_limits(1, "blas"), compiled_ahead(rig_path), ExitStack() as peers:
        # where the demo meets its peers, and where a viewer joins them (loopback only)
        meeting = Meeting()
        peers.callback(meeting.close)
        zenoh_doc = {"endpoint": meeting.endpoint, "watch": meeting.watch_command(robot.name)}
        console.print(f"  the estimator service and the payload estimator meet the demo on {meeting.endpoint} (loopback only); "
                      "to watch them live from another terminal:")
        console.print(f"    {escape(zenoh_doc['watch'])}", soft_wrap=True)  # one line, whatever the width: to be copied
        phases.start("design", DESIGN_PHASE.format(n=len(links) + len(whole_runs)))
        service = peers.enter_context(closing(_estimator_service(rig, out, meeting)))
        def designed(line: str) -> None:  # a plan comes in beside the runs, as the one before it ends
            if phases.current == "runs":
                _at_the_runs_pace(phases, experiments, idle)
            phases.note(line)

        experiments = peers.enter_context(closing(ExperimentsBeside(robot, start, links, whole_runs, rig.period_s, seed=seed, log=designed)))
        phases.estimates.update(design=time.monotonic() - phases.phase_started,
                                runs=experiments.motion_s + len(experiments) * PER_RUN_S + RUNS_START_S)
        # the analysis is not the real-time process's business: a process of its own, its imports made while the arm moves, below
        # the real-time process's priority (spawned: a fork would copy this process's threads' locks; ended with the demo, work cancelled)
        beside = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), initializer=_below_the_real_time)
        peers.callback(beside.shutdown, cancel_futures=True)
        analysis_pid = beside.submit(_ready_to_analyse)
        idle = IdleCpu()  # the CPU the demo leaves over its runs: how busy the machine is beside it
        phases.start("runs", f"running the {len(experiments)} experiments on the drives in real time ({experiments.motion_s:.0f} s of motion, "
                     "2 ms SYNC over the virtual CAN bus), each recorded as MCAP")
        runs_began = time.monotonic()
        # the payload estimator starts on the service's whole_a fit once the last run's records are all out (it meets
        # the demo where the service does): its imports are made while the drives stop and the payload's drives start
        early: list[PeerLink] = []

        def start_the_payload_estimator() -> None:
            service.wait(lambda: _published_fit(service.docs, "whole_a") is not None or len(service.docs) >= len(experiments), 300)
            if (fit := _published_fit(service.docs, "whole_a")) is not None:
                early.append(peers.enter_context(closing(payload_estimator(rig, fit, out, meeting))))
                _at_priority(early[0].peer.proc.pid, above=ESTIMATOR_ABOVE)

        reports, published = _runs_beside_the_service(rig, service, experiments, out, console, start_the_payload_estimator)
        write_json(out / "designs.json", {e.name: e.design.to_json() for e in experiments.experiments})
        motion_s = sum(e.plan.duration_s for e in experiments.experiments)
        stretch = (time.monotonic() - runs_began - RUNS_START_S - len(reports) * PER_RUN_S) / motion_s
        write_json(out / "runs.json", [r.to_json() for r in reports])
        failed = [r for r in reports if not r.completed]
        if failed:
            console.print(f"[red]run {failed[0].name} stopped: {failed[0].stop_reason}[/]")
            return 1
        write_json(out / "service.json", published)
        analysis = beside.submit(_identify_and_analyse, rig, reports, {e.link: e.name for e in experiments.experiments if e.link is not None}, out)
        pid = analysis_pid.result()
        _at_priority(pid)
        share = Share(pid, ANALYSIS_CPU_S)
        if early:
            estimator = early[0]
        else:  # the service published no whole_a fit: the one made from the complete recordings
            prepared = prepared_runs([r for r in reports if r.name.startswith("whole")], robot, rig.period_s)
            fit = identify_whole_arm(robot, prepared["whole_a"], [prepared["whole_b"]]).to_json()
            estimator = peers.enter_context(closing(payload_estimator(rig, fit, out, meeting)))
            _at_priority(estimator.peer.proc.pid, above=ESTIMATOR_ABOVE)
        # the phase's end: the payload run and its last estimates, or the analysis beside it, whichever comes
        # last, at the share of a core it gets over the run; then the report. A longer wait is said when the run ends
        payload_plan = ex.plan(experiments.experiments[-2].design, start, ex.Limits.of(robot), periods=2, lead_fraction=WHOLE_MARGIN)
        payload_s = payload_plan.duration_s * max(stretch, 1.0) + PAYLOAD_OVERHEAD_S

        def drives_up() -> None:
            analysis_s = max(ANALYSIS_CPU_S - share.used_s(), 0.3) / analysis_share_over_the_payload_run(idle.cores()) + REPORT_S
            phases.estimates.update(runs=time.monotonic() - phases.phase_started, payload=max(payload_s, analysis_s))
            phases.start("payload", PAYLOAD_PHASE)

        plotted: list[Any] = []
        payload = run_payload(rig, estimator, experiments.experiments[-2].design, out, plot=lambda *a: plotted.append(beside.submit(_plot_payload, *a)),
                              drives_up=drives_up)
        during_run = share.used_s()
        # a wait worth saying on its own: the analysis's CPU varies (4.9-6.7 s), and a wait of 3-5 s said
        # from it was 1-2 s off (+36-44 %); a shorter one is within the phase's announcement
        if not analysis.done() and (left := share.left_s(measure_s=0.3)) > 6.0:
            phases.estimates["payload"] = time.monotonic() - phases.phase_started + left + REPORT_S
            phases.note("the payload run is done; the analysis beside it is not yet")
        done = analysis.result()
        for f in plotted:
            f.result()
        phases.mark("analysis done")
        analysis_cpu = {"during_payload_run_s": round(during_run, 2), "total_s": round(share.used_s(), 2), "idle_cores_over_the_runs": idle.last}
        _ended_meanwhile(beside, peers)
        whole, seq, truth, comparison, diagnosis = done["whole"], done["seq"], done["truth"], done["comparison"], done["diagnosis"]
        for w in done["warnings"]:
            console.print(f"  [yellow]warning:[/] {escape(w)}")
        agreement = service_agreement(published[-1], whole)
        console.print(f"  the estimator service published {len(published)} estimates; records it missed "
                      f"{sum(d['experiment']['missing'] for d in published)}; its whole_a fit against the recording's: "
                      f"{agreement['max_difference_sigma']:.2g} sigma at most")
        _write_report(out, rig, experiments.experiments, reports, seq, whole, done["whole_doc"], comparison, truth, diagnosis, payload)
        doc = {"rig": rig.name, "arm_seed": arm_seed, "zenoh": zenoh_doc, "analysis_cpu": analysis_cpu, "single_link": seq.to_json(), "whole_arm": done["whole_doc"],
               "comparison": comparison, "truth_check": truth, "service": agreement, "diagnosis": diagnosis.to_json(), "payload": payload,
               "runs": [r.to_json() for r in reports]}
        phases.mark("report written")
    _say_the_figures(console, done, payload)
    console.print(f"[bold]report:[/] {out / 'report.md'} ({time.monotonic() - started:.0f} s)")
    # the timeline last, every process ended: each announced time left beside the time that followed
    write_json(out / "demo.json", {**doc, "timeline": phases.honesty(), "stretch": round(stretch, 3)})
    return 0


def _say_the_figures(console: Any, done: dict[str, Any], payload: dict[str, Any]) -> None:
    """The demo's figures in a few lines: the truth checks, the consistent model, the diagnosis, the payload
    (``done``: :func:`_identify_and_analyse`'s)."""
    truth, whole, diagnosis = done["truth"], done["whole"], done["diagnosis"]
    s, w = truth["single_link"], truth["whole_arm"]
    console.print(f"single-link sequence: {s['within_3_sigma']} of {s['combinations']} combinations within 3 sigma of the truth "
                  f"(max |z| {s['max_abs_z']:.2f}; together {s['per_dof']:.2f} per dof, p {s['chi2_p']:.2f}); "
                  f"whole arm: {w['within_3_sigma']} of {w['combinations']} (max |z| {w['max_abs_z']:.2f}; together {w['per_dof']:.2f} "
                  f"per dof, p {w['chi2_p']:.2f}); validation error {100 * whole.validation['relative_error']:.2f} %")  # type: ignore[index]
    # every error here as the report gives it: each validation sample at its own stamp against the raw torque, in %
    consistent = ((done["whole_doc"].get("feasible") or {}).get("at_stamps") or {}).get("validation") or {}
    figure = f"; validation error {100 * consistent['relative_error']:.2f} %" if "relative_error" in consistent else ""
    console.print(f"physically consistent whole-arm model: {done['feasible_line']}{figure} (identified.urdf)")
    console.print(f"diagnosis (the declared model as `armid identify` fits it: every sample): {len(diagnosis.found)} finding(s); "
                  f"validation error {100 * diagnosis.before['relative_error']:.2f} % -> {100 * diagnosis.after['relative_error']:.2f} %")
    p2 = payload["after_attach_2s"]
    console.print(f"payload: 2 s after the attach {_num(p2['mass'], 1, 3)} kg (true {payload['true_mass']} kg), centre of mass off by "
                  f"{_num(p2['com_error_m'], 1000, 1)} mm; 2 s after the removal {_num(payload['after_removal_2s']['mass'], 1, 3)} kg; "
                  f"{payload['estimates']} estimates at 50 Hz")


def analyse(robot: Robot, whole: IdentificationResult, run: Prepared, validation: Prepared, out: Path) -> tuple[Any, str, dict[str, Any]]:
    """What the payload phase does not need, made while it runs: the diagnosis of the whole-arm
    run's residual, the physically consistent model (``identified.urdf``), the whole arm's and
    the diagnosis's reports with their plots. Returns the diagnosis, the consistent model's
    summary line and the whole-arm fit's document with it."""
    from armid.identify.feasible import feasible_estimate

    from .pipeline import Inputs, diagnose
    from .report import feasible_at_stamps, write_diagnosis_report, write_report
    from .urdf_export import effect_values, write_urdf

    diagnosis = diagnose(robot, Inputs([run], [validation]))
    feasible = feasible_estimate(whole, [validation])
    whole_doc = whole.to_json()
    whole_doc["feasible"] = feasible.to_json()
    # the consistent model's errors measured as the least-squares ones are (every stamp, raw torque)
    whole_doc["feasible"]["at_stamps"] = {"fit": feasible_at_stamps(whole, whole_doc["feasible"], list(run.segments)),
                                          "validation": feasible_at_stamps(whole, whole_doc["feasible"], list(validation.segments))}
    write_urdf(out / "identified.urdf", robot, feasible.phi, effect_values(whole_doc["feasible"]))
    write_report(whole, whole_doc, list(validation.segments), out / "whole_arm", "validation run", identification=list(run.segments),
                 identified_on="whole_a", validated_on="whole_b")
    write_diagnosis_report(diagnosis, robot, out / "diagnosis", identified_on="whole_a", validated_on="whole_b")
    return diagnosis, feasible.summary_line(errors=False), whole_doc


def _ended_meanwhile(pool: ProcessPoolExecutor, peers: ExitStack) -> None:
    """``pool`` shut down in a thread of its own, waited for when ``peers`` close: its process's
    end (0.3-0.6 s) overlaps what comes before (``shutdown(wait=False)`` left its queues'
    semaphores to the resource tracker, which warned of them at exit)."""
    import threading

    ending = threading.Thread(target=pool.shutdown, name="armid-analysis-end")
    ending.start()
    peers.callback(ending.join)


def _below_the_real_time() -> None:
    """A worker beside the real-time process: a lower priority than it, one BLAS thread (the
    demo's products are small; a second thread stalls on a loaded 2-core machine)."""
    import os

    from threadpoolctl import threadpool_limits

    os.nice(5)
    threadpool_limits(1, "blas")


def _estimator_service(rig: Rig[Robot], out: Path, meeting: Meeting | None = None) -> PeerLink:
    """``armid serve`` started in a process of its own (as in a lab), not yet waited for;
    ``meeting``: where it meets the demo (default: an endpoint of its own)."""
    robot = rig.robot
    return PeerLink(robot.name, ["serve", "--robot", robot.source, "--whole-arm", "drives", "--no-payload", "--out", str(out / "service"),
                                 "--json", str(out / "service.jsonl")], out / "service.log", "estimate/parameters", "alive/estimator", wait=False,
                    meeting=meeting)


def _published_fit(docs: list[dict[str, Any]], run: str) -> dict[str, Any] | None:
    """The whole-arm fit of ``run`` (an ``armid identify --json`` document) that the estimator
    service published, if it has."""
    for doc in docs:
        fit = (doc.get("whole_arm") or {}).get(run)
        if fit is not None:
            return dict(fit)
    return None


def _runs_beside_the_service(rig: Rig[Robot], link: PeerLink, experiments: ExperimentsBeside, out: Path, console: Any,
                             after_motion: Any = None) -> tuple[list[Any], list[dict[str, Any]]]:
    """The experiments on the drives, streamed to the estimator service once it is ready; its
    ``estimate/parameters`` documents, one per experiment it identified. ``after_motion``: called
    once the drives have stopped and the stream carries no more records (the service may still
    be identifying the last runs), when every run completed."""
    try:
        link.ready()
        with excitation_session(rig, simulate=True, stream=link.stream) as session:
            console.print(f"  timing: {session.driver.timing_note}; the estimator service runs in process {link.peer.proc.pid}")
            reports = run_experiments(session, experiments, out / "runs", console)
        expected = len(reports) if all(r.completed for r in reports) else 0
        if expected and after_motion is not None:
            after_motion()
        link.wait(lambda: len(link.docs) >= expected, 300)
    finally:
        link.close()
    if len(link.docs) < expected:
        raise SimulationError(f"the estimator service published {len(link.docs)} of {expected} estimates: {link.peer.tail()}")
    return reports, link.docs


DEMO_PAYLOAD = (2.0, (0.02, -0.03, 0.08), (0.004, 0.0, 0.0, 0.004, 0.0, 0.002))
"""Mass (kg), centre of mass in the last link's frame (m), inertia about it (kg m^2)."""


def payload_estimator(rig: Rig[Robot], identification: dict[str, Any], out: Path, meeting: Meeting | None = None) -> PeerLink:
    """``armid estimate live`` on the identified arm (``identification``: its ``armid identify
    --json`` document), started in a process of its own, not yet waited for; ``meeting``: where
    it meets the demo (default: an endpoint of its own)."""
    robot = rig.robot
    params = out / "identified_arm.json"
    write_json(params, identification)
    return PeerLink(robot.name, ["estimate", "live", "--robot", robot.source, "--params", str(params), "--out",
                                 str(out / "payload_estimates.jsonl")], out / "payload_estimator.log", "estimate/payload",
                    "alive/payload_estimator", wait=False, meeting=meeting)


def run_payload(rig: Rig[Robot], link: PeerLink, design: Any, out: Path, plot: Any = None, drives_up: Any = None) -> dict[str, Any]:
    """Khosla's on-line strategy: the identified arm works through a whole-arm trajectory; a
    payload is attached 3 s in and removed 4 s later; ``link``'s ``armid estimate live``, in a
    process of its own, listens to the live Zenoh stream and publishes its estimates; they are
    compared with the truth. ``plot``: where the estimates' plot is made (default: :func:`_plot_payload` here);
    ``drives_up``: called once the drives are up and the estimator ready, before the run starts.

    Everything runs on the arm's clock: the attach and the removal are scheduled in the
    simulated arm at times of its own clock (not when a polling thread gets to them), and
    each "N s after" read-out is the first estimate whose record time is N s after the
    record on which the event took effect.
    """
    import threading

    from armid.identify import excitation as ex
    from armid.io.recordings import read_mcap_arrays
    from armid.sim_bus.physics import Payload

    truth = Payload(*DEMO_PAYLOAD)  # type: ignore[arg-type]
    run_dir = out / "runs" / "payload"
    estimates = link.docs
    try:
        with excitation_session(rig, simulate=True, stream=link.open_stream()) as s:  # the drives start while the estimator does
            assert s.arm is not None
            link.ready()
            if drives_up is not None:
                drives_up()
            physics = s.arm.physics
            plan = ex.plan(design, s.position, s.limits, periods=2, lead_fraction=WHOLE_MARGIN)
            box: dict[str, Any] = {}
            runner = threading.Thread(target=lambda: box.update(report=s.run(plan, run_dir, "payload")))
            runner.start()
            active = None
            while runner.is_alive() and (active is None or active.first_cycle is None):
                active = s.control.active
                time.sleep(0.001)
            if active is not None and active.first_cycle is not None:
                # the plan's cycle k is the arm's step k (one step per SYNC, from time 0)
                start_s = (active.first_cycle - 1) * rig.period_s
                physics.attach_payload(truth, at_time_s=start_s + plan.lead_in_s + 3.0)
                physics.attach_payload(None, at_time_s=start_s + plan.lead_in_s + 7.0)
            runner.join()
            last_time = s.control.last_sample.time_s if s.control.last_sample is not None else float("inf")
        _wait_for_estimates(estimates, last_time - 0.1, link.peer)
    finally:
        link.close()
    report = box["report"]
    if not report.completed:
        raise DriverError(f"payload run stopped: {report.stop_reason}")
    if len(physics.payload_events) != 2 or not estimates:
        raise SimulationError(f"payload phase: {len(physics.payload_events)} payload events took effect, {len(estimates)} estimates "
                           f"(run {'completed' if report.completed else 'stopped: ' + str(report.stop_reason)})")
    # the record on which each event took effect: the step that started at time (k - 1) T is SYNC k
    a, _, _ = read_mcap_arrays(run_dir / "run.mcap")
    cycle, rec_t = np.asarray(a["cycle"]), np.asarray(a["t"], float)
    events = []
    for when, _ in physics.payload_events:
        k = int(np.searchsorted(cycle, int(round(when / rig.period_s)) + 1))
        events.append(float(rec_t[min(k, rec_t.size - 1)]))
    t_on, t_off = events
    t = np.array([e["record_time"] for e in estimates])

    def at(t_event: float, seconds: float) -> dict[str, Any]:
        k = min(int(np.searchsorted(t, t_event + seconds)), len(estimates) - 1)
        e = estimates[k]
        com_err = float(np.linalg.norm(np.array(e["com"]) - truth.com)) if e["com"] is not None else None
        return {"record_time": e["record_time"], "mass": e["mass"], "mass_std": e["mass_std"], "com": e["com"], "com_error_m": com_err,
                "converged": e["converged"], "status": e["status"]}

    (plot or _plot_payload)(out, t - t[0], estimates, truth, t_on - t[0], t_off - t[0])
    write_json(out / "payload_estimates.json", estimates)
    last = estimates[-1]
    return {"true_mass": truth.mass, "true_com": list(truth.com), "estimates": len(estimates), "skipped": last.get("skipped"),
            "lost": last.get("lost"), "estimator_process": link.peer.proc.pid,
            "attach_record_time": t_on, "removal_record_time": t_off, "on_for_s": t_off - t_on,
            "negative_mass_published": int(sum(1 for e in estimates if e["mass"] is not None and e["mass"] < 0)),
            "after_attach_1s": at(t_on, 1.0), "after_attach_2s": at(t_on, 2.0), "after_removal_2s": at(t_off, 2.0),
            "converged_after_attach_s": _converged_after(t, estimates, t_on, t_off),
            "converged_after_removal_s": _converged_after(t, estimates, t_off, float("inf")),
            "report": report.to_json()}


def _converged_after(t: np.ndarray, estimates: list[dict[str, Any]], t_event: float, t_next: float) -> float | None:
    """Seconds from an event (record time ``t_event``) to the first estimate after it from which
    every estimate up to the next event (``t_next``) says converged; None if none does."""
    k = np.flatnonzero((t >= t_event) & (t < t_next))
    if k.size == 0 or not estimates[int(k[-1])]["converged"]:
        return None
    unsettled = [int(i) for i in k if not estimates[int(i)]["converged"]]
    first = int(k[0]) if not unsettled else unsettled[-1] + 1
    return float(t[first] - t_event)


def _wait_for_estimates(estimates: list[dict[str, Any]], until_time: float, estimator: Peer, timeout_s: float = 30.0) -> None:
    """Until the estimator has published on the records up to ``until_time`` (it works through
    the stream at its own pace, in its own process), or has gone quiet for 2 s."""
    deadline, quiet_since, seen = time.monotonic() + timeout_s, time.monotonic(), 0
    while time.monotonic() < deadline and estimator.proc.poll() is None:
        if estimates and estimates[-1]["record_time"] >= until_time:
            return
        if len(estimates) != seen:
            seen, quiet_since = len(estimates), time.monotonic()
        elif time.monotonic() - quiet_since > 2.0:
            return
        time.sleep(0.05)


def _fmt(x: float | None, digits: int = 5) -> str:
    return "—" if x is None else f"{x:.{digits}g}"


def _num(x: float | None, scale: float, digits: int) -> str:
    """A read-out for the console and the report: "not excited" when the estimate has none."""
    return "not excited" if x is None else f"{scale * x:.{digits}f}"


def _plot_payload(out: Path, t: np.ndarray, estimates: list[dict[str, Any]], truth: Any, t_on: float, t_off: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mass = np.array([np.nan if e["mass"] is None else e["mass"] for e in estimates], float)
    com = np.array([[np.nan] * 3 if e["com"] is None else e["com"] for e in estimates], float)
    com[~(mass >= 0.2)] = np.nan  # no centre of mass without a mass
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
    a1.plot(t, mass, lw=1)
    a1.step([0, t_on, t_off, t[-1]], [0, truth.mass, 0, 0], where="post", color="k", lw=0.8, ls="--", label="true")
    a1.set_ylabel("mass [kg]")
    a1.legend(loc="upper right")
    for k, name in enumerate("xyz"):
        a2.plot(t, 100 * com[:, k], lw=1, label=f"c{name}")
        a2.hlines(100 * truth.com[k], t_on, t_off, color="k", lw=0.8, ls="--")
    a2.set_ylim(-30, 30)
    a2.set_ylabel("centre of mass [cm]")
    a2.set_xlabel("time from the payload run's first estimate [s]")
    a2.legend(loc="upper right")
    fig.suptitle("on-line payload estimate (published at 50 Hz over Zenoh) against the truth")
    fig.tight_layout()
    fig.savefig(out / "payload.png", dpi=90)
    plt.close(fig)


def truth_lines(what: str, test: dict[str, Any]) -> list[str]:
    """A truth check (:func:`_truth_test`) as a report says it: the joint test first (chi-square
    per degree of freedom and its p), then the count within 3 sigma, then every combination
    beyond 3 sigma by name with its estimate, truth, std and z."""
    from math import sqrt

    n, chi2, p = test["combinations"], test["chi2"], test["chi2_p"]
    ratio = test.get("per_dof", chi2 / n)
    if p < 0.05:
        verdict = (f"**the joint test rejects the standard deviations (p < 0.05)**: together the errors are about "
                   f"{sqrt(ratio):.2f}x what the standard deviations say, or an estimate is biased")
    elif p > 0.95:
        verdict = (f"together the errors are about {sqrt(ratio):.2f}x what the standard deviations say: "
                   "the standard deviations are larger than these errors need (p > 0.95)")
    else:
        verdict = "consistent with the standard deviations"
    expected = 100 * (1 - 0.9973**n)
    p_text = "p < 0.001" if p < 0.001 else "p > 0.999" if p > 0.999 else f"p = {p:.2g}"
    joint = (f"chi-square {chi2:.1f} on {n} degrees of freedom (chi2/dof {ratio:.2f})" if test.get("batches") is None else
             f"T^2 {chi2:.1f} on {n} with a covariance from batch means worth {test['batches']} independent ones: F {ratio:.2f} per degree "
             "of freedom (Hotelling)")
    out = [f"{what}: all {n} together {joint}, {p_text}: {verdict}. "
           f"{test['within_3_sigma']} of {n} within 3 sigma (max |z| {test['max_abs_z']:.2f}; one or more beyond 3 sigma comes in "
           f"{expected:.0f} % of noise draws when every standard deviation is right)"
           + (": every one within." if not test.get("misses") else "; beyond 3 sigma:"), ""]
    if test.get("misses"):
        out += ["| combination | estimate | truth | std | z |", "|---|---|---|---|---|"]
        out += [f"| `{m['name']}` | {_fmt(m['value'])} | {_fmt(m['truth'])} | {_fmt(m['std'], 3)} | {m['z']:+.2f} |" for m in test["misses"]]
        out.append("")
    return out


def _write_report(out: Path, rig: Rig[Robot], experiments: list[Any], reports: list[Any], seq: SequenceResult, whole: IdentificationResult,
                  whole_doc: dict[str, Any], comparison: list[dict[str, Any]], truth: dict[str, Any], diagnosis: Any,
                  payload: dict[str, Any]) -> None:
    from armid.identify.payload.rls import COM_STD_M, MASS_STD_KG, MASS_STD_REL

    from .report import percent

    f = _fmt
    whole_run = next(e for e in experiments if e.name == "whole_a")
    lines = [f"# armid demo: {rig.name}", "",
             f"Simulated {rig.robot.name} on a {rig.bus.interface} CAN bus, {len(rig.drives)} CiA 402 drives, {rig.period_s * 1000:g} ms SYNC. "
             "Every trajectory was designed (D-optimal finite Fourier series) and checked against every limit before it ran "
             "(the first before the drives started, the others designed beside the runs before them).", "",
             "## Runs", "", "| run | moving joints | duration s | records | max tracking error mrad | peak torque % of limit | "
             "design's condition number |", "|---|---|---|---|---|---|---|"]
    for e, r in zip(experiments, reports):
        lines.append(f"| {r.name} | {', '.join(str(j + 1) for j in e.design.moving)} | {e.plan.duration_s:.1f} | {r.records} | "
                     f"{1000 * max(r.max_tracking_error):.1f} | {100 * max(r.peak_torque_fraction):.0f} | {e.design.condition_number:.3g} |")
    lines += ["", "A design's condition number is its planned motion's (the base regressor of the run's moving joints, columns scaled "
                  f"to unit norm, before any drive moved). The whole-arm model's is that of whole_a as recorded and identified "
                  f"({len(whole.base.expressions())} base parameters, weighted): {whole.excitation.condition_number:.3g} "
                  f"(its design's: {whole_run.design.condition_number:.3g})."]
    # the errors: one per model and data, each named
    v = whole.validation or {}
    at_stamps = (whole_doc.get("feasible") or {}).get("at_stamps") or {}
    fe_fit, fe_val = at_stamps.get("fit"), at_stamps.get("validation")
    b, a = diagnosis.before, diagnosis.after
    n_found = len(diagnosis.found)
    floor = (diagnosis.noise_floor or {}).get("relative_error")
    lines += ["", "## Errors of each model", "",
              "Relative error |tau - tau_hat| / |tau| over every joint, each sample at its own time stamp against the raw measured torque. "
              f"Every model is identified on whole_a ({whole.samples} samples) and validated on whole_b ({whole.validation_samples} samples"
              + (f"; its noise floor, the torque above the low-pass cut-off that no model of the motion removes: {percent(floor)}" if floor is not None else "")
              + ").", "",
              "| model | fit error (on whole_a) | validation error (on whole_b) |", "|---|---|---|",
              f"| whole-arm model: least squares, the `drives` recipe (the samples beside a velocity reversal left out) | "
              f"{percent(whole.fit['relative_error'])} | {percent(v.get('relative_error'))} |",
              f"| whole-arm model, physically consistent (`identified.urdf`) | {percent(fe_fit and fe_fit['relative_error'])} | "
              f"{percent(fe_val and fe_val['relative_error'])} |",
              "| the diagnosis's declared model: the same robot file, least squares with `armid identify`'s defaults "
              f"(every sample) | — | {percent(b['relative_error'])} |",
              (f"| the diagnosis's model with its {n_found} finding{'' if n_found == 1 else 's'} | — | {percent(a['relative_error'])} |" if n_found
               else f"| the diagnosis's model with its findings (none: the same model) | — | {percent(a['relative_error'])} |")]
    s, w = truth["single_link"], truth["whole_arm"]
    lines += ["", "## Against the simulator's known parameters", "",
              "z = (estimate - truth) / std for each identified combination; chi-square: all of them together, with their covariance.", ""]
    lines += truth_lines(f"**Single-link sequence** (links {', '.join(str(st['link']) for st in seq.steps)}, {s['combinations']} combinations)", s)
    lines += truth_lines(f"**Whole-arm model** (identified on whole_a, {w['combinations']} base parameters)", w)
    lines += ["## Single-link sequence (Khosla Tables 2-4)", "", "| link | parameter | initial (modeled) | estimate | std | z vs truth |", "|---|---|---|---|---|---|"]
    for fn, k, z in zip(seq.functionals, range(len(s["z"])), s["z"]):
        lines.append(f"| {fn.link + 1} | `{fn.expression}` | {f(fn.modeled)} | {f(float(seq.beta[k]))} | {f(float(seq.std[k]), 3)} | {z:+.2f} |")
    z_whole = dict(zip(whole.base.expressions(), w["z"]))
    lines += ["", "## Whole-arm base parameters beside the single-link sequence", "",
              "| base parameter | whole arm | std | z vs truth | single-link sequence | std |", "|---|---|---|---|---|---|"]
    for c in comparison:
        z = z_whole.get(c["expression"])
        lines.append(f"| `{c['expression']}` | {f(c['whole_arm'])} | {f(c['whole_arm_std'], 3)} | {'—' if z is None else f'{z:+.2f}'} | "
                     f"{f(c['single_link'])} | {f(c['single_link_std'], 3)} |")
    lines += ["", "## Diagnosis of the residual", "", "Its validation errors: the table under Errors of each model.", ""]
    lines += [f"- {fd.sentence()}" for fd in diagnosis.found] or [f"- {diagnosis.verdict()}"]
    p1, p2, p3 = payload["after_attach_1s"], payload["after_attach_2s"], payload["after_removal_2s"]

    def status(p: dict[str, Any]) -> str:
        return "converged" if p.get("converged") else f"**{p.get('status') or 'not converged'}**: provisional"

    def settled(key: str, event: str) -> str:
        x = payload.get(key)
        return f"converged {x:.2f} s after the {event}" if x is not None else f"never said converged after the {event}"

    unsettled = [when for when, p in (("1 s after the attach", p1), ("2 s after the attach", p2), ("2 s after the removal", p3)) if not p.get("converged")]
    lines += ["", "## On-line payload estimation", "",
              f"The identified arm (whole_a) worked through a whole-arm trajectory; a {payload['true_mass']} kg payload with its centre "
              f"of mass at {[round(100 * c, 1) for c in payload['true_com']]} cm in the last link's frame was attached 3 s in and "
              f"removed 4 s later. The estimator listened to the live Zenoh stream and published {payload['estimates']} estimates "
              f"(50 Hz; skipped records: {payload['skipped']}).", "",
              "| when | mass kg | std | centre of mass error mm | estimator's status |", "|---|---|---|---|---|",
              f"| 1 s after the attach | {_num(p1['mass'], 1, 3)} | {p1['mass_std']:.3f} | {_num(p1['com_error_m'], 1000, 1)} | {status(p1)} |",
              f"| 2 s after the attach | {_num(p2['mass'], 1, 3)} | {p2['mass_std']:.3f} | {_num(p2['com_error_m'], 1000, 1)} | {status(p2)} |",
              f"| 2 s after the removal | {_num(p3['mass'], 1, 3)} | {p3['mass_std']:.3f} | — | {status(p3)} |", "",
              (f"Still converging {' and '.join(unsettled)}: the estimate was still moving there, so those figures are provisional (the "
               f"estimator says converged once the data's part of the mass's std is at most {MASS_STD_KG:g} kg + {100 * MASS_STD_REL:g} % "
               f"of the mass, that of the centre of mass at most {1000 * COM_STD_M:g} mm per axis, and its residual is consistent with the noise). "
               if unsettled else "Every figure above is converged. ")
              + f"The estimate {settled('converged_after_attach_s', 'attach')} and {settled('converged_after_removal_s', 'removal')}.",
              "", "![payload](payload.png)"]
    lines += ["", "Details: [whole_arm/report.md](whole_arm/report.md), [diagnosis/diagnosis.md](diagnosis/diagnosis.md), `demo.json`, `designs.json`, "
              "recordings in `runs/*/run.mcap` (Foxglove, PlotJuggler, `armid identify`)."]
    (out / "report.md").write_text("\n".join(lines) + "\n")

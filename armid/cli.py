"""The ``armid`` command line (docs/reference/interfaces.md). Exit 0 on success, 2 on bad usage or bad
input (one line on stderr naming the file and what is wrong), 1 on a runtime fault."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from armid import __version__
from armid.schema.errors import (
    ArmidError,
    IdentificationError,
    InputError,
    InputFileError,
    OptionError,
    PoorExcitationWarning,
    RecordingError,
    RobotFileError,
    UsageError,
)

ROBOT_HELP = "robot file (YAML), a URDF, or the name of a shipped robot (puma560, kuka_lwr4, ...)"


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        """One line, as every other bad input gets (the usage is one ``--help`` away)."""
        print(f"{self.prog}: error: {message} (see {self.prog} --help)", file=sys.stderr)
        raise SystemExit(2)


def _number(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    return value


def _positive(text: str) -> float:
    """A finite number above zero (durations, frequencies, limits)."""
    value = _number(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return value


def _gap_factor(text: str) -> float:
    """A step this many median steps long splits a log: below 2 every jitter would split it."""
    value = _number(text)
    if value < 2:
        raise argparse.ArgumentTypeError(f"must be at least 2 (median steps), got {text}")
    return value


def _count(text: str) -> int:
    """A whole number of at least 1 (periods)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {text}")
    return value


def _seed(text: str) -> int:
    """NumPy seeds are whole numbers from 0."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {text}")
    return value


LOWPASS_WORDS = ("off", "auto")


def _lowpass(text: str) -> float | str:
    """A cutoff in Hz (checked against each recording's Nyquist frequency once it is read),
    or one of the words ``off`` and ``auto``, passed through as given."""
    if text.strip().lower() in LOWPASS_WORDS:
        return text.strip().lower()
    value = _number(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive cutoff in Hz, 'off' or 'auto', got {text}")
    return value


def _finite_or_none(value: Any) -> Any:
    """``value`` with every non-finite float (NaN, inf) replaced by None, recursively."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, np.floating):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.ndarray):
        return _finite_or_none(value.tolist())
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite_or_none(v) for v in value]
    return value


def strict_json(doc: Any, **kwargs: Any) -> str:
    """JSON that every parser reads: ``null`` where a value is not finite, never a bare ``NaN``."""
    return json.dumps(_finite_or_none(doc), allow_nan=False, **kwargs)


def _write_json(path: Path, doc: Any) -> None:
    """Write ``doc`` as strict JSON (see :func:`strict_json`), making the folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(strict_json(doc, indent=1, default=float) + "\n")


def _show(found: list[str]) -> None:
    """Warnings from the pipeline's checks, held until every input is read (:class:`_HeldWarnings`)."""
    for warning in found:
        _WARNINGS.show(warning, None, "", 0)


def _recipe(args: argparse.Namespace, **extra: Any) -> Any:
    """:data:`~armid.pipeline.USER_LOG` with the command's flags (whose defaults are its own)."""
    from .pipeline import USER_LOG

    return USER_LOG.with_options(max_gap_factor=args.max_gap_factor, lowpass_hz=args.lowpass, torque_hold=args.torque_hold, **extra)


def _identify(args: argparse.Namespace) -> int:
    from armid.io.recordings import write_csv

    from . import pipeline

    robot = load_robot_argument(args.robot)
    recipe = _recipe(args, weighting=args.weighting, prior=args.prior)
    if args.single_link:
        return _identify_single_link(args, robot, recipe)
    inputs = pipeline.load(robot, recipe, args.data, args.validate or [])
    _show(inputs.warnings)
    _inputs_read()
    experiments, validation = inputs.experiments, inputs.validation
    result, excitation = pipeline.identify(robot, experiments, validation, recipe)
    for message in excitation:
        print(f"warning: {message}", file=sys.stderr)
    doc = result.to_json()
    feasible_line = _feasible(args, robot, result, validation, doc)
    for path, prep in zip(inputs.sources, experiments + validation):
        for note in prep.notes:
            print(f"{path}: {note}", file=sys.stderr)
    for out in (args.json, args.predictions):
        if out:
            Path(out).parent.mkdir(parents=True, exist_ok=True)
    if args.json:
        Path(args.json).write_text(strict_json(doc, indent=1) + "\n")
    segments = [s for p in (validation or experiments) for s in p.segments]
    if args.predictions:
        if not validation:
            raise IdentificationError("--predictions needs --validate data")
        t, _, tau_hat = result.predict_stamps(segments)
        write_csv(args.predictions, t, {"tau_hat": tau_hat})
    if args.report:
        from .report import write_report

        write_report(result, doc, segments, Path(args.report), "validation data" if validation else "identification data")
    v = doc["validation"]
    print(
        f"{robot.name}: {doc['samples']} samples, {len(doc['base_parameters'])} base parameters, "
        f"condition number {doc['condition_number']:.3g}, fit error {doc['fit']['relative_error']:.4g}"
        + (f", validation error {v['relative_error']:.4g}" if v else "")
    )
    if feasible_line:
        print(feasible_line)
    return 0


def _identify_single_link(args: argparse.Namespace, robot: Any, recipe: Any) -> int:
    """``armid identify --single-link``: Khosla's off-line sequence on the user's recordings,
    each moving one joint (property 4), identified last link first; each validation recording
    (one joint moving too) predicted and scored on the joint that moved."""
    from armid.identify.preprocess import prepare
    from armid.identify.single_link import single_link_sequence
    from armid.io.recordings import write_csv

    if args.feasible or args.urdf or args.bounding_box or args.report:
        raise UsageError("--single-link gives Khosla's tables and predictions: --feasible, --urdf, --bounding-box and --report "
                         "are for a whole-arm identification")
    runs: dict[int, list[Any]] = {}
    for path in args.data:
        rec, link = _single_joint_run(path, robot)
        runs.setdefault(link, []).append(prepare(rec, robot, recipe.prepare))
    checked = [(path, *_single_joint_run(path, robot)) for path in args.validate or []]
    _inputs_read()
    seq = single_link_sequence(robot, runs)
    for row in seq.table():
        print(f"link {row['link']}: {row['parameter']} = {row['estimate']:.6g} +- {row['std']:.3g} (modeled {row['modeled']:.6g})")
    validation, predicted = [], []
    for path, rec, link in checked:
        prep = prepare(rec, robot, recipe.prepare)
        t = np.concatenate([g.t for g in prep.segments])
        tau = np.concatenate([g.tau for g in prep.segments])
        tau_hat = np.concatenate([seq.predict(g.q, g.qd, g.qdd) for g in prep.segments])
        error = float(np.linalg.norm(tau[:, link] - tau_hat[:, link]) / max(float(np.linalg.norm(tau[:, link])), 1e-300))
        validation.append({"recording": path, "joint": link + 1, "samples": int(t.size), "relative_error": error})
        predicted.append((t, tau_hat))
        print(f"{path}: joint {link + 1} predicted with relative error {100 * error:.3g} %")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(strict_json({"single_link": seq.to_json(), "validation": validation}, indent=1) + "\n")
    if args.predictions:
        if not predicted:
            raise IdentificationError("--predictions needs --validate data")
        Path(args.predictions).parent.mkdir(parents=True, exist_ok=True)
        write_csv(args.predictions, np.concatenate([t for t, _ in predicted]), {"tau_hat": np.concatenate([h for _, h in predicted])})
    done = ", ".join(str(step["link"]) for step in seq.steps)
    print(f"{robot.name}: single-link sequence over links {done}: {len(seq.functionals)} combinations identified"
          + (f"; validation error {100 * float(np.mean([v['relative_error'] for v in validation])):.3g} % (mean over the runs)" if validation else ""))
    return 0


def _single_joint_run(path: str, robot: Any) -> tuple[Any, int]:
    """The recording, cut to its excitation window where ``armid excite``'s ``runs.json`` gives
    it, and the one joint (0-based) that moved in it."""
    from armid.identify.single_link import MOVING_RAD, joint_spans

    from .pipeline import read

    rec, found = read(path, robot, need_motion=False)
    _show(found)
    rec = _excitation_window(Path(path), rec)
    moved = np.flatnonzero(joint_spans(rec.q) > MOVING_RAD)
    if moved.size != 1:
        what = "no joint moved" if moved.size == 0 else f"joints {', '.join(str(j + 1) for j in moved)} moved"
        raise RecordingError(path, f"{what} (by more than {MOVING_RAD} rad): a single-link experiment moves one joint alone "
                                   "(Khosla's property 4)")
    return rec, int(moved[0])


def _excitation_window(path: Path, rec: Any) -> Any:
    """The part of an ``armid excite`` recording inside its plan's excitation window (whole
    periods of the design, as the demo and the service identify it), when a ``runs.json`` of
    that run lies in one of the three folders above it; else the whole recording."""
    from .pipeline import Window, cut_to_window

    for folder in list(path.resolve().parents)[:3]:
        runs = folder / "runs.json"
        if not runs.is_file() or rec.cycle is None:
            continue
        try:
            reports = json.loads(runs.read_text())
        except (OSError, ValueError):
            continue
        for r in reports if isinstance(reports, list) else []:
            if not isinstance(r, dict) or Path(str(r.get("recording", ""))).name != path.name or r.get("name") != path.parent.name:
                continue
            w0, w1 = (float(x) for x in r["window_s"])
            return cut_to_window(rec, Window(int(r["first_cycle"]), (w0, w1), float(np.median(np.diff(rec.t)))))
    return rec


def _feasible(args: argparse.Namespace, robot: Any, result: Any, validation: list[Any], doc: dict[str, Any]) -> str | None:
    """``--feasible`` / ``--urdf``: the physically consistent estimate into ``doc["feasible"]``
    and, with ``--urdf OUT``, the identified inertials written back as a URDF."""
    if not (args.feasible or args.urdf or args.bounding_box):
        return None
    from armid.identify.feasible import feasible_estimate

    from .urdf_export import collision_boxes, effect_values, write_urdf

    boxes = collision_boxes(robot) if args.bounding_box else None
    if boxes is not None and all(b is None for b in boxes):
        raise IdentificationError(f"--bounding-box: {robot.source} gives no link a box (no URDF, or only meshes)")
    fr = feasible_estimate(result, validation or None, boxes=boxes)
    doc["feasible"] = fr.to_json()
    if args.urdf:
        write_urdf(args.urdf, robot, fr.phi, effect_values(doc["feasible"]))
    for note in fr.fit.prior_notes:
        print(f"{robot.source}: {note}", file=sys.stderr)
    for check in fr.least_squares_checks:
        for v in check.violations:
            print(f"least squares, link {check.link}: {v}")
    return f"{robot.name}: {fr.summary_line()}" + (f"; URDF written to {args.urdf}" if args.urdf else "")


def _diagnose(args: argparse.Namespace) -> int:
    from armid.identify.diagnosis import extrapolation_sentence, set_aside_sentence
    from armid.io.recordings import write_csv

    from . import pipeline

    robot = load_robot_argument(args.robot)
    inputs = pipeline.load(robot, _recipe(args), args.data, args.validate)
    _show(inputs.warnings)
    _inputs_read()
    experiments, validation = inputs.experiments, inputs.validation
    for path, prep in zip(inputs.sources, experiments + validation):
        for note in prep.notes:
            print(f"{path}: {note}", file=sys.stderr)
    diag = pipeline.diagnose(robot, inputs)
    doc = diag.to_json()
    feasible_line = None
    if args.feasible or args.urdf or args.bounding_box:
        feasible_line = _diagnosed_feasible(args, robot, diag, experiments, validation, doc)
    for out in (args.json, args.predictions):
        if out:
            Path(out).parent.mkdir(parents=True, exist_ok=True)
    if args.json:
        Path(args.json).write_text(strict_json(doc, indent=1) + "\n")
    if args.predictions:
        assert diag.predictions is not None
        write_csv(args.predictions, diag.predictions[0], {"tau_hat": diag.predictions[2]})
    if args.report:
        from .report import write_diagnosis_report

        write_diagnosis_report(diag, robot.name, Path(args.report), doc.get("feasible"))
    for f in diag.found:
        print(f.sentence())
    if not diag.found:
        print("nothing significant found: the declared model explains the data to its noise")
    for a in diag.absorbed:
        print(f"absorbed (not a finding): {a['effect']} on joint {a['joint']} joins {a['into']}")
    for c in diag.conflicting:
        print(f"set aside (not a finding): {set_aside_sentence(c)}")
    for x in diag.extrapolated:
        print(f"extrapolated: {extrapolation_sentence(x)}")
    print(f"{robot.name}: validation error {100 * doc['before']['relative_error']:.3g} % -> {100 * doc['after']['relative_error']:.3g} %")
    if feasible_line:
        print(feasible_line)
    return 0


def _diagnosed_feasible(args: argparse.Namespace, robot: Any, diag: Any, experiments: list[Any], validation: list[Any], doc: dict[str, Any]) -> str | None:
    """The feasible estimate of the model diagnose ends with: the declared model plus every
    finding (identify.diagnosis.findings_model), the same fit as its 'after'."""
    from armid.identify.diagnosis import findings_model
    from armid.identify.identification import identify

    model, options = findings_model(robot, diag.found)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoorExcitationWarning)
        result = identify(model, experiments, validation, options)
    line = _feasible(args, model, result, validation, doc)
    doc["feasible"]["model"] = {"declared": doc.get("declared", []),
                                "added_findings": [f"{f.effect}@{'arm' if f.joint is None else f.joint + 1}" for f in diag.found]}
    return line


def _rig(args: argparse.Namespace) -> Any:
    """The rig file, with ``--interface``/``--channel`` replacing its CAN bus's."""
    from armid.io.rig_file import load_rig

    rig = load_rig(args.rig)
    changes = {k: v for k, v in (("interface", args.interface), ("channel", args.channel)) if v}
    return rig.with_bus(**changes) if changes and not rig.is_serial else rig


def _record(args: argparse.Namespace) -> int:
    import threading
    import time

    from armid.daq.acquisition import Acquisition, Sink
    from armid.daq.recorder import McapRecorder
    from armid.schema import versions

    rig = _rig(args)
    _inputs_read()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    driver, sim = _open_driver(rig, args)
    # an arm simulated in this process never runs ahead of what records it (SYNC waits for
    # the consumer); --duration is then the arm's time, whatever the wall clock does
    paced = driver.paced_by_consumer
    stop = threading.Event()
    restore = _stop_on_signals(stop)
    session = stream = None
    can_log = None
    try:
        driver.start()
        if not rig.is_serial:
            assert driver.network is not None and driver.network.notifier is not None
            from armid.daq.canlog import BusLog

            can_log = BusLog(driver, out / "can.log")  # every frame on the bus, the master's included
        metadata = {
            "robot": rig.robot.name, "rig": rig.name, "rig_file": rig.source, "period_s": rig.period_s,
            "bus": f"dynamixel {driver.port_name} at {rig.bus.bitrate} baud" if rig.is_serial else f"{rig.bus.interface}:{rig.bus.channel}",
            "pdo_plan": None if rig.is_serial else rig.pdo_plan,
            "driver": rig.driver, "drives": driver.drive_configuration, "excitation": "none (armid record)",
            "versions": versions("python-can"),
        }
        recorder = McapRecorder(out / "run.mcap", [j.name for j in rig.robot.joints], metadata)
        sinks = [Sink("recorder", recorder.write, bounded=False)]
        if not args.no_zenoh:
            from armid.daq.stream import Stream

            session = open_zenoh(args)
            stream = Stream(session, rig.robot.name, "recorder", lambda: {"records": acq.sequence, "invalid": acq.invalid.tolist(),
                                                                          "dropped_by_stream": sinks[-1].dropped})
            sinks.append(Sink("zenoh", stream.publish, bounded=True, capacity=5000))
        from armid.daq.supervision import Supervision

        supervision = Supervision(lambda text: print(f"armid record: {text}", file=sys.stderr, flush=True), stream)
        faults: list[Any] = []

        def on_fault(f: Any) -> None:
            faults.append(f)
            supervision.fault(f)

        acq = Acquisition(driver, sinks, on_fault=on_fault)
        from armid.daq.experiment_stream import experiment_description

        run_name = out.name or "record"
        experiment = experiment_description(run_name, None, rig.n_joints, metadata)
        if stream:
            stream.event("start", rig=rig.name, run=run_name, experiment=experiment)
        from .live import LiveLine, acquisition_line

        live = LiveLine(lambda: acquisition_line(acq, driver, len(faults), rig.period_s))
        acq.start()
        start = time.monotonic()
        print(f"armid record: {rig.name} -> {out / 'run.mcap'} (Ctrl-C stops)", file=sys.stderr, flush=True)
        with live:
            while not stop.wait(0.1):
                supervision.events(driver.events())
                elapsed = acq.sequence * rig.period_s if paced else time.monotonic() - start
                if args.duration and elapsed >= args.duration:
                    break
                if acq.error:
                    break
        acq.stop()
        supervision.events(driver.events())
        recorder.close()
        if can_log is not None:
            can_log.stop()
        if stream:
            stream.event("stop", rig=rig.name, run=run_name, experiment=experiment, records=recorder.count, completed=acq.error is None,
                         reason=acq.error, first_sequence=0, last_sequence=acq.sequence - 1, first_cycle=0, window_s=None)
        print(f"armid record: {acq.sequence} records, invalid per joint {acq.invalid.tolist()}, lost cycles per joint "
              f"{driver.lost_cycles.tolist()}" + (f", dropped by the stream {sinks[-1].dropped}" if stream else ""), file=sys.stderr)
        for line in supervision.summary():
            print(f"armid record: {line}", file=sys.stderr)
        if supervision.failed:
            print(f"armid record: {supervision.verdict()} ({out / 'run.mcap'} holds every record)", file=sys.stderr)
        return 1 if acq.error or supervision.failed else 0
    finally:
        driver.close()
        if stream:
            stream.close()
        if session is not None:
            session.close()
        if sim is not None:
            sim.close()
        restore()


def _simulating(rig: Any, args: argparse.Namespace) -> bool:
    """``--simulate``/``--no-simulate``, else: a serial rig on ``port: sim``, a CAN rig on ``virtual``."""
    if args.simulate is not None:
        return bool(args.simulate)
    if rig.serial is not None:
        return (getattr(args, "channel", None) or rig.serial.port) == "sim"
    return bool(rig.bus.interface == "virtual")


def _open_driver(rig: Any, args: argparse.Namespace) -> tuple[Any, Any]:
    """The rig's driver (the registry names it), on the simulated hardware when simulating: (driver, simulator or None)."""
    from armid.drivers import open_driver

    if _simulating(rig, args):
        from .simulated import simulated_driver

        return simulated_driver(rig)
    kwargs = {"port": args.channel} if rig.serial is not None and getattr(args, "channel", None) else {}
    return open_driver(rig, **kwargs), None


def _stop_on_signals(stop: Any) -> Any:
    """SIGINT and SIGTERM set ``stop`` until the returned function puts the previous handlers back."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}

    def restore() -> None:
        for sig, handler in previous.items():
            signal.signal(sig, handler)

    return restore


def _excite(args: argparse.Namespace) -> int:
    import time

    from rich.console import Console

    rig = _rig(args)
    robot = rig.robot
    n = robot.n_joints
    if args.frequency is not None and args.frequency >= 0.5 / rig.period_s:
        raise OptionError("--frequency", f"{args.frequency:g} Hz is not below the {0.5 / rig.period_s:g} Hz Nyquist frequency "
                                         f"of {rig.source}'s {rig.period_s:g} s period")
    console = Console(stderr=True)
    simulate = _simulating(rig, args)
    links: list[int] = []
    for spec in args.link or []:
        if spec == "all":
            links += list(range(n - 1, -1, -1))  # Khosla's sequence: last link first
        else:
            try:
                j = int(spec)
            except ValueError:
                raise UsageError(f"--link: {spec!r} is not a joint number or 'all'") from None
            if not 1 <= j <= n:
                raise UsageError(f"--link: joint {j} does not exist; {robot.name} has joints 1..{n}")
            links.append(j - 1)
    trajectory = load_trajectory(args.trajectory, n, rig.period_s) if args.trajectory else None  # checked before any drive is enabled
    _inputs_read()
    out = Path(args.out or f"runs/{time.strftime('%Y%m%d-%H%M%S')}")
    # the pose the arm will be at: the rig's (simulated) start, or the drives' own report
    start = np.asarray(rig.simulation.get("initial_position", np.zeros(n)), float) if simulate else None
    zsession = stream = None
    holder: dict[str, Any] = {}
    if not args.no_zenoh and not args.dry_run:  # every record on armid/<robot>/joint_state, each experiment on events
        from armid.daq.stream import Stream

        zsession = open_zenoh(args)

        def status() -> dict[str, Any]:
            s = holder.get("session")
            acq = s.acquisition if s is not None else None
            return {"component": "excite", "records": acq.sequence if acq else 0, "invalid": acq.invalid.tolist() if acq else [],
                    "dropped_by_stream": s._sinks[-1].dropped if s is not None else 0}

        stream = Stream(zsession, robot.name, "excite", status)
    try:
        return _excite_run(args, rig, robot, n, simulate, links, trajectory, out, start, console, stream, holder)
    finally:
        if stream is not None:
            stream.close()
        if zsession is not None:
            zsession.close()


def _excite_run(args: argparse.Namespace, rig: Any, robot: Any, n: int, simulate: bool, links: list[int], trajectory: Any, out: Path,
                start: Any, console: Any, stream: Any, holder: dict[str, Any]) -> int:
    from armid.daq.excite import ExcitationSession
    from armid.identify import excitation as ex

    from .experiments import Experiment, design_experiments, run_experiments

    if start is None:  # the pose the drives report; the drives are let be while this process designs
        driver, sim = _open_driver(rig, args)
        with ExcitationSession(rig, driver, simulator=sim, tracking_limit_rad=args.tracking_limit) as probe:
            start = probe.position
    if trajectory is not None:
        traj, moving = trajectory
        limits = ex.Limits.of(robot)
        p = ex.plan(traj, start, limits, periods=args.periods)
        ex.check_plan(robot, p, rig.period_s, limits)
        design = ex.Design(traj, moving, tuple(range(n)), [], [], 0, float("nan"), float("nan"), {})
        experiments = [Experiment(Path(args.trajectory).stem, design, p)]
    else:
        whole = [("whole", args.periods)] if not links or args.whole else []
        experiments = design_experiments(robot, start, links, whole, rig.period_s, link_frequency_hz=args.frequency or 0.5,
                                          link_periods=args.periods, whole_frequency_hz=args.frequency or 0.2, seed=args.seed,
                                          log=lambda m: console.print(f"  {m}"))
    _write_json(out / "designs.json", {e.name: e.design.to_json() for e in experiments})
    if args.dry_run:
        console.print(f"armid excite: {len(experiments)} trajectories checked against every limit (dry run: nothing recorded)")
        return 0
    console.print(f"armid excite: {len(experiments)} trajectories checked against every limit; recording to {out}")
    # designing can keep this process busy for tens of seconds: only now the drives run with it
    driver, sim = _open_driver(rig, args)
    with ExcitationSession(rig, driver, simulator=sim, tracking_limit_rad=args.tracking_limit, stream=stream,
                           say=lambda text: console.print(f"armid excite: {text}", markup=False, highlight=False)) as session:
        holder["session"] = session
        console.print(f"armid excite: timing: {session.driver.timing_note}")
        moved = float(np.abs(start - session.position).max())
        if moved > 0.02:
            raise UsageError(f"the arm is {moved:.3f} rad from the pose the trajectories were designed from: it moved; run again")
        from .live import RateLine, acquisition_counts, enabled

        rate = RateLine()

        def status() -> str:
            acq = session.acquisition
            if acq is None:
                return ""
            records, lost, invalid = acquisition_counts(acq, session.driver)
            faults = 1 if session.control.stop_reason and "fault" in session.control.stop_reason else 0
            return rate(records, lost, invalid, faults, sum(s.dropped for s in acq.sinks))

        reports = run_experiments(session, experiments, out, console, status=status if enabled() else None)
    _write_json(out / "runs.json", [r.to_json() for r in reports])
    for r in reports:
        status = "completed" if r.completed else f"STOPPED: {r.stop_reason}"
        console.print(f"{r.name}: {status}; {r.records} records in {r.recording}; max tracking error {1000 * max(r.max_tracking_error):.1f} mrad")
    return 0 if all(r.completed for r in reports) else 1


def load_trajectory(path: str | Path, n_joints: int, period_s: float) -> tuple[Any, tuple[int, ...]]:
    """A trajectory JSON for ``armid excite --trajectory``: a ``designs.json`` entry (or a file
    holding exactly one), ``{"fourier": {...}}``, or the Fourier block itself. Returns the
    trajectory and the moving joints (0-based); every problem names the file and the field."""
    from armid.identify.trajectories import FourierTrajectory

    src = str(path)
    try:
        text = Path(path).read_text()
    except FileNotFoundError:
        raise InputFileError(src, "", "no such file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise InputFileError(src, "", f"cannot read ({err})") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as err:
        raise InputFileError(src, f"line {err.lineno} column {err.colno}", f"not valid JSON ({err.msg})") from None
    except RecursionError:
        raise InputFileError(src, "", "nested too deeply to be a trajectory") from None
    where = ""
    if not isinstance(doc, dict):
        raise InputFileError(src, "", f"must be a JSON object with 'fourier' (a designs.json entry), got {type(doc).__name__}")
    if "fourier" not in doc and "q0" not in doc:
        designs = {k: v for k, v in doc.items() if isinstance(v, dict) and "fourier" in v}
        if len(designs) == 1 and len(doc) == 1:
            where, doc = next(iter(designs.items()))
        elif designs:
            raise InputFileError(src, "", f"holds {len(designs)} designs ({', '.join(designs)}); save the one to run in a file of its own")
        else:
            raise InputFileError(src, "fourier", "missing (a designs.json entry or {\"fourier\": {q0, a, b, base_frequency_hz}})")
    f = doc["fourier"] if "fourier" in doc else doc
    fw = f"{where}.fourier" if where else ("fourier" if "fourier" in doc else "")

    def field(key: str) -> str:
        return f"{fw}.{key}" if fw else key

    if not isinstance(f, dict):
        raise InputFileError(src, fw or "fourier", "must be an object with q0, a, b, base_frequency_hz")
    for key in ("q0", "a", "b", "base_frequency_hz"):
        if key not in f:
            raise InputFileError(src, field(key), "missing")

    def array(key: str, ndim: int) -> np.ndarray:
        try:
            a = np.asarray(f[key], dtype=float)
        except (TypeError, ValueError):
            raise InputFileError(src, field(key), f"must be {'a list' if ndim == 1 else 'a list of lists'} of numbers") from None
        if a.ndim != ndim:
            raise InputFileError(src, field(key), f"must be {'a list' if ndim == 1 else 'a list of lists (joint x harmonic)'} of numbers")
        if not np.isfinite(a).all():
            raise InputFileError(src, field(key), "must hold finite numbers only")
        return a

    q0 = array("q0", 1)
    if q0.shape[0] != n_joints:
        raise InputFileError(src, field("q0"), f"{q0.shape[0]} joints, the rig's robot has {n_joints}")
    a, b = array("a", 2), array("b", 2)
    for key, m in (("a", a), ("b", b)):
        if m.shape[0] != n_joints or m.shape[1] < 1:
            raise InputFileError(src, field(key), f"shape {m.shape}, expected ({n_joints}, harmonics >= 1)")
    if a.shape != b.shape:
        raise InputFileError(src, field("b"), f"shape {b.shape} differs from a's {a.shape}")
    hz = f["base_frequency_hz"]
    if isinstance(hz, bool) or not isinstance(hz, int | float) or not math.isfinite(hz):
        raise InputFileError(src, field("base_frequency_hz"), f"must be a finite number, got {hz!r}")
    top = 0.5 / period_s / a.shape[1]
    if not 0 < hz < top:
        raise InputFileError(src, field("base_frequency_hz"), f"must lie in (0, {top:g}) Hz (its {a.shape[1]} harmonics below "
                                                               f"the {0.5 / period_s:g} Hz Nyquist frequency of the rig's period), got {hz}")
    moving_doc = doc.get("moving_joints", list(range(1, n_joints + 1)))
    if (not isinstance(moving_doc, list) or not moving_doc
            or any(isinstance(j, bool) or not isinstance(j, int) or not 1 <= j <= n_joints for j in moving_doc)
            or len(set(moving_doc)) != len(moving_doc)):
        raise InputFileError(src, f"{where}.moving_joints" if where else "moving_joints",
                             f"must be a list of distinct joint numbers 1..{n_joints}, got {moving_doc!r}")
    return FourierTrajectory(q0, a, b, float(hz)), tuple(j - 1 for j in moving_doc)


def _replay_records(path: Path, robot: Any, period_s: float | None) -> tuple[tuple[np.ndarray, ...], list[str]]:
    """The replay's records by :func:`armid.pipeline.replay_records` (identify's checks: ms stamps,
    degrees refused; their warnings held), and ``--period`` against their stamps."""
    from .pipeline import replay_records

    records, notes, found = replay_records(path, robot)
    _show(found)
    t = records[1]
    if t.size >= 2 and period_s is not None:
        step = float(np.median(np.diff(t)))
        if abs(step - period_s) > 0.1 * period_s:
            raise RecordingError(str(path), f"its time stamps say a {1000 * step:.4g} ms period, --period says {1000 * period_s:.4g} ms "
                                            "(the estimator always uses the time stamps; leave --period out)")
    return records, notes


def _identification_document(path: str, robot: Any) -> dict[str, Any]:
    """The ``armid identify --json`` document, checked for what the estimator reads."""
    try:
        doc = json.loads(Path(path).read_text())
    except json.JSONDecodeError as err:
        raise RecordingError(path, f"not JSON: line {err.lineno}: {err.msg}") from None
    except UnicodeDecodeError as err:
        raise RecordingError(path, f"not a text file ({err.reason})") from None
    if not isinstance(doc, dict):
        raise RecordingError(path, f"must be a JSON object (the output of armid identify --json), got a JSON {type(doc).__name__}")
    base = doc.get("base_parameters")
    if not isinstance(base, list):
        raise RecordingError(path, "base_parameters: missing or not a list")
    for k, b in enumerate(base):
        if not isinstance(b, dict) or not isinstance(b.get("expression"), str):
            raise RecordingError(path, f"base_parameters[{k}]: must be an object with an 'expression' string and a 'value'")
        v = b.get("value")
        if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v):
            raise RecordingError(path, f"base_parameters[{k}].value: must be a finite number, got {v!r}")
    sigma = doc.get("joint_noise_sigma")
    if sigma is not None:
        ok = isinstance(sigma, list) and len(sigma) == robot.n_joints and all(
            isinstance(x, int | float) and not isinstance(x, bool) and np.isfinite(x) and x > 0 for x in sigma)
        if not ok:
            raise RecordingError(path, f"joint_noise_sigma: must be {robot.n_joints} positive numbers, got {sigma!r}")
    return doc


def _estimate_summary(n: int, docs: list[dict[str, Any]], seconds: float, stream: Any) -> str:
    est = stream.estimator
    head = f"armid estimate: {n} updates, {len(docs)} estimates in {seconds:.2f} s"
    extra = [f"{v} {k.replace('_', ' ')}" for k, v in (("rate_changes", est.rate_changes_), ("rejected", est.rejected_),
                                                       ("lost", stream.lost), ("invalid", stream.invalid)) if v]
    if stream.dropped:
        reasons = ", ".join(f"{v} {k}" for k, v in stream.dropped.items())
        extra.append(f"dropped {reasons}; last: {stream.last_drop}")
    if not docs:
        return head + "; no estimate (too few records to differentiate)"
    last = docs[-1]
    if last["mass"] is None:
        what = "mass not excited: the motion does not determine it (no estimate)"
    else:
        com = "" if last["com"] is None else ", centre of mass [" + ", ".join(f"{100 * c:.1f}" for c in last["com"]) + "] cm"
        what = f"mass {last['mass']:.3f} +- {last['mass_std']:.3f} kg{com}, {last['status']}"
    return head + f"; last: {what}" + (f" ({', '.join(extra)})" if extra else "")


def _replay_problem(n_records: int, docs: list[dict[str, Any]], stream: Any) -> str | None:
    """What makes a replay's input unusable: no record the estimator could take (each dropped
    by the screen: not finite, invalid), or most of them gross outliers against the identified
    arm (torque in mN*m, another arm's parameters). None when the replay says something."""
    dropped = sum(stream.dropped.values()) + stream.invalid
    if not docs:
        reasons = ", ".join(f"{v} {k}" for k, v in stream.dropped.items()) or "too few records to differentiate"
        return f"no estimate from {n_records} records ({dropped} dropped: {reasons}; last: {stream.last_drop})" if dropped else \
               f"no estimate from {n_records} records ({reasons})"
    rejected = stream.estimator.rejected_
    if rejected > 0.5 * max(n_records - dropped, 1):
        return (f"{rejected} of {n_records - dropped} records are gross outliers against the identified arm: is the torque in N*m "
                "(not mN*m), and are --params this arm's?")
    return None


def _estimate(args: argparse.Namespace) -> int:
    """On-line payload estimation, live or on a recording; always on the records' time stamps."""
    import time

    from armid.daq.payload_service import EstimateStream
    from armid.identify.payload import PayloadRLS, ReferenceRun, arm_model_from_identification

    if not args.replay and args.mode != "live":
        raise UsageError("say what to run on: 'live' (the Zenoh stream) or --replay DATA")
    if args.period is not None and not (np.isfinite(args.period) and args.period > 0):
        raise UsageError(f"--period must be a positive number of seconds, got {args.period:g}")
    if args.publish_every < 1:
        raise UsageError(f"--publish-every must be a whole number of records >= 1, got {args.publish_every}")
    if not (np.isfinite(args.forgetting) and 0 < args.forgetting <= 1):
        raise UsageError(f"--forgetting must be in (0, 1] (a factor per 2 ms of the arm's time; 0.998: about 1 s), got {args.forgetting:g}")
    if args.duration is not None and not (np.isfinite(args.duration) and args.duration > 0):
        raise UsageError(f"--duration must be a positive number of seconds, got {args.duration:g}")
    robot = load_robot_argument(args.robot)
    doc = _identification_document(args.params, robot)
    arm = arm_model_from_identification(robot, doc)
    reference = None
    if args.reference:
        ref_records, ref_notes = _replay_records(Path(args.reference), robot, args.period)
        for note in ref_notes:
            print(f"{args.reference}: {note}", file=sys.stderr)
        keep = ref_records[2].all(axis=1)
        try:
            reference = ReferenceRun(arm, ref_records[1][keep], ref_records[3][keep], ref_records[4][keep])
        except ValueError as err:
            raise RecordingError(args.reference, str(err)) from None
    estimator = PayloadRLS(arm, forgetting=args.forgetting, reference=reference)
    stream = EstimateStream(estimator, publish_every=args.publish_every, strict_time=bool(args.replay),
                            source=str(args.replay or "stream"))
    if args.replay:
        records, notes = _replay_records(Path(args.replay), robot, args.period)
        for note in notes:
            print(f"{args.replay}: {note}", file=sys.stderr)
    out = open(args.out, "w") if args.out else sys.stdout  # noqa: SIM115 - closed below
    try:
        if args.replay:
            start = time.perf_counter()
            docs = stream.feed_arrays(*records)
            for d in docs:
                out.write(json.dumps(d, allow_nan=False) + "\n")
            seconds = time.perf_counter() - start
            print(_estimate_summary(estimator.n_updates_ if hasattr(estimator, "n_updates_") else 0, docs, seconds, stream), file=sys.stderr)
            problem = _replay_problem(len(records[0]), docs, stream)
            if problem is not None:  # the estimates made are written; the input is named
                raise RecordingError(str(args.replay), problem)
            return 0
        from armid.daq.payload_service import PayloadService
        from armid.drivers.realtime import ordinary_priority

        ordinary_priority()  # the arithmetic never at a real-time policy inherited from what started it
        estimator.warm()  # nothing left to run for the first time once records arrive
        session = open_zenoh(args)
        service = PayloadService(session, robot.name, stream, on_estimate=lambda d: out.write(json.dumps(d, allow_nan=False) + "\n"))
        print(f"armid estimate: listening on armid/{robot.name}/joint_state (Ctrl-C stops)", file=sys.stderr, flush=True)
        try:
            deadline = time.monotonic() + args.duration if args.duration else None
            while deadline is None or time.monotonic() < deadline:
                time.sleep(0.1)
        except KeyboardInterrupt:
            pass
        finally:
            service.close()
            session.close()
        return 0
    finally:
        if out is not sys.stdout:
            out.close()


def _serve(args: argparse.Namespace) -> int:
    """The estimator service (``armid/serve.py``) until Ctrl-C, SIGTERM or ``--duration``."""
    import signal
    import tempfile
    import threading
    import time

    from .serve import EstimatorService, ServiceOptions

    robot = load_robot_argument(args.robot)
    _inputs_read()
    from armid.drivers.realtime import ordinary_priority, realtime_allowed

    ordinary_priority()  # started from a real-time thread, it would have inherited that policy
    if not realtime_allowed():  # acquisition here runs at real-time priority where allowed; else it needs our nice
        try:  # never slow acquisition on the same machine: the arithmetic runs at a lower priority
            os.nice(5)
        except OSError:
            pass
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    out_json = open(args.json, "a") if args.json else None  # noqa: SIM115 - closed below
    tmp = None if args.out else tempfile.TemporaryDirectory(prefix="armid-serve-")
    out = Path(args.out) if args.out else Path(tmp.name)  # type: ignore[union-attr]

    def published(doc: dict[str, Any]) -> None:
        e = doc["experiment"]
        what = e.get("note") or (f"links done {doc['links_done']}" if e.get("kind") == "single_link" else f"whole arm from {e['run']}")
        v = doc.get("validation")
        print(f"armid serve: {e['run']}: {what}; {len(doc['base_parameters'])} base parameters published"
              + (f", validation error {100 * v['relative_error']:.3g} %" if v else "")
              + (f" ({e['missing']} records of the run not received)" if e.get("missing") else ""), file=sys.stderr, flush=True)
        if out_json is not None:
            out_json.write(strict_json(doc) + "\n")
            out_json.flush()

    options = ServiceOptions(max_backlog=args.max_backlog, whole_arm=args.whole_arm, payload=not args.no_payload)
    try:
        with open_zenoh(args) as session:
            service = EstimatorService(session, robot, out, options, on_publish=published,
                                       log=lambda m: print(f"armid serve: {m}", file=sys.stderr, flush=True))
            print(f"armid serve: {robot.name}: listening on armid/{robot.name}/joint_state and events; publishing "
                  f"armid/{robot.name}/estimate/parameters (Ctrl-C stops)", file=sys.stderr, flush=True)
            try:
                deadline = time.monotonic() + args.duration if args.duration else None
                while not stop.wait(0.1):
                    if deadline is not None and time.monotonic() >= deadline:
                        break
            finally:
                service.close()
        print(f"armid serve: {service.received} records received, {service.skipped} skipped, {service.lost} lost; "
              f"{service.published} estimates published", file=sys.stderr)
        return 0
    finally:
        if out_json is not None:
            out_json.close()
        if tmp is not None:
            tmp.cleanup()


def _watch(args: argparse.Namespace) -> int:
    from .watch import watch

    with open_zenoh(args) as session:
        state = watch(session, args.robot, args.duration)
    print(f"armid watch: {state.received} records, {state.gaps} gaps ({state.missing} missing), {state.bad} unreadable", file=sys.stderr)
    return 0


def _demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    return run_demo(Path(args.out), Path(args.rig) if args.rig else None, seed=args.seed)


def _sim(args: argparse.Namespace) -> int:
    import threading

    rig = _rig(args)
    _inputs_read()
    stop = threading.Event()
    restore = _stop_on_signals(stop)
    try:
        return _sim_chain(rig, args, stop) if rig.is_serial else _sim_arm(rig, args, stop)
    finally:
        restore()


def _sim_arm(rig: Any, args: argparse.Namespace, stop: Any) -> int:
    from armid.sim_bus.arm import SimulatedArm

    arm = SimulatedArm(rig, seed=args.seed)
    print(f"armid sim: {rig.name}: {rig.n_joints} drives (nodes {', '.join(str(d.node_id) for d in rig.drives)}) "
          f"on {rig.bus.interface}:{rig.bus.channel}, lock-step with SYNC at {rig.period_s * 1000:g} ms (co-simulated: a late "
          f"SYNC pauses the arm); {arm.timing.sentence('simulator threads')}", file=sys.stderr, flush=True)
    if args.ready:
        Path(args.ready).write_text("ready\n")
    try:
        _run_until(stop, args.duration)
    finally:
        arm.close()
        if args.log:
            _write_sim_log(arm, Path(args.log))
    st = arm.status()
    print(f"armid sim: {st['syncs']} SYNC periods simulated ({st['time_s']:.3f} s of arm time)", file=sys.stderr)
    return 0


def _run_until(stop: Any, duration: float | None) -> None:
    """Until ``stop`` is set (a signal) or ``duration`` seconds have passed."""
    import time

    start = time.monotonic()
    while not stop.wait(0.05):
        if duration and time.monotonic() - start > duration:
            return


def _sim_chain(rig: Any, args: argparse.Namespace, stop: Any) -> int:
    """A Dynamixel rig: the simulated servo chain on a pty; the driver opens the printed port."""

    from armid.sim_bus.servo_chain import SimulatedServoChain

    chain = SimulatedServoChain(rig, seed=args.seed)
    print(f"armid sim: {rig.name}: {rig.n_joints} Dynamixel servos (ids {', '.join(str(d.node_id) for d in rig.drives)}) "
          f"at {rig.bus.bitrate:,} baud on {chain.port}", file=sys.stderr, flush=True)
    print(chain.port, flush=True)
    if args.ready:
        Path(args.ready).write_text(chain.port + "\n")
    try:
        _run_until(stop, args.duration)
    finally:
        chain.close()
    print(f"armid sim: {chain.periods} periods simulated ({chain.physics.time_s:.3f} s of arm time), "
          f"{chain.instructions} instructions served", file=sys.stderr)
    return 0


def _write_sim_log(arm: object, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **arm.log.arrays())  # type: ignore[attr-defined]


def _zenoh_message(err: BaseException) -> str:
    """Zenoh's error text without its Rust source locations, on one line."""
    import re

    text = str(err)
    inner = re.search(r'msg: "(.*?)(?: at /[^"]*)?"', text)
    text = inner.group(1) if inner else re.sub(r" at /\S+\.rs:\d+\.?", "", text)
    return _one_line(text, 200)


def open_zenoh(args: argparse.Namespace) -> Any:
    """A Zenoh session from the command's options; a configuration file that cannot be read,
    names a certificate that is not there, or cannot open a session is bad input (exit 2)."""
    import zenoh

    from armid.daq.stream import session_config

    src = args.zenoh_config
    endpoints = "--zenoh-listen/--zenoh-connect"
    if src is None and args.zenoh_listen is None and args.zenoh_connect is None:
        from armid.daq.stream import local_endpoint, open_local_session

        try:  # no flags: find the other armid processes on this machine (daq.stream.open_local_session)
            return open_local_session()
        except Exception as err:
            raise OptionError(endpoints, f"no endpoint given and the local one {local_endpoint()} cannot be used "
                                         f"({_zenoh_message(err)})") from None
    if src is not None and not Path(src).is_file():
        raise InputFileError(src, "", "no such file")
    try:
        config = session_config(args.zenoh_listen, args.zenoh_connect, src)
    except Exception as err:  # zenoh raises ZError for syntax, schema and endpoints alike
        if src is not None:
            raise InputFileError(src, "", f"not a usable Zenoh configuration ({_zenoh_message(err)})") from None
        raise OptionError(endpoints, _zenoh_message(err)) from None
    if src is not None:
        try:
            tls = json.loads(config.get_json("transport/link/tls"))
        except Exception:
            tls = {}
        for name, value in (tls or {}).items():
            if isinstance(value, str) and name.endswith(("_certificate", "_private_key")) and not Path(value).is_file():
                raise InputFileError(src, f"transport.link.tls.{name}", f"no such file {value}")
    try:
        return zenoh.open(config)
    except Exception as err:
        raise InputFileError(src or endpoints, "", f"cannot open a Zenoh session ({_zenoh_message(err)})") from None


def _zenoh_arguments(p: argparse.ArgumentParser) -> None:
    """Where the Zenoh session connects (peer mode, multicast scouting off). With none of
    these, armid processes on one machine find each other (``daq.stream.open_local_session``)."""
    p.add_argument("--zenoh-listen", nargs="*", metavar="ENDPOINT", help="Zenoh endpoints to listen on, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--zenoh-connect", nargs="*", metavar="ENDPOINT", help="Zenoh endpoints to connect to")
    p.add_argument("--zenoh-config", metavar="JSON5", help="a Zenoh configuration file (config/zenoh/lab.json5)")


def _feasible_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--feasible", action="store_true",
                   help="also the physically consistent estimate (pseudo-inertia PSD, friction >= 0) and a consistency report in the JSON")
    p.add_argument("--urdf", metavar="OUT", help="write the physically consistent model as a URDF (implies --feasible)")
    p.add_argument("--bounding-box", action="store_true",
                   help="keep each link's mass inside the box of its URDF collision geometry (links with a mesh or without geometry: "
                        "no box; implies --feasible)")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="armid", description="Robot dynamics identification (Khosla 1987) from servo data.")
    parser.add_argument("--version", action="version", version=f"armid {__version__}")  # the installed metadata
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    p = sub.add_parser("identify", help="least-squares identification (eq. 18) with identifiability classes")
    p.add_argument("data", nargs="+", help="recordings to identify on (CSV, NPZ or MCAP)")
    p.add_argument("--robot", required=True, help=ROBOT_HELP)
    p.add_argument("--validate", nargs="+", metavar="DATA", help="held-out recordings for the validation error")
    p.add_argument("--json", metavar="OUT", help="write the result as JSON (docs/reference/interfaces.md)")
    p.add_argument("--report", metavar="DIR", help="write a markdown report with PNG plots")
    p.add_argument("--predictions", metavar="CSV", help="write predicted validation torques (t, tau_hat1..n)")
    p.add_argument("--weighting", choices=("wls", "ols"), default="wls", help="per-joint weighted (default) or ordinary LS")
    p.add_argument("--prior", choices=("modeled", "none"), default="modeled",
                   help="the robot file's modeled values as a prior for what the data do not excite (default), or least squares alone")
    _feasible_arguments(p)
    p.add_argument("--lowpass", type=_lowpass, default="auto", metavar="HZ|auto|off",
                   help="zero-phase low-pass of the kinematics, the regressor and the torque alike (default auto: chosen from each recording's spectrum)")
    p.add_argument("--torque-hold", action="store_true", help="torques were held over the period before each sample (drive currents between SYNCs)")
    p.add_argument("--max-gap-factor", type=_gap_factor, default=20.0, help="split where a step exceeds this many median steps")
    p.add_argument("--single-link", action="store_true",
                   help="Khosla's off-line sequence: each recording moves one joint alone; identified last link first, its "
                        "combinations with their std; each --validate run predicted on the joint that moved")
    p.set_defaults(run=_identify)

    p = sub.add_parser("diagnose", help="residual analysis: find undeclared effects, add them, refit, error before/after")
    p.add_argument("data", nargs="+", help="recordings to identify on (CSV, NPZ or MCAP)")
    p.add_argument("--robot", required=True, help=ROBOT_HELP)
    p.add_argument("--validate", nargs="+", metavar="DATA", required=True, help="held-out recordings: the errors before and after are measured on them, and a finding they contradict is set aside (findings are chosen on the identification data)")
    p.add_argument("--json", metavar="OUT", help="write the findings and the errors before and after as JSON")
    p.add_argument("--report", metavar="DIR", help="write diagnosis.md with residual plots per joint")
    p.add_argument("--predictions", metavar="CSV", help="write the final model's predicted validation torques (t, tau_hat1..n)")
    p.add_argument("--lowpass", type=_lowpass, default="auto", metavar="HZ|auto|off",
                   help="zero-phase low-pass of the kinematics, the regressor and the torque alike (default auto: chosen from each recording's spectrum)")
    _feasible_arguments(p)
    p.add_argument("--torque-hold", action="store_true", help="torques were held over the period before each sample (drive currents between SYNCs)")
    p.add_argument("--max-gap-factor", type=_gap_factor, default=20.0, help="split where a step exceeds this many median steps")
    p.set_defaults(run=_diagnose)

    p = sub.add_parser("record", help="record the drives through daq/: MCAP, raw CAN log, live Zenoh stream")
    p.add_argument("--rig", required=True, help="rig file")
    p.add_argument("--out", required=True, help="output folder (run.mcap, can.log)")
    p.add_argument("--duration", type=_positive, help="seconds to record (the arm's time when it is simulated here; default: until Ctrl-C)")
    p.add_argument("--interface", help="override the rig's python-can interface")
    p.add_argument("--channel", help="override the rig's channel")
    p.add_argument("--simulate", action=argparse.BooleanOptionalAction, default=None,
                   help="run the rig's simulated arm in this process (default: when the bus is virtual)")
    p.add_argument("--no-zenoh", action="store_true", help="do not stream")
    _zenoh_arguments(p)
    p.set_defaults(run=_record)

    p = sub.add_parser("excite", help="the operator's excitation: designed and checked trajectories, run on the drives, recorded")
    p.add_argument("--rig", required=True, help="rig file")
    p.add_argument("--link", action="append", metavar="J", help="single-link experiment of joint J (repeat; 'all' = Khosla's sequence N..1)")
    p.add_argument("--whole", action="store_true", help="also a whole-arm run (the default without --link)")
    p.add_argument("--trajectory", metavar="JSON", help="run this designed trajectory (designs.json entry or {fourier: ...}) instead of designing")
    p.add_argument("--periods", type=_count, default=2, help="periods of each trajectory (default 2)")
    p.add_argument("--frequency", type=_positive, metavar="HZ", help="base frequency (default 0.5 Hz single-link, 0.2 Hz whole arm)")
    p.add_argument("--tracking-limit", type=_positive, default=0.2, metavar="RAD", help="quick stop beyond this tracking error (default 0.2 rad)")
    p.add_argument("--seed", type=_seed, default=0, help="seed of the trajectory optimiser's starts")
    p.add_argument("--out", help="output folder (default runs/<date-time>)")
    p.add_argument("--dry-run", action="store_true", help="design and check only; enable nothing")
    p.add_argument("--interface", help="override the rig's python-can interface")
    p.add_argument("--channel", help="override the rig's channel")
    p.add_argument("--simulate", action=argparse.BooleanOptionalAction, default=None,
                   help="run the rig's simulated arm in this process (default: when the bus is virtual)")
    p.add_argument("--no-zenoh", action="store_true", help="do not stream the records and the experiments' events")
    _zenoh_arguments(p)
    p.set_defaults(run=_excite)

    p = sub.add_parser("serve", help="the estimator service: streamed experiments in, estimate/parameters (and estimate/payload) out")
    p.add_argument("--robot", required=True, help=ROBOT_HELP)
    p.add_argument("--out", metavar="DIR", help="where the service keeps its copy of each experiment it received (default: a temporary folder)")
    p.add_argument("--whole-arm", choices=("identify", "drives"), default="identify",
                   help="identify a whole-arm run as 'armid identify RUN.mcap' does (default), or as 'armid demo' does (excitation window, no low-pass)")
    p.add_argument("--no-payload", action="store_true", help="do not run the payload estimator once the arm is identified")
    p.add_argument("--max-backlog", type=_count, default=2500, help="records queued before the service skips to the newest (default 2500: 5 s at 2 ms)")
    p.add_argument("--duration", type=_positive, help="stop after this many seconds (default: until Ctrl-C)")
    p.add_argument("--json", metavar="JSONL", help="also write every published estimate/parameters document as a JSON line")
    _zenoh_arguments(p)
    p.set_defaults(run=_serve)

    p = sub.add_parser("watch", help="a live view of the stream in the terminal (joints, rate, gaps, events, payload)")
    p.add_argument("--robot", required=True, help="robot name, as in armid/<robot>/... (e.g. puma560)")
    p.add_argument("--duration", type=_positive, help="stop after this many seconds (default: until Ctrl-C)")
    _zenoh_arguments(p)
    p.set_defaults(run=_watch)

    p = sub.add_parser("estimate", help="on-line payload recursive least squares (live over Zenoh, or --replay a recording)")
    p.add_argument("mode", nargs="?", choices=["live"], help="live: subscribe to armid/<robot>/joint_state")
    p.add_argument("--robot", required=True, help="robot description")
    p.add_argument("--params", required=True, metavar="IDENT.json", help="the arm's identification (armid identify --json)")
    p.add_argument("--replay", metavar="DATA", help="run on a recording (MCAP or CSV) and write what would have been published")
    p.add_argument("--out", metavar="JSONL", help="write the estimates as JSON lines (default: standard output)")
    p.add_argument("--reference", metavar="UNLOADED",
                   help="a run of the same trajectory without the payload (MCAP or CSV): estimate from the torque difference at the "
                        "same positions, so that arm-model and friction errors cancel")
    p.add_argument("--period", type=float, default=None,
                   help="expected sample period in s: only checked against the time stamps, which the estimator always uses")
    p.add_argument("--forgetting", type=float, default=0.998,
                   help="forgetting factor per 2 ms of the arm's time while it moves, in (0, 1] (default 0.998: about 1 s)")
    p.add_argument("--publish-every", type=int, default=10, help="publish on every Nth record (default 10: 50 Hz at 2 ms)")
    p.add_argument("--duration", type=float, help="live: stop after this many seconds")
    _zenoh_arguments(p)
    p.set_defaults(run=_estimate)

    p = sub.add_parser("demo", help="the whole job on the simulated arm: excitation, recording, identification, diagnosis, payload, report")
    p.add_argument("--out", default="report", help="report folder (default: report)")
    p.add_argument("--rig", help="rig file (default: the embedded config/rigs/sim.yaml)")
    p.add_argument("--seed", type=_seed, default=0, help="seed of the trajectory optimiser's starts")
    p.set_defaults(run=_demo)

    p = sub.add_parser("sim", help="simulated arm on a CAN bus (virtual, udp_multicast, socketcan), or a Dynamixel chain on a pty")
    p.add_argument("--rig", required=True, help="rig file (config/rigs/sim.yaml)")
    p.add_argument("--interface", help="override the rig's python-can interface")
    p.add_argument("--channel", help="override the rig's channel")
    p.add_argument("--seed", type=_seed, help="override the simulation seed")
    p.add_argument("--duration", type=_positive, help="stop after this many seconds (default: until SIGINT/SIGTERM)")
    p.add_argument("--log", metavar="NPZ", help="on exit, write the simulated state per SYNC")
    p.add_argument("--ready", metavar="FILE", help="write this file once the drives are on the bus (a serial chain: its port)")
    p.set_defaults(run=_sim)

    from .fleet.command import add_parser as add_fleet_parser  # issue 37: the command lives in armid/fleet/

    add_fleet_parser(sub)
    return parser


class _HeldWarnings:
    """Warnings are held while a command reads its inputs: bad input then ends in its one
    error line alone. Once the inputs are read (:meth:`release`) and at a successful end,
    they are printed, one line each."""

    def __init__(self) -> None:
        self.command = ""
        self.held: list[str] | None = []

    def show(self, message: Any, category: Any, filename: str, lineno: int, file: Any = None, line: Any = None) -> None:
        text = f"armid {self.command}: warning: {_one_line(str(message))}"
        if self.held is None:
            print(text, file=sys.stderr)
        elif text not in self.held:
            self.held.append(text)

    def release(self) -> None:
        for text in self.held or []:
            print(text, file=sys.stderr)
        self.held = None


_WARNINGS = _HeldWarnings()



def load_robot_argument(value: str) -> Any:
    """``--robot``: a robot file's path, a URDF's path (a robot of the URDF alone), or the name
    of a shipped robot (``puma560``, ``kuka_lwr4``, ...: ``config/robots/NAME.yaml``)."""
    from armid.io.robot_file import load_robot
    from armid.resources import config_file

    path = Path(value)
    if not path.exists() and "/" not in value and not path.suffix:
        shipped = config_file(f"robots/{value}.yaml")
        if shipped.is_file():
            return load_robot(shipped)
        names = sorted(p.stem for p in config_file("robots").glob("*.yaml"))
        raise RobotFileError(value, "", f"no such file, nor a shipped robot (shipped: {', '.join(names)})")
    return load_robot(path)

def _inputs_read() -> None:
    """The command has read and checked its inputs: print what they warned about."""
    _WARNINGS.release()


def _one_line(text: str, most: int = 600) -> str:
    line = " ".join(str(text).split())
    return line if len(line) <= most else line[: most - 3] + "..."


def _exit_code(err: BaseException) -> tuple[int, str]:
    """(exit code, message) for an error that reached the command line, by type: 2 for bad
    input (an :class:`InputError`: files, recordings, options, data that cannot give an
    estimate, refused plans), 1 for a runtime fault (any other :class:`ArmidError`: a drive,
    the bus, the simulated hardware) or a bug. A ``ValueError`` from elsewhere is a bug, not
    bad input. The tree is drawn in :mod:`armid.schema.errors`."""
    if isinstance(err, ArmidError):
        return (2 if isinstance(err, InputError) else 1), str(err)
    if isinstance(err, OSError):
        # a named file that cannot be opened or written is the user's to fix; a socket or a
        # device failing under a running command is a runtime fault
        if err.filename is not None:
            return 2, f"{err.filename}: {err.strerror or err}"
        return 1, f"{type(err).__name__}: {err}"
    if isinstance(err, RecursionError):
        return 2, "an input is nested too deeply to be read"
    return 1, f"internal error ({type(err).__name__}: {err}); ARMID_DEBUG=1 shows where"


def main(argv: list[str] | None = None) -> int:
    """Run one command. The one boundary: whatever a command raises ends as one line on
    stderr and an exit code; a traceback only with ``ARMID_DEBUG=1``."""
    args = build_parser().parse_args(argv)
    _WARNINGS.command, _WARNINGS.held = args.command, []
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _WARNINGS.show
            code = int(args.run(args))
        _WARNINGS.release()
        return code
    except KeyboardInterrupt:
        print(f"armid {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as err:
        if os.environ.get("ARMID_DEBUG", "") not in ("", "0"):
            import traceback

            traceback.print_exc()
        code, message = _exit_code(err)
        print(f"armid {args.command}: error: {_one_line(message)}", file=sys.stderr)
        return code


if __name__ == "__main__":
    raise SystemExit(main())

"""The ``armid`` command line (INTERFACES.md). Exit 0 on success, 2 on bad usage or bad
input (one line on stderr naming the file and what is wrong), 1 on a runtime fault."""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from identify.errors import ArmidError, IdentificationError, PoorExcitationWarning, RecordingError, RobotFileError, UsageError


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        self.print_usage(sys.stderr)
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        raise SystemExit(2)


def _identify(args: argparse.Namespace) -> int:
    from identify.identification import IdentifyOptions, identify
    from identify.preprocess import PrepareOptions, prepare
    from identify.recordings import read_recording, write_csv
    from identify.robot_file import load_robot

    robot = load_robot(args.robot)
    options = PrepareOptions(max_gap_factor=args.max_gap_factor, lowpass_hz=args.lowpass)
    experiments = [prepare(read_recording(p, robot), robot, options) for p in args.data]
    validation = [prepare(read_recording(p, robot), robot, options) for p in args.validate or []]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PoorExcitationWarning)
        result = identify(robot, experiments, validation, IdentifyOptions(weighting=args.weighting))
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    doc = result.to_json()
    feasible_line = _feasible(args, robot, result, validation, doc)
    for path, prep in zip(list(args.data) + list(args.validate or []), experiments + validation):
        for note in prep.notes:
            print(f"{path}: {note}", file=sys.stderr)
    for out in (args.json, args.predictions):
        if out:
            Path(out).parent.mkdir(parents=True, exist_ok=True)
    if args.json:
        Path(args.json).write_text(json.dumps(doc, indent=1) + "\n")
    segments = [s for p in (validation or experiments) for s in p.segments]
    if args.predictions:
        if not validation:
            raise IdentificationError("--predictions needs --validate data")
        t = np.concatenate([s.t for s in segments])
        write_csv(args.predictions, t, {"tau_hat": np.concatenate([result.predict(s) for s in segments])})
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


def _feasible(args: argparse.Namespace, robot: Any, result: Any, validation: list[Any], doc: dict[str, Any]) -> str | None:
    """``--feasible`` / ``--urdf``: the physically consistent estimate into ``doc["feasible"]``
    and, with ``--urdf OUT``, the identified inertials written back as a URDF."""
    if not (args.feasible or args.urdf):
        return None
    from identify.feasible import feasible_estimate

    from .urdf_export import effect_values, write_urdf

    fr = feasible_estimate(result, validation or None)
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
    from identify.diagnosis import diagnose
    from identify.preprocess import PrepareOptions, prepare
    from identify.recordings import read_recording, write_csv
    from identify.robot_file import load_robot

    robot = load_robot(args.robot)
    options = PrepareOptions(max_gap_factor=args.max_gap_factor, lowpass_hz=args.lowpass, torque_hold=args.torque_hold)
    experiments = [prepare(read_recording(p, robot), robot, options) for p in args.data]
    validation = [prepare(read_recording(p, robot), robot, options) for p in args.validate]
    for path, prep in zip(list(args.data) + list(args.validate), experiments + validation):
        for note in prep.notes:
            print(f"{path}: {note}", file=sys.stderr)
    diag = diagnose(robot, experiments, validation)
    doc = diag.to_json()
    feasible_line = None
    if args.feasible or args.urdf:
        feasible_line = _diagnosed_feasible(args, robot, diag, experiments, validation, doc)
    for out in (args.json, args.predictions):
        if out:
            Path(out).parent.mkdir(parents=True, exist_ok=True)
    if args.json:
        Path(args.json).write_text(json.dumps(doc, indent=1) + "\n")
    if args.predictions:
        t = diag.validation_motion[0]
        write_csv(args.predictions, t, {"tau_hat": diag.residual_after[1]})
    if args.report:
        from .report import write_diagnosis_report

        write_diagnosis_report(diag, robot.name, Path(args.report))
    for f in diag.found:
        print(f.sentence())
    if not diag.found:
        print("nothing significant found: the declared model explains the data to its noise")
    for a in diag.absorbed:
        print(f"absorbed (not a finding): {a['effect']} on joint {a['joint']} joins {a['into']}")
    print(f"{robot.name}: validation error {100 * doc['before']['relative_error']:.3g} % -> {100 * doc['after']['relative_error']:.3g} %")
    if feasible_line:
        print(feasible_line)
    return 0


def _diagnosed_feasible(args: argparse.Namespace, robot: Any, diag: Any, experiments: list[Any], validation: list[Any], doc: dict[str, Any]) -> str | None:
    """The feasible estimate of the declared model plus every finding that is a declarable
    (linear) effect; findings that are not (delay, gain, cogging, tilt, ...) are named as
    left out."""
    from dataclasses import replace

    from identify.effects import LINEAR_EFFECTS
    from identify.identification import IdentifyOptions, identify
    from identify.robot import DeclaredEffect

    added = [f for f in diag.found if f.effect in LINEAR_EFFECTS and f.joint is not None]
    left_out = [f"{f.effect}@{'arm' if f.joint is None else f.joint + 1}" for f in diag.found if f not in added]
    model = replace(robot, effects=tuple(robot.effects) + tuple(DeclaredEffect(f.effect, f.joint + 1) for f in added))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoorExcitationWarning)
        result = identify(model, experiments, validation, IdentifyOptions())
    line = _feasible(args, model, result, validation, doc)
    doc["feasible"]["model"] = {"declared": doc.get("declared", []), "added_findings": [f"{f.effect}@{f.joint + 1}" for f in added],
                                "left_out_findings": left_out}
    return line


def _record(args: argparse.Namespace) -> int:
    import platform
    import signal
    import threading
    import time

    import can

    from daq.acquisition import Acquisition, Sink
    from daq.recorder import McapRecorder
    from drivers.rig import load_rig, open_bus

    rig = load_rig(args.rig)
    changes = {k: v for k, v in (("interface", args.interface), ("channel", args.channel)) if v}
    if changes and not rig.is_serial:
        rig = rig.with_bus(**changes)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    driver: Any
    arm = chain = None
    if rig.serial is not None:  # a Dynamixel chain: 'port: sim' is the simulated chain on a pty
        from drivers.dynamixel_driver import DynamixelDriver

        port = args.channel or rig.serial.port
        simulate = port == "sim" if args.simulate is None else args.simulate
        if simulate:
            from sim_bus.servo_chain import ServoChainProcess

            chain = ServoChainProcess(args.rig)
            port = chain.port
        driver = DynamixelDriver(rig, port=port)
    else:
        from drivers.canopen_driver import CanopenDriver

        simulate = args.simulate if args.simulate is not None else rig.bus.interface == "virtual"
        if simulate:
            from sim_bus.arm import SimulatedArm

            arm = SimulatedArm(rig, bus=open_bus(**rig.bus.kwargs()))
        driver = CanopenDriver(rig)
        # an arm simulated in this process never runs ahead of what records it (SYNC waits for
        # the consumer); --duration is then the arm's time, whatever the wall clock does
        driver.paced_by_consumer = simulate
    paced = simulate and not rig.is_serial
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    session = stream = None
    can_log = None
    try:
        driver.start()
        if not rig.is_serial:
            assert driver.network is not None and driver.network.notifier is not None
            from daq.canlog import BusLog

            can_log = BusLog(driver, out / "can.log")  # every frame on the bus, the master's included
        import armid as _armid_pkg

        metadata = {
            "robot": rig.robot.name, "rig": rig.name, "rig_file": rig.source, "period_s": rig.period_s,
            "bus": f"dynamixel {driver.port_name} at {rig.bus.bitrate} baud" if rig.is_serial else f"{rig.bus.interface}:{rig.bus.channel}",
            "pdo_plan": None if rig.is_serial else rig.pdo_plan,
            "drives": driver.drive_configuration, "excitation": "none (armid record)",
            "versions": {"armid": getattr(_armid_pkg, "__version__", "0.1.0"), "python": platform.python_version(),
                         "python-can": can.__version__},
        }
        recorder = McapRecorder(out / "run.mcap", [j.name for j in rig.robot.joints], driver.torque_constants, metadata)
        sinks = [Sink("recorder", recorder.write, bounded=False)]
        if not args.no_zenoh:
            import zenoh

            from daq.stream import Stream, session_config

            session = zenoh.open(session_config(args.zenoh_listen, args.zenoh_connect, args.zenoh_config))
            stream = Stream(session, rig.robot.name, "recorder", lambda: {"records": acq.sequence, "invalid": acq.invalid.tolist(),
                                                                          "dropped_by_stream": sinks[-1].dropped})
            sinks.append(Sink("zenoh", stream.publish, bounded=True, capacity=5000))
        acq = Acquisition(driver, sinks, on_fault=lambda f: stream.event("fault", joint=f.joint + 1, code=f.code, meaning=f.meaning) if stream else None)
        if stream:
            stream.event("start", rig=rig.name)
        acq.start()
        start = time.monotonic()
        print(f"armid record: {rig.name} -> {out / 'run.mcap'} (Ctrl-C stops)", file=sys.stderr, flush=True)
        while not stop.wait(0.1):
            elapsed = acq.sequence * rig.period_s if paced else time.monotonic() - start
            if args.duration and elapsed >= args.duration:
                break
            if acq.error:
                break
        acq.stop()
        recorder.close()
        if can_log is not None:
            can_log.stop()
        if stream:
            stream.event("stop", records=acq.sequence)
        print(f"armid record: {acq.sequence} records, invalid per joint {acq.invalid.tolist()}, lost cycles per joint "
              f"{driver.lost_cycles.tolist()}" + (f", dropped by the stream {sinks[-1].dropped}" if stream else ""), file=sys.stderr)
        return 1 if acq.error else 0
    finally:
        driver.close()
        if stream:
            stream.close()
        if session is not None:
            session.close()
        if arm is not None:
            arm.close()
        if chain is not None:
            chain.close()


def _excite(args: argparse.Namespace) -> int:
    import time

    from rich.console import Console

    from daq.excite import ExcitationSession
    from drivers.rig import load_rig
    from identify import excitation as ex

    from .experiments import Experiment, design_experiments, run_experiments, write_json

    rig = load_rig(args.rig)
    changes = {k: v for k, v in (("interface", args.interface), ("channel", args.channel)) if v}
    if changes:
        rig = rig.with_bus(**changes)
    robot = rig.robot
    n = robot.n_joints
    console = Console(stderr=True)
    simulate = args.simulate if args.simulate is not None else rig.bus.interface == "virtual"
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
    out = Path(args.out or f"runs/{time.strftime('%Y%m%d-%H%M%S')}")
    # the pose the arm will be at: the rig's (simulated) start, or the drives' own report
    start = np.asarray(rig.simulation.get("initial_position", np.zeros(n)), float) if simulate else None
    with ExcitationSession(rig, simulate=simulate, tracking_limit_rad=args.tracking_limit) as session:
        if start is None or np.abs(start - session.position).max() > 0.02:
            start = session.position
        if args.trajectory:
            doc = json.loads(Path(args.trajectory).read_text())
            traj = ex.trajectory_from_json(doc)
            limits = ex.Limits.of(robot)
            p = ex.plan(traj, start, limits, periods=args.periods)
            ex.check_plan(robot, p, rig.period_s, limits)
            design = ex.Design(traj, tuple(int(j) - 1 for j in doc.get("moving_joints", range(1, n + 1))), tuple(range(n)), [], [], 0,
                               float("nan"), float("nan"), {})
            experiments = [Experiment(Path(args.trajectory).stem, design, p)]
        else:
            whole = [("whole", args.periods)] if not links or args.whole else []
            experiments = design_experiments(robot, start, links, whole, rig.period_s, link_frequency_hz=args.frequency or 0.5,
                                              link_periods=args.periods, whole_frequency_hz=args.frequency or 0.2, seed=args.seed,
                                              log=lambda m: console.print(f"  {m}"))
        write_json(out / "designs.json", {e.name: e.design.to_json() for e in experiments})
        console.print(f"armid excite: {len(experiments)} trajectories checked against every limit; recording to {out}")
        if args.dry_run:
            return 0
        reports = run_experiments(session, experiments, out, console)
    write_json(out / "runs.json", [r.to_json() for r in reports])
    for r in reports:
        status = "completed" if r.completed else f"STOPPED: {r.stop_reason}"
        console.print(f"{r.name}: {status}; {r.records} records in {r.recording}; max tracking error {1000 * max(r.max_tracking_error):.1f} mrad")
    return 0 if all(r.completed for r in reports) else 1


def _estimate(args: argparse.Namespace) -> int:
    import time

    from daq.payload_service import EstimateStream
    from identify.payload import PayloadRLS, arm_model_from_identification
    from identify.recordings import read_mcap_arrays, read_recording
    from identify.robot_file import load_robot

    if not args.replay and args.mode != "live":
        raise UsageError("say what to run on: 'live' (the Zenoh stream) or --replay DATA")
    robot = load_robot(args.robot)
    try:
        doc = json.loads(Path(args.params).read_text())
    except json.JSONDecodeError as err:
        raise RecordingError(args.params, f"not JSON: line {err.lineno}: {err.msg}") from None
    arm = arm_model_from_identification(robot, doc)
    kt = np.array([j.torque_constant for j in robot.joints])
    period = args.period
    stream = EstimateStream(PayloadRLS(arm, period, forgetting=args.forgetting), kt, publish_every=args.publish_every)
    out = open(args.out, "w") if args.out else sys.stdout  # noqa: SIM115 - closed below
    try:
        if args.replay:
            path = Path(args.replay)
            if path.suffix.lower() == ".mcap":
                a, _, notes = read_mcap_arrays(path)
                if not a:
                    raise RecordingError(str(path), "no joint_state record could be read" + (f": {notes[0]}" if notes else ""))
                records = zip(a["sequence"].tolist(), a["t"].tolist(), a["valid"], a["position"], a["measured_current"])
            else:
                rec = read_recording(path, robot)
                notes = rec.notes
                ones = np.ones(robot.n_joints, bool)
                records = ((k, float(rec.t[k]), ones, rec.q[k], rec.tau[k] / kt) for k in range(rec.n_samples))
            for note in notes:
                print(f"{path}: {note}", file=sys.stderr)
            start = time.perf_counter()
            docs = stream.feed(records)
            for d in docs:
                out.write(json.dumps(d) + "\n")
            seconds = time.perf_counter() - start
            n = stream.estimator.n_updates_ if hasattr(stream.estimator, "n_updates_") else 0
            print(f"armid estimate: {n} updates, {len(docs)} estimates in {seconds:.2f} s"
                  + (f"; last: mass {docs[-1]['mass']:.3f} kg" if docs else ""), file=sys.stderr)
            return 0
        import zenoh

        from daq.payload_service import PayloadService
        from daq.stream import session_config

        session = zenoh.open(session_config(args.zenoh_listen, args.zenoh_connect, args.zenoh_config))
        service = PayloadService(session, robot.name, stream, on_estimate=lambda d: out.write(json.dumps(d) + "\n"))
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


def _watch(args: argparse.Namespace) -> int:
    import zenoh

    from daq.stream import session_config

    from .watch import watch

    with zenoh.open(session_config(args.zenoh_listen, args.zenoh_connect, args.zenoh_config)) as session:
        state = watch(session, args.robot, args.duration)
    print(f"armid watch: {state.received} records, {state.gaps} gaps ({state.missing} missing), {state.bad} unreadable", file=sys.stderr)
    return 0


def _demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    return run_demo(Path(args.out), Path(args.rig) if args.rig else None, seed=args.seed)


def _sim(args: argparse.Namespace) -> int:
    import signal
    import threading

    from drivers.rig import load_rig
    from sim_bus.arm import SimulatedArm

    rig = load_rig(args.rig)
    changes = {k: v for k, v in (("interface", args.interface), ("channel", args.channel)) if v}
    if changes and not rig.is_serial:
        rig = rig.with_bus(**changes)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    if rig.is_serial:
        return _sim_chain(rig, args, stop)
    arm = SimulatedArm(rig, seed=args.seed)
    print(f"armid sim: {rig.name}: {rig.n_joints} drives (nodes {', '.join(str(d.node_id) for d in rig.drives)}) "
          f"on {rig.bus.interface}:{rig.bus.channel}, lock-step with SYNC at {rig.period_s * 1000:g} ms", file=sys.stderr, flush=True)
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

    from sim_bus.servo_chain import SimulatedServoChain

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


def _zenoh_arguments(p: argparse.ArgumentParser) -> None:
    """Where the Zenoh session connects (peer mode, multicast scouting off)."""
    p.add_argument("--zenoh-listen", nargs="*", metavar="ENDPOINT", help="Zenoh endpoints to listen on, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--zenoh-connect", nargs="*", metavar="ENDPOINT", help="Zenoh endpoints to connect to")
    p.add_argument("--zenoh-config", metavar="JSON5", help="a Zenoh configuration file (config/zenoh/lab.json5)")


def _feasible_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--feasible", action="store_true",
                   help="also the physically consistent estimate (pseudo-inertia PSD, friction >= 0) and a consistency report in the JSON")
    p.add_argument("--urdf", metavar="OUT", help="write the physically consistent model as a URDF (implies --feasible)")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="armid", description="Robot dynamics identification (Khosla 1987) from servo data.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    p = sub.add_parser("identify", help="least-squares identification (eq. 18) with identifiability classes")
    p.add_argument("data", nargs="+", help="recordings to identify on (CSV or .npz)")
    p.add_argument("--robot", required=True, help="robot description (config/robots/*.yaml)")
    p.add_argument("--validate", nargs="+", metavar="DATA", help="held-out recordings for the validation error")
    p.add_argument("--json", metavar="OUT", help="write the result as JSON (INTERFACES.md)")
    p.add_argument("--report", metavar="DIR", help="write a markdown report with PNG plots")
    p.add_argument("--predictions", metavar="CSV", help="write predicted validation torques (t, tau_hat1..n)")
    p.add_argument("--weighting", choices=("wls", "ols"), default="wls", help="per-joint weighted (default) or ordinary LS")
    _feasible_arguments(p)
    p.add_argument("--lowpass", type=float, metavar="HZ", help="zero-phase low-pass before differentiating")
    p.add_argument("--max-gap-factor", type=float, default=20.0, help="split where a step exceeds this many median steps")
    p.set_defaults(run=_identify)

    p = sub.add_parser("diagnose", help="residual analysis: find undeclared effects, add them, refit, error before/after")
    p.add_argument("data", nargs="+", help="recordings to identify on (CSV or .npz)")
    p.add_argument("--robot", required=True, help="robot description (config/robots/*.yaml)")
    p.add_argument("--validate", nargs="+", metavar="DATA", required=True, help="held-out recordings: every score is measured on them")
    p.add_argument("--json", metavar="OUT", help="write the findings and the errors before and after as JSON")
    p.add_argument("--report", metavar="DIR", help="write diagnosis.md with residual plots per joint")
    p.add_argument("--predictions", metavar="CSV", help="write the final model's predicted validation torques (t, tau_hat1..n)")
    p.add_argument("--lowpass", type=float, metavar="HZ", help="zero-phase low-pass before differentiating")
    _feasible_arguments(p)
    p.add_argument("--torque-hold", action="store_true", help="torques were held over the period before each sample (drive currents between SYNCs)")
    p.add_argument("--max-gap-factor", type=float, default=20.0, help="split where a step exceeds this many median steps")
    p.set_defaults(run=_diagnose)

    p = sub.add_parser("record", help="record the drives through daq/: MCAP, raw CAN log, live Zenoh stream")
    p.add_argument("--rig", required=True, help="rig file")
    p.add_argument("--out", required=True, help="output folder (run.mcap, can.log)")
    p.add_argument("--duration", type=float, help="seconds to record (the arm's time when it is simulated here; default: until Ctrl-C)")
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
    p.add_argument("--periods", type=int, default=2, help="periods of each trajectory (default 2)")
    p.add_argument("--frequency", type=float, metavar="HZ", help="base frequency (default 0.5 Hz single-link, 0.2 Hz whole arm)")
    p.add_argument("--tracking-limit", type=float, default=0.2, metavar="RAD", help="quick stop beyond this tracking error (default 0.2 rad)")
    p.add_argument("--seed", type=int, default=0, help="seed of the trajectory optimiser's starts")
    p.add_argument("--out", help="output folder (default runs/<date-time>)")
    p.add_argument("--dry-run", action="store_true", help="design and check only; enable nothing")
    p.add_argument("--interface", help="override the rig's python-can interface")
    p.add_argument("--channel", help="override the rig's channel")
    p.add_argument("--simulate", action=argparse.BooleanOptionalAction, default=None,
                   help="run the rig's simulated arm in this process (default: when the bus is virtual)")
    p.set_defaults(run=_excite)

    p = sub.add_parser("watch", help="a live view of the stream in the terminal (joints, rate, gaps, events, payload)")
    p.add_argument("--robot", required=True, help="robot name, as in armid/<robot>/... (e.g. puma560)")
    p.add_argument("--duration", type=float, help="stop after this many seconds (default: until Ctrl-C)")
    _zenoh_arguments(p)
    p.set_defaults(run=_watch)

    p = sub.add_parser("estimate", help="on-line payload recursive least squares (live over Zenoh, or --replay a recording)")
    p.add_argument("mode", nargs="?", choices=["live"], help="live: subscribe to armid/<robot>/joint_state")
    p.add_argument("--robot", required=True, help="robot description")
    p.add_argument("--params", required=True, metavar="IDENT.json", help="the arm's identification (armid identify --json)")
    p.add_argument("--replay", metavar="DATA", help="run on a recording (MCAP or CSV) and write what would have been published")
    p.add_argument("--out", metavar="JSONL", help="write the estimates as JSON lines (default: standard output)")
    p.add_argument("--period", type=float, default=0.002, help="sample period in s (default 0.002)")
    p.add_argument("--forgetting", type=float, default=0.998, help="forgetting factor while the arm moves (default 0.998: about 1 s)")
    p.add_argument("--publish-every", type=int, default=10, help="publish on every Nth record (default 10: 50 Hz at 2 ms)")
    p.add_argument("--duration", type=float, help="live: stop after this many seconds")
    _zenoh_arguments(p)
    p.set_defaults(run=_estimate)

    p = sub.add_parser("demo", help="the whole job on the simulated arm: excitation, recording, identification, diagnosis, payload, report")
    p.add_argument("--out", default="report", help="report folder (default: report)")
    p.add_argument("--rig", help="rig file (default: the embedded config/rigs/sim.yaml)")
    p.add_argument("--seed", type=int, default=0, help="seed of the trajectory optimiser's starts")
    p.set_defaults(run=_demo)

    p = sub.add_parser("sim", help="simulated arm on a CAN bus (virtual, udp_multicast, socketcan), or a Dynamixel chain on a pty")
    p.add_argument("--rig", required=True, help="rig file (config/rigs/sim.yaml)")
    p.add_argument("--interface", help="override the rig's python-can interface")
    p.add_argument("--channel", help="override the rig's channel")
    p.add_argument("--seed", type=int, help="override the simulation seed")
    p.add_argument("--duration", type=float, help="stop after this many seconds (default: until SIGINT/SIGTERM)")
    p.add_argument("--log", metavar="NPZ", help="on exit, write the simulated state per SYNC")
    p.add_argument("--ready", metavar="FILE", help="write this file once the drives are on the bus (a serial chain: its port)")
    p.set_defaults(run=_sim)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.run(args))
    except ArmidError as err:
        # bad input (files, recordings, data that cannot give an estimate, refused plans) is 2
        print(f"armid {args.command}: error: {err}", file=sys.stderr)
        return 2 if isinstance(err, ValueError | RobotFileError | RecordingError | IdentificationError) else 1
    except OSError as err:
        print(f"armid {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())

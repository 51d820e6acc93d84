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
    return 0


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
    return 0


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


def _replay_records(path: Path, robot: Any, kt: np.ndarray, period_s: float | None) -> tuple[list[tuple[Any, ...]], list[str]]:
    """(sequence, time, valid, position, current) of a recording (MCAP or CSV), in order, on
    the recording's own time stamps; time must increase (a CSV names its line)."""
    from identify.recordings import read_mcap_arrays, read_recording

    if path.suffix.lower() == ".mcap":
        if not path.exists():
            raise RecordingError(str(path), "no such file")
        a, _, notes = read_mcap_arrays(path)
        if not a:
            raise RecordingError(str(path), "no joint_state record could be read" + (f": {notes[0]}" if notes else ""))
        if a["position"].shape[1] != robot.n_joints:
            raise RecordingError(str(path), f"{a['position'].shape[1]} joints recorded, robot {robot.name} has {robot.n_joints}")
        t = np.asarray(a["t"], float)
        records = list(zip(a["sequence"].tolist(), t.tolist(), a["valid"], a["position"], a["measured_current"]))
    else:
        rec = read_recording(path, robot)
        notes, t = list(rec.notes), np.asarray(rec.t, float)
        back = np.flatnonzero(~(np.diff(t) > 0))
        if back.size:
            k = int(back[0]) + 1
            raise RecordingError(str(path), f"line {k + 2}: time {t[k]:.6g} s is not after the line before ({t[k - 1]:.6g} s): "
                                            "time must increase (a reversed or shuffled log?)")
        ones = np.ones(robot.n_joints, bool)
        records = [(k, float(t[k]), ones, rec.q[k], rec.tau[k] / kt) for k in range(rec.n_samples)]
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
    if not docs:
        return head + "; no estimate (too few records to differentiate)"
    last = docs[-1]
    if last["mass"] is None:
        what = "mass not excited: the motion does not determine it (no estimate)"
    else:
        com = "" if last["com"] is None else ", centre of mass [" + ", ".join(f"{100 * c:.1f}" for c in last["com"]) + "] cm"
        what = f"mass {last['mass']:.3f} +- {last['mass_std']:.3f} kg{com}, {last['status']}"
    return head + f"; last: {what}" + (f" ({', '.join(extra)})" if extra else "")


def _estimate(args: argparse.Namespace) -> int:
    """On-line payload estimation, live or on a recording; always on the records' time stamps."""
    import time

    from daq.payload_service import EstimateStream
    from identify.payload import PayloadRLS, ReferenceRun, arm_model_from_identification
    from identify.robot_file import load_robot

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
    robot = load_robot(args.robot)
    doc = _identification_document(args.params, robot)
    arm = arm_model_from_identification(robot, doc)
    kt = np.array([j.torque_constant for j in robot.joints])
    reference = None
    if args.reference:
        ref_records, ref_notes = _replay_records(Path(args.reference), robot, kt, args.period)
        for note in ref_notes:
            print(f"{args.reference}: {note}", file=sys.stderr)
        keep = [r for r in ref_records if np.all(r[2])]
        try:
            reference = ReferenceRun(arm, np.array([r[1] for r in keep]), np.array([r[3] for r in keep]),
                                     np.array([r[4] for r in keep]) * kt)
        except ValueError as err:
            raise RecordingError(args.reference, str(err)) from None
    estimator = PayloadRLS(arm, forgetting=args.forgetting, reference=reference)
    stream = EstimateStream(estimator, kt, publish_every=args.publish_every, strict_time=bool(args.replay),
                            source=str(args.replay or "stream"))
    if args.replay:
        records, notes = _replay_records(Path(args.replay), robot, kt, args.period)
        for note in notes:
            print(f"{args.replay}: {note}", file=sys.stderr)
    out = open(args.out, "w") if args.out else sys.stdout  # noqa: SIM115 - closed below
    try:
        if args.replay:
            start = time.perf_counter()
            docs = stream.feed(records)
            for d in docs:
                out.write(json.dumps(d, allow_nan=False) + "\n")
            seconds = time.perf_counter() - start
            print(_estimate_summary(estimator.n_updates_ if hasattr(estimator, "n_updates_") else 0, docs, seconds, stream), file=sys.stderr)
            return 0
        import zenoh

        from daq.payload_service import PayloadService
        from daq.stream import session_config

        estimator.warm()  # nothing left to run for the first time once records arrive
        session = zenoh.open(session_config(args.zenoh_listen, args.zenoh_connect, args.zenoh_config))
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

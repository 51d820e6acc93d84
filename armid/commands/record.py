"""``armid record``: the drives recorded through daq/ (MCAP, the raw CAN log) and streamed over Zenoh."""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path
from typing import Any

from .arguments import positive_number
from .output import inputs_read
from .rig import open_rig_driver, rig_from_arguments, stopped_by_signals
from .ros2 import add_ros2_arguments, check_source_arguments, record_ros2_source, ros2_bridge
from .session import add_zenoh_arguments, open_zenoh


def _record(args: argparse.Namespace) -> int:
    check_source_arguments(args)
    if args.ros2_source is not None:
        return record_ros2_source(args)
    return _record_rig(args)


def _record_rig(args: argparse.Namespace) -> int:
    import time

    from armid.daq.acquisition import Acquisition, Sink, SinkFailure
    from armid.daq.recorder import McapRecorder
    from armid.schema import versions

    rig = rig_from_arguments(args)
    inputs_read()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    driver, sim = open_rig_driver(rig, args)
    # an arm simulated here or by `armid sim` never runs ahead of what records it (SYNC waits
    # for the consumer or the drives); --duration is then the arm's time, whatever the wall clock does
    session = stream = None
    can_log = None
    with stopped_by_signals() as stop, contextlib.ExitStack() as ros2:
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
            acq: Acquisition  # made below, once its sinks are; the stream's status reads it
            if not args.no_zenoh:
                from armid.daq.stream import Stream

                session = open_zenoh(args)
                stream = Stream(session, rig.robot.name, "recorder", lambda: {"records": acq.sequence, "invalid": acq.invalid.tolist(),
                                                                              "dropped_by_stream": sinks[-1].dropped})
                sinks.append(Sink("zenoh", stream.publish, bounded=True, capacity=5000))
            ros2.enter_context(ros2_bridge(args, session, rig.robot.name, [j.name for j in rig.robot.joints], ("joint_state", "events")))
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
            from ..live import LiveLine, acquisition_line

            live = LiveLine(lambda: acquisition_line(acq, driver, len(faults), rig.period_s))
            acq.start()
            start = time.monotonic()
            print(f"armid record: {rig.name} -> {out / 'run.mcap'} (Ctrl-C stops)", file=sys.stderr, flush=True)
            print(f"armid record: timing: {driver.timing_note}", file=sys.stderr, flush=True)
            with live:
                while not stop.wait(0.1):
                    supervision.events(driver.events())
                    elapsed = acq.sequence * rig.period_s if driver.paced else time.monotonic() - start
                    if args.duration and elapsed >= args.duration:
                        break
                    if acq.error or (can_log is not None and can_log.failure):
                        break
            acq.stop()
            supervision.events(driver.events())
            # how the run ended, in the recording: a run cut short says so wherever it is read
            if can_log is not None:
                can_log.stop()
            log_failure = can_log.failure if can_log is not None else None
            stop_line = acq.error or log_failure
            closed = _close(recorder, {"completed": stop_line is None, "stop": stop_line})
            if stream:
                stream.event("stop", rig=rig.name, run=run_name, experiment=experiment, records=recorder.count, completed=stop_line is None,
                             reason=stop_line, first_sequence=0, last_sequence=acq.sequence - 1, first_cycle=0, window_s=None)
            print(f"armid record: {acq.sequence} records, invalid per joint {acq.invalid.tolist()}, lost cycles per joint "
                  f"{driver.lost_cycles.tolist()}" + (f", dropped by the stream {sinks[-1].dropped}" if stream else ""), file=sys.stderr)
            if driver.waits_note():  # the simulated chain's own stalls, waited through (drivers.line_progress)
                print(f"armid record: {driver.waits_note()}", file=sys.stderr)
            for line in supervision.summary():
                print(f"armid record: {line}", file=sys.stderr)
            if supervision.failed:
                print(f"armid record: {supervision.verdict()} ({out / 'run.mcap'} holds every record)", file=sys.stderr)
            failure = acq.error if acq.failed is not None else log_failure or closed
            if failure is not None:  # a sink failed (a full disk): the run stopped on it
                raise SinkFailure(f"{failure}; the run stopped after {acq.sequence} records: what reached {out / 'run.mcap'} "
                                  "before it reads back")
            return 1 if acq.error or supervision.failed else 0
        finally:
            driver.close()
            ros2.close()  # what is queued published before the session it listens on closes
            if stream:
                stream.close()
            if session is not None:
                session.close()
            if sim is not None:
                sim.close()


def _close(recorder: Any, end: dict[str, Any]) -> str | None:
    """Close the recording; why it could not be (a full disk), None when it closed. After a
    sink's failure the file may not take its summary either: what it holds reads without one."""
    from armid.daq.recorder import RecorderWriteError

    try:
        recorder.close(end)
    except RecorderWriteError as err:
        return str(err)
    return None


def add_parser(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """``armid record``: its options."""
    p = sub.add_parser("record", help="record the drives through daq/ (or a ROS 2 arm's JointState): MCAP, raw CAN log, live Zenoh stream")
    p.add_argument("--rig", help="rig file (the drives to record)")
    p.add_argument("--robot", help="with --ros2-source: the robot file (or a shipped robot's name) whose joints the messages are matched to")
    p.add_argument("--out", required=True, help="output folder (run.mcap, can.log)")
    p.add_argument("--duration", type=positive_number, help="seconds to record (the arm's time when it is simulated here; default: until Ctrl-C)")
    p.add_argument("--interface", help="override the rig's python-can interface")
    p.add_argument("--channel", help="override the rig's channel")
    p.add_argument("--simulate", action=argparse.BooleanOptionalAction, default=None,
                   help="run the rig's simulated arm in this process (default: when the bus is virtual)")
    p.add_argument("--no-zenoh", action="store_true", help="do not stream")
    add_zenoh_arguments(p)
    add_ros2_arguments(p, source=True)
    p.set_defaults(run=_record)

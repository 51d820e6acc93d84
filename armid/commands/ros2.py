"""ROS 2 over rmw_zenoh on the command line: ``--ros2`` (armid's live keys as ROS 2 topics,
:mod:`armid.daq.ros2_bridge`) and ``armid record --ros2-source TOPIC`` (a ROS 2 arm's JointState
recorded and streamed as armid's own, :mod:`armid.daq.ros2_source`)."""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from armid.schema.errors import UsageError


def add_ros2_arguments(p: argparse.ArgumentParser, source: bool = False) -> None:
    """``--ros2``, ``--ros2-router``, ``--ros2-domain`` (and, on ``record``, ``--ros2-source``)."""
    p.add_argument("--ros2", action="store_true",
                   help="also publish as a ROS 2 node over rmw_zenoh (/armid/<robot>/joint_states, payload, inertia/<link>, diagnostics)")
    p.add_argument("--ros2-router", metavar="ENDPOINT", default=None,
                   help="the ROS 2 Zenoh router (rmw_zenohd) to connect to (default tcp/localhost:7447)")
    p.add_argument("--ros2-domain", metavar="N", type=int, default=None, help="ROS 2 domain id (default: ROS_DOMAIN_ID, else 0)")
    if source:
        p.add_argument("--ros2-source", metavar="TOPIC",
                       help="record a ROS 2 arm's sensor_msgs/msg/JointState from TOPIC (with --robot, instead of --rig)")
        p.add_argument("--ros2-timeout", metavar="S", type=float, default=2.0,
                       help="--ros2-source: seconds without a message after which the source has stopped (default 2)")


@contextlib.contextmanager
def ros2_bridge(args: argparse.Namespace, session: Any, robot: str, joint_names: Sequence[str], listen: Sequence[str]) -> Iterator[Any]:
    """With ``--ros2``: a bridge republishing ``listen`` (armid's keys on ``session``) as ROS 2
    topics for the block's duration; else None."""
    if not getattr(args, "ros2", False) or getattr(args, "dry_run", False):  # a dry run publishes nothing
        yield None
        return
    if session is None:
        raise UsageError("--ros2 publishes what armid streams: it cannot go with --no-zenoh")
    from armid.daq.ros2_bridge import Ros2Bridge
    from armid.io.rmw_zenoh import DEFAULT_ROUTER, Ros2Node, domain_id, open_session

    domain = domain_id(args.ros2_domain)
    router = args.ros2_router or DEFAULT_ROUTER
    ros = open_session(router)
    bridge = None
    try:
        bridge = Ros2Bridge(session, Ros2Node(ros, f"armid_{robot}", domain), robot, joint_names, listen)
        print(f"armid {args.command}: ROS 2 node armid_{robot} on {router}, domain {domain}: topics under {bridge.prefix}",
              file=sys.stderr, flush=True)
        yield bridge
    finally:
        if bridge is not None:
            bridge.close()
            if bridge.dropped or bridge.errors:
                print(f"armid {args.command}: ROS 2: {bridge.dropped} messages dropped"
                      + (f"; last error: {bridge.errors[-1]}" if bridge.errors else ""), file=sys.stderr)
        ros.close()


def check_source_arguments(args: argparse.Namespace) -> None:
    """``--ros2-source`` takes ``--robot`` and no rig; a rig takes no ``--robot``; ``--ros2``
    needs the stream (checked before any drive starts)."""
    from armid.io.rmw_zenoh import domain_id

    if args.ros2 and args.no_zenoh:
        raise UsageError("--ros2 publishes what armid streams: it cannot go with --no-zenoh")
    domain_id(args.ros2_domain)
    if args.ros2_source is None:
        if args.rig is None:
            raise UsageError("armid record needs --rig RIG (the drives) or --ros2-source TOPIC --robot ROBOT (a ROS 2 arm)")
        if args.robot is not None:
            raise UsageError("--robot goes with --ros2-source; a rig file names its robot")
        return
    if args.rig is not None:
        raise UsageError("--ros2-source records a ROS 2 arm, --rig the drives: one or the other")
    if args.robot is None:
        raise UsageError("--ros2-source needs --robot ROBOT: the robot file whose joints the messages are matched to by name")
    if not args.ros2_timeout > 0:
        raise UsageError(f"--ros2-timeout must be a positive number of seconds, got {args.ros2_timeout:g}")


def record_ros2_source(args: argparse.Namespace) -> int:
    """``armid record --ros2-source TOPIC --robot ROBOT``: the source's JointState recorded as
    armid's MCAP and, unless ``--no-zenoh``, streamed on armid's keys."""
    import time

    from armid.daq.recorder import McapRecorder
    from armid.daq.ros2_source import Ros2JointStateSource, Ros2SourceError
    from armid.io.rmw_zenoh import DEFAULT_ROUTER, Ros2Node, check_topic, domain_id, open_session
    from armid.schema import versions

    from .arguments import load_robot_argument
    from .output import inputs_read
    from .rig import stopped_by_signals
    from .session import open_zenoh

    topic = check_topic(args.ros2_source)
    robot = load_robot_argument(args.robot)
    domain = domain_id(args.ros2_domain)
    router = args.ros2_router or DEFAULT_ROUTER
    inputs_read()
    out = Path(args.out)
    names = [j.name for j in robot.joints]
    ros = open_session(router)
    session = stream = recorder = None
    closed = False
    node = Ros2Node(ros, f"armid_{robot.name}_recorder", domain)
    try:
        source = Ros2JointStateSource(node, topic, names, args.ros2_timeout)
        metadata = {"robot": robot.name, "rig": None, "source": f"ROS 2 {topic} (sensor_msgs/msg/JointState) on {router}, domain {domain}",
                    "excitation": "none (armid record --ros2-source)", "versions": versions("eclipse-zenoh", "rosbags")}
        if not args.no_zenoh:
            from armid.daq.stream import Stream

            session = open_zenoh(args)
            stream = Stream(session, robot.name, "recorder", lambda: {"records": source.sequence})
        with stopped_by_signals() as stop, ros2_bridge(args, session, robot.name, names, ("joint_state", "events")):
            print(f"armid record: {topic} on {router} (domain {domain}) -> {out / 'run.mcap'} (Ctrl-C stops)", file=sys.stderr, flush=True)
            source.wait_first(args.ros2_timeout + 3.0, f"router {router}, domain {domain}")
            run_name = out.name or "record"
            recorder = McapRecorder(out / "run.mcap", names, metadata)
            if stream:
                from armid.daq.experiment_stream import experiment_description

                experiment = experiment_description(run_name, None, robot.n_joints, metadata)
                stream.event("start", rig=None, run=run_name, experiment=experiment)
            failure: str | None = None
            said_extra = False
            while not stop.wait(0.05):
                try:
                    states = source.take()
                except Ros2SourceError as err:
                    failure = str(err)
                    break
                if states is None:
                    continue
                if source.extra_names and not said_extra:
                    print(f"armid record: {topic}: joints {', '.join(source.extra_names)} are not the robot file's: left out", file=sys.stderr)
                    said_extra = True
                recorder.write(states)
                if stream:
                    stream.publish(states)
                assert source.first_stamp_s is not None
                if args.duration and float(states.time[-1]) - source.first_stamp_s >= args.duration:
                    break
            recorder.close({"completed": failure is None, "stop": failure})
            closed = True
            if stream:
                stream.event("stop", rig=None, run=run_name, experiment=experiment, records=recorder.count, completed=failure is None,
                             reason=failure, first_sequence=0, last_sequence=source.sequence - 1, first_cycle=0, window_s=None)
                time.sleep(0.1)  # the stop event on its way before the session closes
        print(f"armid record: {recorder.count} records from {topic}", file=sys.stderr)
        if failure is not None:
            raise Ros2SourceError(f"{failure}; the {recorder.count} records before it are in {out / 'run.mcap'}")
        return 0
    finally:
        if recorder is not None and not closed:  # bad input from the source (its joints): what came before it reads back
            recorder.close({"completed": False, "stop": "stopped on an error"})
        node.close()
        if stream is not None:
            stream.close()
        if session is not None:
            session.close()
        ros.close()

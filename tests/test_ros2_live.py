"""ROS 2 over rmw_zenoh, live, against ROS 2 code armid did not write: ``zenoh-ros2-sdk`` (ROBOTIS) as
the ROS 2 node, through a real Zenoh router on loopback (multicast scouting off).

- type hashes (REP-2016) equal the values ROS 2 publishes, and rosbags' independent implementation;
- the attachment is byte for byte zenoh-ext's serialization of (int64, int64, 16 bytes), rmw_zenoh's;
- live in: an SDK node publishes JointState at 100 Hz, names reversed; ``armid record --ros2-source``
  records it by name with its stamps, and re-streams it on armid's keys;
- live out: ``armid record --rig sim.yaml --ros2``: the SDK node receives /armid/puma560/joint_states,
  and armid's node and publisher are on the ROS 2 graph (liveliness);
- a payload and an identified link's inertial reach the SDK node as InertiaStamped.

The SDK reads .msg files; with no local ones it clones ROS 2's repositories (CI has no internet):
each test writes the ones it needs from rosbags' Jazzy typestore (``_write_msgs``).
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from armid.cli import main

zenoh = pytest.importorskip("zenoh")
pytest.importorskip("zenoh_ros2_sdk")
pytestmark = pytest.mark.realtime  # live streams, a 100 Hz source, a simulated arm: run with the timing-sensitive tests

ROOT = Path(__file__).resolve().parent.parent
PUBLISHED = {  # as ROS 2 prints them (`ros2 topic info --verbose`) and ROS 2 code lists them
    "sensor_msgs/msg/JointState": "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e",
    "geometry_msgs/msg/InertiaStamped": "RIHS01_766be45976252babf7f9d8ac4ae7c912a7ceccf71035622529f27518b695aa09",
    "diagnostic_msgs/msg/DiagnosticArray": "RIHS01_5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e",
}
UR5 = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait(condition: Any, seconds: float = 10.0) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.05)
    return bool(condition())


@pytest.fixture
def router() -> Any:
    """A Zenoh router on loopback, as rmw_zenohd is; yields (endpoint, port)."""
    port = _free_port()
    config = zenoh.Config()
    config.insert_json5("mode", '"router"')
    config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    config.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(config)
    try:
        yield f"tcp/127.0.0.1:{port}", port
    finally:
        session.close()


def _msg_text(store: Any, kind: str) -> str:
    """A .msg file of ``kind`` written from the typestore's field definitions."""
    consts, fields = store.fielddefs[kind]

    def spell(desc: Any) -> str:
        node, detail = int(desc[0]), desc[1]
        if node == 1:
            base, bound = detail
            return f"{base}<={bound}" if bound else base
        if node == 2:
            return detail.replace("/msg/", "/")
        inner, n = detail
        return spell(inner) + (f"[{n}]" if node == 3 else (f"[<={n}]" if n else "[]"))

    lines = [f"{typ} {name}={value}" for name, typ, value in consts]
    lines += [f"{spell(desc)} {name}" for name, desc in fields]
    return "\n".join(lines) + "\n"


@pytest.fixture
def sdk(tmp_path: Path) -> Any:
    """The SDK with local .msg files (from rosbags' Jazzy typestore); its one session closed after."""
    from rosbags.typesys import Stores, get_typestore
    from zenoh_ros2_sdk import message_registry
    from zenoh_ros2_sdk.session import ZenohSession

    store = get_typestore(Stores.ROS2_JAZZY)
    msgs = tmp_path / "msgs"
    for kind in ("sensor_msgs/msg/JointState", "std_msgs/msg/Header", "builtin_interfaces/msg/Time", "geometry_msgs/msg/InertiaStamped",
                 "geometry_msgs/msg/Inertia", "geometry_msgs/msg/Vector3", "diagnostic_msgs/msg/DiagnosticArray",
                 "diagnostic_msgs/msg/DiagnosticStatus", "diagnostic_msgs/msg/KeyValue"):
        path = msgs / f"{kind}.msg"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(_msg_text(store, kind))
    message_registry._registry = message_registry.MessageRegistry(str(msgs))
    import zenoh_ros2_sdk

    try:
        yield zenoh_ros2_sdk
    finally:
        if ZenohSession._instance is not None:
            ZenohSession._instance.close()
        message_registry._registry = None


def test_type_hashes_equal_the_published_ones_and_rosbags() -> None:
    from rosbags.typesys import Stores, get_typestore

    from armid.io.rmw_zenoh import type_hash

    jazzy = get_typestore(Stores.ROS2_JAZZY)
    for kind, published in PUBLISHED.items():
        assert type_hash(kind) == published, kind
        assert type_hash(kind, jazzy) == jazzy.hash_rihs01(kind) == published
    # another type through the same code, from rosbags' store: a nested array, constants, a bounded string
    for kind in ("sensor_msgs/msg/BatteryState", "visualization_msgs/msg/Marker", "std_msgs/msg/Empty"):
        assert type_hash(kind, jazzy) == jazzy.hash_rihs01(kind), kind


def test_the_attachment_is_zenoh_ext_s_serialization_and_the_sdk_reads_it() -> None:
    from zenoh.ext import Int64, z_serialize
    from zenoh_ros2_sdk.attachment import Attachment

    from armid.io.rmw_zenoh import attachment, read_attachment

    gid = bytes(range(100, 116))
    ours = attachment(41, 1_700_000_000_123_456_789, gid)
    assert ours == z_serialize((Int64(41), Int64(1_700_000_000_123_456_789), gid)).to_bytes()
    theirs = Attachment.from_bytes(ours)
    assert (theirs.sequence_id, theirs.timestamp_ns, theirs.gid) == (41, 1_700_000_000_123_456_789, gid)
    assert read_attachment(Attachment(7, 9, gid).to_bytes()) == (7, 9, gid)
    with pytest.raises(ValueError, match="not an rmw_zenoh attachment"):
        read_attachment(b"\x0fsequence_number" + ours)


def _publish_joint_states(sdk: Any, port: int, names: list[str], rate_hz: float, seconds: float, sent: dict[int, dict[str, float]],
                          stop: threading.Event, mutate: Any = None) -> None:
    """An SDK node publishing JointState on /joint_states; ``mutate(k, names, ns) -> (names, ns)``
    changes message ``k`` (a fault of the source)."""
    pub = sdk.ROS2Publisher(topic="/joint_states", msg_type="sensor_msgs/msg/JointState", router_ip="127.0.0.1", router_port=port,
                            node_name="joint_state_broadcaster")
    types = pub.session_mgr.store.types
    rng = np.random.default_rng(5)
    start = time.monotonic()
    k = 0
    try:
        while not stop.is_set() and time.monotonic() - start < seconds:
            ns = 1_700_000_000_000_000_000 + k * int(1e9 / rate_hz)
            these = names
            if mutate is not None:
                these, ns = mutate(k, names, ns)
            q, qd, tau = rng.uniform(-3, 3, len(these)), rng.normal(size=len(these)), rng.normal(size=len(these))
            header = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9), frame_id="")
            pub.publish(header=header, name=these, position=q, velocity=qd, effort=tau)
            sent[ns] = {n: (float(a), float(b), float(c)) for n, a, b, c in zip(these, q, qd, tau)}  # type: ignore[misc]
            k += 1
            time.sleep(max(0.0, start + k / rate_hz - time.monotonic()))
    finally:
        pub.close()


def test_record_from_a_ros2_node_by_name_with_its_stamps(router: Any, sdk: Any, tmp_path: Path) -> None:
    """Must hold: 100 Hz, names reversed, 3 s: at least 250 records, every value equal by name, stamps kept;
    and the records re-streamed on armid's keys (so that serve and estimate run unchanged)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from armid.schema.joint_states import JointStates

    endpoint, port = router
    sent: dict[int, Any] = {}
    stop = threading.Event()
    names = list(reversed(UR5)) + ["gripper_joint"]
    publisher = threading.Thread(target=_publish_joint_states, args=(sdk, port, names, 100.0, 30.0, sent, stop), daemon=True)
    publisher.start()
    armid_port = _free_port()
    listener = zenoh.open(_peer([], [f"tcp/127.0.0.1:{armid_port}"]))
    streamed: list[int] = []
    sub = listener.declare_subscriber("armid/ur5/joint_state", lambda s: streamed.append(len(JointStates.unpack(s.payload.to_bytes()))))
    try:
        assert _wait(lambda: len(sent) > 5)
        out = tmp_path / "ros2_run"
        code = main(["record", "--ros2-source", "/joint_states", "--ros2-router", endpoint, "--robot", "ur5", "--duration", "3",
                     "--out", str(out), "--zenoh-connect", f"tcp/127.0.0.1:{armid_port}"])
        assert code == 0
    finally:
        stop.set()
        publisher.join(5)
        sub.undeclare()
        listener.close()
    with open(out / "run.mcap", "rb") as f:  # read by mcap's ROS 2 decoder, not armid's reader
        msgs = [m.decoded_message for m in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(topics=["/joint_states"])]
    print(f"\nlive in: {len(msgs)} records in 3 s of the source's stamps ({len(sent)} published); {sum(streamed)} re-streamed")
    assert len(msgs) >= 250
    assert sum(streamed) == len(msgs)
    # armid's records hold time as f64 seconds: at today's epoch a stamp keeps 2**-22 s (238 ns)
    recorded = np.array([m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in msgs], np.int64)
    published = np.array(sorted(sent), np.int64)
    at = np.searchsorted(published, recorded).clip(1, len(published) - 1)
    at = np.where(np.abs(published[at - 1] - recorded) < np.abs(published[at] - recorded), at - 1, at)
    off = np.abs(published[at] - recorded)
    print(f"header stamps: largest difference {off.max()} ns")
    assert off.max() <= 250 and np.all(np.diff(at) == 1), "the header stamps are the source's, in order, none missed"
    for m, s in zip(msgs, published[at]):
        assert list(m.name) == UR5
        for j, name in enumerate(UR5):
            q, qd, tau = sent[s][name]
            assert abs(m.position[j] - q) <= 1e-9 and abs(m.velocity[j] - qd) <= 1e-9 and abs(m.effort[j] - tau) <= 1e-9


def _peer(connect: list[str], listen: list[str]) -> Any:
    from armid.daq.stream import session_config

    return session_config(listen, connect)


def test_a_source_that_stops_or_lacks_a_joint_is_named(router: Any, sdk: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    endpoint, port = router
    sent: dict[int, Any] = {}
    stop = threading.Event()
    publisher = threading.Thread(target=_publish_joint_states, args=(sdk, port, list(reversed(UR5)), 100.0, 1.5, sent, stop), daemon=True)
    publisher.start()
    try:
        assert _wait(lambda: len(sent) > 5)
        out = tmp_path / "stopped"
        code = main(["record", "--ros2-source", "/joint_states", "--ros2-router", endpoint, "--robot", "ur5", "--duration", "10",
                     "--out", str(out), "--no-zenoh", "--ros2-timeout", "0.5"])
    finally:
        stop.set()
        publisher.join(5)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1
    assert "/joint_states: no message for 0.5 s after" in err[-1] and "the source stopped" in err[-1] and "run.mcap" in err[-1]
    from armid.io.recordings import read_mcap_arrays

    cols, _, _ = read_mcap_arrays(out / "run.mcap")
    assert len(cols["t"]) > 20, "what was recorded is kept"
    # a robot whose joints the source does not have: exit 2, naming them
    sent.clear()
    stop.clear()
    publisher = threading.Thread(target=_publish_joint_states, args=(sdk, port, ["a", "b"], 100.0, 3.0, sent, stop), daemon=True)
    publisher.start()
    try:
        assert _wait(lambda: len(sent) > 5)
        code = main(["record", "--ros2-source", "/joint_states", "--ros2-router", endpoint, "--robot", "ur5", "--duration", "1",
                     "--out", str(tmp_path / "missing"), "--no-zenoh"])
    finally:
        stop.set()
        publisher.join(5)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and "/joint_states: the messages have no joint shoulder_pan_joint" in err[-1]


FAULTS = {
    "back in time": (lambda k, names, ns: (names, ns - 50_000_000 if k == 150 else ns), r"message \d+ goes back in time by 0\.04 s"),
    "a repeated stamp": (lambda k, names, ns: (names, ns - 10_000_000 if k == 150 else ns), r"message \d+ repeats the stamp"),
    "joints changed": (lambda k, names, ns: (names[:-1] if k >= 150 else names, ns),
                       r"the joint names changed at message \d+: \['wrist_3_joint', .*'shoulder_pan_joint'\] before, \['wrist_3_joint', .*'shoulder_lift_joint'\] now"),
}


@pytest.mark.parametrize("fault", list(FAULTS))
def test_a_source_that_goes_back_in_time_or_changes_its_joints_is_named(router: Any, sdk: Any, tmp_path: Path, fault: str,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    """The run ends with one line naming what the source did (exit 1), the records before it kept."""
    from armid.io.recordings import read_mcap_arrays

    endpoint, port = router
    mutate, expect = FAULTS[fault]
    sent: dict[int, Any] = {}
    stop = threading.Event()
    publisher = threading.Thread(target=_publish_joint_states, args=(sdk, port, list(reversed(UR5)), 100.0, 20.0, sent, stop),
                                 kwargs={"mutate": lambda k, names, ns: mutate(k + 1 - first[0], names, ns)}, daemon=True)
    first = [10**9]
    publisher.start()
    try:
        assert _wait(lambda: len(sent) > 5)
        first[0] = len(sent)  # message k of the fault counts from the first the recorder can have seen
        code = main(["record", "--ros2-source", "/joint_states", "--ros2-router", endpoint, "--robot", "ur5", "--duration", "10",
                     "--out", str(tmp_path / "run"), "--no-zenoh"])
    finally:
        stop.set()
        publisher.join(5)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and __import__("re").search(expect, err[-1]), err[-1]
    cols, _, _ = read_mcap_arrays(tmp_path / "run" / "run.mcap")
    assert 50 < len(cols["t"]) < 200 and f"the {len(cols['t'])} records before it are in" in err[-1]


def test_a_second_publisher_on_the_topic_is_named(router: Any, sdk: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    endpoint, port = router
    sent: dict[int, Any] = {}
    stop = threading.Event()
    one = threading.Thread(target=_publish_joint_states, args=(sdk, port, UR5, 100.0, 20.0, sent, stop), daemon=True)
    other: dict[int, Any] = {}
    two = threading.Thread(target=_publish_joint_states, args=(sdk, port, UR5, 100.0, 20.0, other, stop),
                           kwargs={"mutate": lambda k, names, ns: (names, ns + 5_000_000)}, daemon=True)
    one.start()
    try:
        assert _wait(lambda: len(sent) > 5)
        threading.Timer(1.0, two.start).start()
        code = main(["record", "--ros2-source", "/joint_states", "--ros2-router", endpoint, "--robot", "ur5", "--duration", "10",
                     "--out", str(tmp_path / "run"), "--no-zenoh"])
    finally:
        stop.set()
        one.join(5)
        time.sleep(1.1)
        two.join(5)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and "/joint_states: a second publisher (GID" in err[-1], err[-1]


def test_record_with_ros2_is_a_ros2_publisher_the_sdk_receives_and_discovers(router: Any, sdk: Any, tmp_path: Path) -> None:
    """Must hold: `armid record --rig sim.yaml --ros2 --duration 3`: at least 1,000 JointState messages
    on /armid/puma560/joint_states with the robot file's joint names; its node and publisher on the graph."""
    from armid.io.rmw_zenoh import type_hash
    from armid.io.robot_file import load_robot

    endpoint, port = router
    names = [j.name for j in load_robot(ROOT / "config" / "robots" / "puma560.yaml").joints]
    got: list[Any] = []
    sub = sdk.ROS2Subscriber(topic="/armid/puma560/joint_states", msg_type="sensor_msgs/msg/JointState", callback=got.append,
                             router_ip="127.0.0.1", router_port=port)
    assert sub.type_hash == PUBLISHED["sensor_msgs/msg/JointState"], "the SDK's own hash of its .msg files"
    proc = subprocess.Popen([sys.executable, "-m", "armid.cli", "record", "--rig", str(ROOT / "config" / "rigs" / "sim.yaml"), "--ros2",
                             "--ros2-router", endpoint, "--duration", "3", "--out", str(tmp_path / "run"),
                             "--zenoh-listen", f"tcp/127.0.0.1:{_free_port()}"],
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "ARMID_REALTIME": "off"})
    tokens: list[str] = []
    try:
        assert _wait(lambda: len(got) > 50, 60), "no JointState reached the ROS 2 node"
        replies = sub.session_mgr.session.liveliness().get("@ros2_lv/**", timeout=5.0)
        tokens = [str(r.ok.key_expr) for r in replies if r.ok is not None]
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
        sub.close()
    assert proc.returncode == 0, err[-2000:]
    time.sleep(0.5)
    print(f"\nlive out: the ROS 2 node received {len(got)} JointState messages")
    assert len(got) >= 1000
    assert all(list(m.name) == names for m in got)
    stamps = [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in got]
    assert np.all(np.diff(stamps) > 0)
    ours = [t for t in tokens if "/armid_puma560/" in t or t.endswith("/armid_puma560")]
    assert any("/NN/%/%/armid_puma560" in t for t in ours), tokens
    hash_ = type_hash("sensor_msgs/msg/JointState")
    assert any(f"/MP/%/%/armid_puma560/%armid%puma560%joint_states/sensor_msgs::msg::dds_::JointState_/{hash_}/" in t for t in ours), ours


def test_excite_with_ros2_streams_its_run_to_the_ros2_node(router: Any, sdk: Any, tmp_path: Path) -> None:
    """`armid excite --ros2`: the excitation's records reach the ROS 2 node as JointState, as
    `record --ros2`'s do (the same bridge), with the robot file's joint names, and the run completes."""
    from armid.io.robot_file import load_robot

    endpoint, port = router
    names = [j.name for j in load_robot(ROOT / "config" / "robots" / "puma560.yaml").joints]
    got: list[Any] = []
    sub = sdk.ROS2Subscriber(topic="/armid/puma560/joint_states", msg_type="sensor_msgs/msg/JointState", callback=got.append,
                             router_ip="127.0.0.1", router_port=port)
    proc = subprocess.Popen([sys.executable, "-m", "armid.cli", "excite", "--rig", str(ROOT / "config" / "rigs" / "sim.yaml"), "--link", "6",
                             "--periods", "1", "--ros2", "--ros2-router", endpoint, "--out", str(tmp_path / "runs"),
                             "--zenoh-listen", f"tcp/127.0.0.1:{_free_port()}"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**os.environ, "ARMID_REALTIME": "off"})
    try:
        out, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
        sub.close()
    assert proc.returncode == 0, (out + err)[-2000:]
    time.sleep(0.5)
    print(f"\nexcite --ros2: the ROS 2 node received {len(got)} JointState messages")
    assert len(got) >= 1000 and all(list(m.name) == names for m in got)
    moved = np.array([m.position[5] for m in got])
    assert np.ptp(moved) > 0.05, "joint 6 moved in the run the node saw"


def test_payload_and_an_identified_link_reach_the_ros2_node_as_inertia_stamped(router: Any, sdk: Any) -> None:
    """What `serve --ros2` and `estimate --ros2` hear on armid's keys (estimate/parameters,
    estimate/payload: documents of their shape) reaches the ROS 2 node; a link's inertial is the
    identified parameters about the centre of mass (parallel axis, computed here)."""
    from armid.daq.ros2_bridge import Ros2Bridge
    from armid.daq.stream import key
    from armid.io.rmw_zenoh import Ros2Node, open_session

    endpoint, port = router
    armid_port = _free_port()
    armid = zenoh.open(_peer([], [f"tcp/127.0.0.1:{armid_port}"]))
    ros = open_session(endpoint)
    names = [f"j{i}" for i in range(1, 7)]
    bridge = Ros2Bridge(armid, Ros2Node(ros, "armid_puma560", 0), "puma560", names, ("estimate/parameters", "estimate/payload", "events"))
    keys: set[str] = set()
    raw = ros.declare_subscriber("0/armid/puma560/inertia/**", lambda sample: keys.add(str(sample.key_expr)))
    payloads: list[Any] = []
    links: list[Any] = []
    diagnostics: list[Any] = []
    subs = [sdk.ROS2Subscriber(topic=topic, msg_type=kind, callback=got.append, router_ip="127.0.0.1", router_port=port)
            for topic, kind, got in (("/armid/puma560/payload", "geometry_msgs/msg/InertiaStamped", payloads),
                                     ("/armid/puma560/inertia/link6", "geometry_msgs/msg/InertiaStamped", links),
                                     ("/armid/puma560/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", diagnostics))]
    # link 6: mass 0.9 kg, centre of mass c, inertia about it ic; the parameters are about the link frame
    m, c = 0.9, np.array([0.01, -0.02, 0.05])
    ic = np.array([[0.004, 0.0002, -0.0001], [0.0002, 0.005, 0.0003], [-0.0001, 0.0003, 0.003]])
    io = ic + m * (c @ c * np.eye(3) - np.outer(c, c))
    phi6 = [m, *(m * c), io[0, 0], io[0, 1], io[0, 2], io[1, 1], io[1, 2], io[2, 2]]
    # link 6: five parameters identified (their estimates), five not (their modeled values count, not their values);
    # links 1-5: none identified, none published
    params = [{"name": f"p{k}", "link": link, "value": phi6[k] if link == 6 and k in (0, 1, 2, 3, 9) else 99.0,
               "identified": link == 6 and k in (0, 1, 2, 3, 9), "modeled": phi6[k] if link == 6 else 1.0}
              for link in range(1, 7) for k in range(10)]
    doc = {"robot": "puma560", "time": 1_700_000_100.5, "source": "whole_arm whole", "experiment": {"run": "whole", "kind": "whole_arm"},
           "whole_arm": {"whole": {"parameters": params}}, "base_parameters": [{}] * 3, "validation": {"relative_error": 0.031}}
    payload = {"time": 1_700_000_101.25, "mass": 2.013, "com": [0.001, 0.002, 0.081], "inertia": [0.01, 0.0, 0.0, 0.011, 0.0, 0.012]}
    try:
        time.sleep(1.0)  # the subscriptions known to the router
        armid.put(key("puma560", "estimate/parameters"), json.dumps(doc))
        armid.put(key("puma560", "estimate/payload"), json.dumps(payload))
        armid.put(key("puma560", "estimate/payload"), json.dumps({**payload, "mass": None, "com": None, "inertia": None}))
        armid.put(key("puma560", "events"), json.dumps({"time": 1_700_000_102.0, "event": "fault", "joint": 3, "node": 3,
                                                         "code": 0x8130, "meaning": "heartbeat lost"}))
        assert _wait(lambda: payloads and links and len(diagnostics) >= 2)
        time.sleep(0.3)
    finally:
        for s in subs:
            s.close()
        raw.undeclare()
        bridge.close()
        ros.close()
        armid.close()
    assert keys == {f"0/armid/puma560/inertia/link6/geometry_msgs::msg::dds_::InertiaStamped_/{PUBLISHED['geometry_msgs/msg/InertiaStamped']}"}
    assert len(payloads) == 1, "an estimate without a mass, centre of mass and inertia is not published"
    p = payloads[0]
    assert (p.header.frame_id, p.inertia.m, [p.inertia.com.x, p.inertia.com.y, p.inertia.com.z]) == ("link6", 2.013, payload["com"])
    assert p.header.stamp.sec == 1_700_000_101 and p.header.stamp.nanosec == 250_000_000
    assert [p.inertia.ixx, p.inertia.ixy, p.inertia.ixz, p.inertia.iyy, p.inertia.iyz, p.inertia.izz] == payload["inertia"]
    li = links[0].inertia
    assert links[0].header.frame_id == "link6" and abs(li.m - m) < 1e-12
    assert np.allclose([li.com.x, li.com.y, li.com.z], c, atol=1e-12)
    got = np.array([[li.ixx, li.ixy, li.ixz], [li.ixy, li.iyy, li.iyz], [li.ixz, li.iyz, li.izz]])
    assert np.allclose(got, ic, atol=1e-12)
    levels = sorted(s.level for d in diagnostics for s in d.status)
    assert levels == [0, 2], "the experiment identified (OK) and the drive fault (ERROR)"
    fault = next(s for d in diagnostics for s in d.status if s.level == 2)
    assert fault.name == "armid/puma560/joint3" and fault.message == "heartbeat lost"
    outcome = next(s for d in diagnostics for s in d.status if s.level == 0)
    assert {kv.key: kv.value for kv in outcome.values}["link6_identified"] == "5 of 10"


BAD_OPTIONS = {
    "neither rig nor source": (["record", "--out", "x"], r"armid record needs --rig RIG .* or --ros2-source TOPIC --robot ROBOT"),
    "source without robot": (["record", "--ros2-source", "/joint_states", "--out", "x"], r"--ros2-source needs --robot ROBOT"),
    "source and rig": (["record", "--ros2-source", "/joint_states", "--robot", "ur5", "--rig", "r.yaml", "--out", "x"],
                       r"--ros2-source records a ROS 2 arm, --rig the drives: one or the other"),
    "ros2 without the stream": (["record", "--rig", "r.yaml", "--ros2", "--no-zenoh", "--out", "x"], r"--ros2 publishes what armid streams"),
    "domain out of range": (["record", "--ros2-source", "/joint_states", "--robot", "ur5", "--ros2-domain", "300", "--out", "x"],
                            r"--ros2-domain: 300 is not a ROS 2 domain id"),
    "not a topic name": (["record", "--ros2-source", "joint states", "--robot", "ur5", "--out", "x"],
                         r"--ros2-source: 'joint states' is not a ROS 2 topic name"),
    "timeout zero": (["record", "--ros2-source", "/joint_states", "--robot", "ur5", "--ros2-timeout", "0", "--out", "x"],
                     r"--ros2-timeout must be a positive number"),
}


@pytest.mark.parametrize("case", list(BAD_OPTIONS))
def test_bad_ros2_options_exit_2_with_one_line(case: str, capsys: pytest.CaptureFixture[str], tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    argv, expect = BAD_OPTIONS[case]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and __import__("re").search(expect, err[0]), err
    assert not (tmp_path / "x").exists()


def test_a_router_that_is_not_there_is_named(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    assert main(["record", "--ros2-source", "/joint_states", "--robot", "ur5", "--ros2-router", endpoint, "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--ros2-router: cannot reach a ROS 2 Zenoh router at {endpoint}" in err[0], err


@pytest.mark.slow
def test_estimate_live_with_ros2_publishes_its_payload_to_the_ros2_node(router: Any, sdk: Any, tmp_path: Path) -> None:
    """`armid estimate live --ros2` in a process of its own, on a simulated run with a 2 kg payload
    streamed on armid's keys: the ROS 2 node receives the payload as InertiaStamped, each message
    one of the estimates the command wrote."""
    from test_payload import PAYLOAD, _arm_and_design, _ident_doc

    from armid.daq.stream import Stream
    from armid.schema.joint_states import JointStates
    from armid.sim_bus.offline import simulate

    endpoint, port = router
    arm, plan, cfg = _arm_and_design()
    run = simulate(arm.robot, cfg, plan.evaluate, plan.duration_s, payloads=[(0.0, PAYLOAD)], seed=4)  # type: ignore[arg-type]
    n = len(run.t)
    records = JointStates.of_log(np.arange(n), 1_700_000_000.0 + run.t, np.ones((n, 6), bool), run.position, run.torque)
    ident = _ident_doc(arm, tmp_path / "ident.json")
    stream_port = _free_port()
    got: list[Any] = []
    sub = sdk.ROS2Subscriber(topic="/armid/puma560/payload", msg_type="geometry_msgs/msg/InertiaStamped", callback=got.append,
                             router_ip="127.0.0.1", router_port=port)
    out = tmp_path / "estimates.jsonl"
    proc = subprocess.Popen([sys.executable, "-m", "armid.cli", "estimate", "live", "--robot", "puma560", "--params", str(ident),
                             "--ros2", "--ros2-router", endpoint, "--zenoh-listen", f"tcp/127.0.0.1:{stream_port}", "--out", str(out),
                             "--duration", "120"], stderr=subprocess.PIPE, text=True)
    publisher = zenoh.open(_peer([f"tcp/127.0.0.1:{stream_port}"], []))
    stream = Stream(publisher, "puma560", "test", lambda: {})
    try:
        assert proc.stderr is not None
        while "listening" not in (line := proc.stderr.readline()):
            assert line, "estimate ended before it listened"
        time.sleep(1.0)
        for a in range(0, n, 50):  # 0.1 s of the arm's time a put, at about its own pace
            stream.publish(records[a : a + 50])
            time.sleep(0.05)
        assert _wait(lambda: len(got) > 20 and got[-1].inertia.m > 1.0, 30)
        time.sleep(1.0)
    finally:
        stream.close()
        publisher.close()
        sub.close()
        proc.terminate()
        _, err = proc.communicate(timeout=60)
    docs = [json.loads(line) for line in out.read_text().splitlines()]
    published = {(round(d["time"], 6), d["mass"]) for d in docs if d["mass"] is not None and d["com"] is not None}
    print(f"\nestimate --ros2: {len(got)} payload messages, {len(published)} estimates with a mass; last {got[-1].inertia.m:.3f} kg")
    assert all(m.header.frame_id == "link6" for m in got)
    assert all((round(m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec, 6), m.inertia.m) in published for m in got)
    assert len(got) == len(published)
    assert abs(got[-1].inertia.m - PAYLOAD.mass) < 0.1 * PAYLOAD.mass


def _stream_run(stream: Any, name: str, records: Any, n_joints: int, pace_s: float = 0.02) -> None:
    """A run on armid's keys as `armid record` streams one: a start event, the records, a stop event."""
    from armid.daq.experiment_stream import experiment_description

    experiment = experiment_description(name, None, n_joints, {"robot": "puma560", "period_s": 0.002})
    stream.event("start", rig=None, run=name, experiment=experiment)
    for a in range(0, len(records), 50):
        stream.publish(records[a : a + 50])
        time.sleep(pace_s)
    stream.event("stop", rig=None, run=name, experiment=experiment, records=len(records), completed=True, reason=None,
                 first_sequence=int(records.sequence[0]), last_sequence=int(records.sequence[-1]), first_cycle=int(records.cycle[0]),
                 window_s=None)


@pytest.mark.slow
def test_serve_with_ros2_publishes_the_arms_links_and_then_its_payload(router: Any, sdk: Any, tmp_path: Path) -> None:
    """`armid serve --ros2` in a process of its own: a whole-arm run streamed on armid's keys is
    identified, its identified links reach the ROS 2 node as InertiaStamped and its outcome as a
    diagnostic; a second run with a 2 kg payload then reaches it as the payload topic."""
    from test_payload import PAYLOAD, _arm_and_design

    from armid.daq.stream import Stream
    from armid.schema.joint_states import JointStates
    from armid.sim_bus.offline import simulate

    endpoint, port = router
    arm, plan, cfg = _arm_and_design()
    runs = []
    for k, payloads in enumerate(([], [(0.0, PAYLOAD)])):
        run = simulate(arm.robot, cfg, plan.evaluate, plan.duration_s, payloads=payloads, seed=7 + k)  # type: ignore[arg-type]
        n = len(run.t)
        t0 = 1_700_000_000.0 + k * (plan.duration_s + 1.0)
        seq, nan = np.arange(k * n, (k + 1) * n), np.full((n, 6), np.nan)
        runs.append(JointStates(seq, seq.copy(), t0 + run.t, np.ones((n, 6), bool), np.ones((n, 6), bool), run.position, run.velocity,
                                nan, nan.copy(), run.torque, np.zeros((n, 6), np.int64)))  # what a ROS 2 arm's JointState gives
    got: dict[str, list[Any]] = {"link6": [], "payload": [], "diagnostics": []}
    subs = [sdk.ROS2Subscriber(topic=f"/armid/puma560/{topic}", msg_type=kind, callback=got[name].append, router_ip="127.0.0.1",
                               router_port=port)
            for name, topic, kind in (("link6", "inertia/link6", "geometry_msgs/msg/InertiaStamped"),
                                      ("payload", "payload", "geometry_msgs/msg/InertiaStamped"),
                                      ("diagnostics", "diagnostics", "diagnostic_msgs/msg/DiagnosticArray"))]
    stream_port = _free_port()
    docs = tmp_path / "parameters.jsonl"
    proc = subprocess.Popen([sys.executable, "-m", "armid.cli", "serve", "--robot", "puma560", "--ros2", "--ros2-router", endpoint,
                             "--zenoh-listen", f"tcp/127.0.0.1:{stream_port}", "--json", str(docs), "--duration", "400"],
                            stderr=subprocess.PIPE, text=True)
    publisher = zenoh.open(_peer([f"tcp/127.0.0.1:{stream_port}"], []))
    stream = Stream(publisher, "puma560", "test", lambda: {})
    try:
        assert proc.stderr is not None
        while "listening" not in (line := proc.stderr.readline()):
            assert line, "serve ended before it listened"
        time.sleep(1.0)
        _stream_run(stream, "unloaded", runs[0], 6)
        assert _wait(lambda: got["diagnostics"] and docs.exists() and docs.read_text().strip(), 300), "no identification published"
        time.sleep(2.0)  # the payload estimator starts once the arm is identified
        _stream_run(stream, "loaded", runs[1], 6)
        _wait(lambda: len(got["payload"]) > 20 and got["payload"][-1].inertia.m > 1.0, 120)
        time.sleep(1.0)
    finally:
        stream.close()
        publisher.close()
        for s in subs:
            s.close()
        proc.terminate()
        _, err = proc.communicate(timeout=60)
    assert len(got["payload"]) > 20, err[-3000:]
    doc = json.loads(docs.read_text().splitlines()[0])
    from armid.daq.ros2_bridge import link_inertials

    expected = link_inertials(doc)
    print(f"\nserve --ros2: links published {sorted(expected)}, link 6 {len(got['link6'])} message(s), "
          f"{len(got['payload'])} payload messages, last {got['payload'][-1].inertia.m:.3f} kg")
    assert 6 in expected and len(got["link6"]) >= 1
    m, com, inertia, _ = expected[6]
    li = got["link6"][0].inertia
    assert (li.m, (li.com.x, li.com.y, li.com.z), (li.ixx, li.ixy, li.ixz, li.iyy, li.iyz, li.izz)) == (m, com, inertia)
    assert any(s.name == "armid/puma560/identification" and s.level == 0 for d in got["diagnostics"] for s in d.status)
    assert abs(got["payload"][-1].inertia.m - PAYLOAD.mass) < 0.1 * PAYLOAD.mass

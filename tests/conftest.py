"""Shared fixtures: random robots (standard and modified DH, with a prismatic joint), and an
autouse guard that fails a test which leaks a python-can bus, a Zenoh session or a thread,
or leaves a process-wide setting changed (switch interval, frozen objects, signal handlers)."""

from __future__ import annotations

import gc
import os
import signal
import sys
import threading
import time
import weakref
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from armid.identify.robot import Inertial, Joint, JointLimits, JointType, Robot, dh_joint, inertia_entries, mdh_joint

ROOT = Path(__file__).resolve().parent.parent
ROBOTS = ROOT / "config" / "robots"
SHARED = ROOT.parent / "shared"

REALTIME_MODULES = ("test_canopen", "test_daq", "test_dynamixel", "test_excitation", "test_excitation_dynamixel", "test_serve", "test_supervision")
"""The timing-sensitive tests (a bus, a pty, a simulated arm, a live stream): marked ``realtime``
(a test elsewhere is marked so itself); the README's command runs them after the arithmetic,
three at a time (they wait on the arm's clock more than they compute: 65 % of two cores busy
two at a time), and those marked ``alone`` last, one at a time; CI runs those that are not slow
a second time with two busy processes beside them (``.ci/run``)."""


def pytest_configure(config: pytest.Config) -> None:
    """Once per run, before any xdist worker starts: armid's modules compiled to bytecode. Where
    ``PYTHONDONTWRITEBYTECODE`` is set (CI's machines), no process writes it, and each of the
    suite's hundreds of ``armid`` processes compiled the modules it imports again (0.12 s of a
    core for the service's or the demo's imports, measured); the bytecode is read all the same."""
    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        import compileall

        for package in ("armid", "identify", "daq", "drivers", "sim_bus", "config"):
            compileall.compile_dir(ROOT / package, quiet=1)


@pytest.hookimpl(wrapper=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> Iterator[None]:
    for item in items:
        if item.module is not None and item.module.__name__.rsplit(".", 1)[-1] in REALTIME_MODULES:
            item.add_marker(pytest.mark.realtime)
    yield  # -m and -k deselect here
    long_ones_first_on_each_worker(items)


def long_ones_first_on_each_worker(items: list[pytest.Item], workers: int | None = None) -> None:
    """The timing-sensitive tests marked ``slow`` first in each worker's share of the list, in turn.
    ``--dist worksteal`` hands each of the ``workers`` (xdist's count, default 2) an equal share
    and lets an idle worker take another's last tests, never the one it runs nor its next: in
    collection order the two longest came last on one worker, and the other stood idle 95 s of a
    338 s pass. Only the order changes: the arithmetic pass (no ``realtime`` test) keeps its own,
    with its modules' shared fixtures in one piece."""
    n = max(1, workers if workers is not None else int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "2")))
    slow = [item for item in items if item.get_closest_marker("realtime") and item.get_closest_marker("slow")]
    if not slow:
        return
    rest = [item for item in items if not (item.get_closest_marker("realtime") and item.get_closest_marker("slow"))]
    share = len(items) // n
    ordered: list[pytest.Item] = []
    for k in range(n):  # worker k's share: its slow ones, then ordinary tests up to the share's end
        ordered += slow[k::n]
        take = len(rest) if k == n - 1 else max(0, (k + 1) * share - len(ordered))
        ordered += rest[:take]
        rest = rest[take:]
    items[:] = ordered


def random_robot(n: int, convention: str, prismatic_at: int | None, seed: int) -> Robot:
    """A random serial arm with physically valid random inertial values."""
    rng = np.random.default_rng(seed)
    make = dh_joint if convention == "dh" else mdh_joint
    joints = []
    for i in range(n):
        kind = JointType.PRISMATIC if i == prismatic_at else JointType.REVOLUTE
        alpha = float(rng.choice([0.0, np.pi / 2, -np.pi / 2, rng.uniform(-3, 3)]))
        pre, axis, post = make(kind, rng.normal(0, 0.3), alpha, rng.normal(0, 0.3), rng.uniform(-3, 3))
        a = rng.normal(size=(3, 3))
        inertia = a @ a.T * 0.1 + 0.05 * np.eye(3)
        inertial = Inertial(float(rng.uniform(0.5, 5)), tuple(rng.normal(0, 0.2, 3)), tuple(inertia_entries(inertia)))  # type: ignore[arg-type]
        limits = JointLimits((-2.0, 2.0), 2.0, None, 100.0)
        joints.append(Joint(f"j{i + 1}", kind, pre, axis, post, 1.0, limits, inertial))
    return Robot(f"random_{convention}_{seed}", np.array([0.3, -0.2, -9.81]), tuple(joints))


def declare(robot_yaml: Path, path: Path, effects: list[dict[str, Any]], inertials: bool = True) -> Path:
    """A copy of a robot file at ``path`` with ``effects`` declared too (and, with
    ``inertials`` False, no link's modeled inertial values)."""
    import yaml

    doc = yaml.safe_load(robot_yaml.read_text())
    doc["effects"] = [*(doc.get("effects") or []), *effects]
    if not inertials:
        for joint in doc["joints"]:
            joint.pop("inertial", None)
    path.write_text(yaml.safe_dump(doc))
    return path


def identify_blind(case: Any, robot: Path, out: Path) -> tuple[float, dict[str, Any]]:
    """`armid identify` on a blind case (tests/blindgen.py) with ``robot``: the held-out error
    of its ``--predictions`` against the raw validation torque (every stamp predicted), and its JSON."""
    import json

    import blindgen

    from armid.cli import main

    pred, doc = out.with_suffix(".csv"), out.with_suffix(".json")
    assert main(["identify", *map(str, case.ident_csvs), "--robot", str(robot), "--validate", str(case.valid_csv),
                 "--predictions", str(pred), "--json", str(doc)]) == 0
    err, covered = blindgen.relative_error(case.valid_csv, pred)
    assert covered == 1.0
    return err, json.loads(doc.read_text())


def random_motion(n_samples: int, n_joints: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.uniform(-2, 2, (n_samples, n_joints)), rng.normal(size=(n_samples, n_joints)), rng.normal(size=(n_samples, n_joints))


@pytest.fixture(params=[("dh", 5, 2, 11), ("mdh", 6, 3, 12), ("dh", 3, None, 13), ("mdh", 4, 0, 14)], ids=lambda p: f"{p[0]}-{p[1]}j")
def any_robot(request: pytest.FixtureRequest) -> Robot:
    convention, n, prismatic, seed = request.param
    return random_robot(n, convention, prismatic, seed)


# --- leaks -------------------------------------------------------------------------------
_BUSES: weakref.WeakSet[Any] = weakref.WeakSet()
_SESSIONS: list[Any] = []  # zenoh.Session takes no weak reference: closed ones are dropped after each test
_LONG_LIVED_THREADS = ("armid-regressor", "armid-scoring")  # identify.kernels.threads pools: one each per process, by design
_THREAD_GRACE_S = 3.0


def _track_buses_and_sessions() -> None:
    import can
    import zenoh

    if getattr(can.BusABC.__init__, "_armid_tracked", False):
        return
    original_init = can.BusABC.__init__

    def init(self: Any, *args: Any, **kwargs: Any) -> None:
        _BUSES.add(self)
        original_init(self, *args, **kwargs)

    init._armid_tracked = True  # type: ignore[attr-defined]
    can.BusABC.__init__ = init  # type: ignore[method-assign]
    original_open = zenoh.open

    def open_session(*args: Any, **kwargs: Any) -> Any:
        config = args[0] if args else kwargs.get("config")
        _OFF_LOOPBACK.extend(zenoh_off_loopback(config) if config is not None else ["a Zenoh session on the default configuration"])
        session = original_open(*args, **kwargs)
        _SESSIONS.append(session)
        return session

    zenoh.open = open_session


# --- loopback only -------------------------------------------------------------------------
_OFF_LOOPBACK: list[str] = []  # multicast sockets and Zenoh sessions this process opened that could reach another machine
_LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "[::1]")


def joined_devices(group: str) -> set[str]:
    """The network devices on which this machine has joined IPv4 ``group`` (``/proc/net/igmp``)."""
    import socket

    wanted = socket.inet_aton(group)[::-1].hex().upper()  # the kernel prints the address as a host-order word
    devices, device = set(), ""
    for line in Path("/proc/net/igmp").read_text().splitlines()[1:]:
        if not line.startswith("\t"):
            device = line.split()[1]
        elif line.split()[0] == wanted:
            devices.add(device)
    return devices


def _track_network() -> None:
    """Check every multicast socket (python-can's ``udp_multicast``, pinned or not) and every
    Zenoh session this process opens, as it opens: nothing may be sent beyond loopback."""
    from can.interfaces.udp_multicast.bus import GeneralPurposeUdpMulticastBus

    from armid.drivers.multicast import socket_pinning

    if getattr(GeneralPurposeUdpMulticastBus.__init__, "_armid_tracked", False):
        return
    original_init = GeneralPurposeUdpMulticastBus.__init__

    def init(self: Any, *args: Any, **kwargs: Any) -> None:
        original_init(self, *args, **kwargs)
        interface, ttl = socket_pinning(self._socket)
        outside = joined_devices(self.group) - {"lo"}
        if interface != "127.0.0.1" or ttl != 0 or outside:
            _OFF_LOOPBACK.append(f"multicast {self.group}: sends on {interface} with TTL {ttl}, joined on {sorted(outside) or 'lo only'}")

    init._armid_tracked = True  # type: ignore[attr-defined]
    GeneralPurposeUdpMulticastBus.__init__ = init  # type: ignore[method-assign]


def zenoh_off_loopback(config: Any) -> list[str]:
    """What of a Zenoh configuration could send to another machine: multicast scouting on, an
    endpoint to connect to that is not on loopback, a listener on one other host. Zenoh's default
    listener (``tcp/[::]:0``, every interface, where no listen endpoint is given) sends nothing
    by itself: a peer that learns its addresses by gossip reaches this machine's own address,
    which the kernel delivers on loopback (test_loopback's capture sees none of it elsewhere)."""
    import json

    problems = []
    if json.loads(config.get_json("scouting/multicast/enabled")) is not False:
        problems.append("Zenoh multicast scouting is on")
    for side in ("listen", "connect"):
        endpoints = json.loads(config.get_json(f"{side}/endpoints")) or []
        if isinstance(endpoints, dict):  # per mode: {router: [...], peer: [...]}
            endpoints = [e for es in endpoints.values() for e in es]
        for endpoint in endpoints:
            host = endpoint.split("/", 1)[-1].split("#")[0].rsplit(":", 1)[0]
            wildcard = side == "listen" and host in ("[::]", "0.0.0.0")
            if not host.startswith(_LOOPBACK_HOSTS) and not endpoint.startswith("unixsock") and not wildcard:
                problems.append(f"Zenoh {side} endpoint {endpoint} is not on loopback")
    return problems


def _process_settings() -> dict[str, Any]:
    return {"sys.getswitchinterval()": sys.getswitchinterval(), "gc.get_freeze_count()": gc.get_freeze_count(),
            "SIGINT handler": signal.getsignal(signal.SIGINT), "SIGTERM handler": signal.getsignal(signal.SIGTERM),
            "scheduling policy": os.sched_getscheduler(0) if hasattr(os, "sched_getscheduler") else None}


@pytest.fixture(autouse=True)
def no_leaks() -> Iterator[None]:
    """Fail a test that leaves a bus open, a Zenoh session open, a thread running or a
    process-wide setting changed (python-can's and zenoh-python's test suites do the same), or
    that opens a multicast socket or a Zenoh session able to reach another machine."""
    _track_buses_and_sessions()
    _track_network()
    buses, sessions, off_loopback = set(map(id, _BUSES)), len(_SESSIONS), len(_OFF_LOOPBACK)
    threads = set(threading.enumerate())
    settings = _process_settings()
    yield
    problems = []
    for bus in list(_BUSES):
        if id(bus) not in buses and not getattr(bus, "_is_shutdown", True):
            problems.append(f"a python-can bus left open: {bus!r}")
            bus.shutdown()
    problems += [f"beyond loopback: {what}" for what in _OFF_LOOPBACK[off_loopback:]]
    for session in _SESSIONS[sessions:]:
        if not session.is_closed():
            problems.append("a Zenoh session left open")
            session.close()
    _SESSIONS[:] = [s for s in _SESSIONS if not s.is_closed()]
    deadline = time.monotonic() + _THREAD_GRACE_S
    for t in set(threading.enumerate()) - threads:
        if isinstance(t, threading._DummyThread) or t.name.startswith(_LONG_LIVED_THREADS):  # foreign (Rust) threads
            continue
        t.join(max(0.0, deadline - time.monotonic()))
        if t.is_alive():
            problems.append(f"a thread still running {_THREAD_GRACE_S:g} s after the test: {t.name}")
    after = _process_settings()
    for name, value in settings.items():
        if after[name] != value:
            problems.append(f"{name} changed: {value!r} -> {after[name]!r}")
    if after["sys.getswitchinterval()"] != settings["sys.getswitchinterval()"]:
        # put the process back, so that one leak does not fail every test after it
        from armid.drivers.interface import ProcessSettings

        sys.setswitchinterval(settings["sys.getswitchinterval()"])
        ProcessSettings._interval_holders = 0
    if after["gc.get_freeze_count()"] != settings["gc.get_freeze_count()"] and settings["gc.get_freeze_count()"] == 0:
        from armid.drivers.interface import ProcessSettings

        gc.unfreeze()
        ProcessSettings._freeze_holders, ProcessSettings._froze = 0, False
    if problems:
        pytest.fail("the test leaks:\n" + "\n".join(problems), pytrace=False)

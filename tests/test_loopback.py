"""Network traffic stays on this machine: every ``udp_multicast`` bus is pinned to loopback
(``IP_MULTICAST_IF`` 127.0.0.1, TTL 0, the group joined on ``lo`` only), and a cross-process
exchange (``armid sim`` and ``armid record`` on one group, the record streamed over Zenoh)
puts not one packet of it on any other interface: a packet capture (``AF_PACKET``) on every
interface says so. Every multicast socket and Zenoh session the tests open in their own
process is checked as it opens (``tests/conftest.py``)."""

from __future__ import annotations

import os
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import numpy as np
import pytest
import yaml
from conftest import joined_devices, zenoh_off_loopback

from armid.drivers.multicast import socket_pinning
from armid.drivers.rig import open_bus

ROOT = Path(__file__).resolve().parent.parent
SIM_RIG = ROOT / "config" / "rigs" / "sim.yaml"
ETH_P_ALL = 0x0003
UDP_MULTICAST_PORT = 43113  # python-can's default port


def _group() -> str:
    rng = np.random.default_rng()
    return f"239.74.{rng.integers(1, 250)}.{rng.integers(1, 250)}"


def test_a_udp_multicast_bus_sends_and_joins_on_loopback_only() -> None:
    group = _group()
    a, b = open_bus(interface="udp_multicast", channel=group), open_bus(interface="udp_multicast", channel=group)
    try:
        assert socket_pinning(a._multicast._socket) == ("127.0.0.1", 0)
        assert joined_devices(group) == {"lo"}
        a.send(can.Message(arbitration_id=0x80, data=[7], is_extended_id=False))
        got = b.recv(2.0)
        assert got is not None and got.arbitration_id == 0x80 and bytes(got.data) == b"\x07"
    finally:
        a.shutdown()
        b.shutdown()
    assert joined_devices(group) == set()


def test_two_rigs_on_one_machine_each_read_their_own_group_only() -> None:
    """Two ``udp_multicast`` buses on one port and two groups (two simulated arms on one
    machine, or two tests at once): each reads its own group's frames, not the other's (Linux
    hands a socket bound to the port every group joined on it unless ``IP_MULTICAST_ALL`` is off:
    one arm's boot-up was read by the other as a reset of its node 1)."""
    first, second = _group(), _group()
    while second == first:
        second = _group()
    a, b, a_too = (open_bus(interface="udp_multicast", channel=g) for g in (first, second, first))
    try:
        b.send(can.Message(arbitration_id=0x701, data=[0], is_extended_id=False))  # the other rig's boot-up
        a_too.send(can.Message(arbitration_id=0x702, data=[5], is_extended_id=False))  # this rig's own frame
        got = []
        while (m := a.recv(0.5)) is not None:
            got.append(m.arbitration_id)
        assert got == [0x702], [hex(i) for i in got]
    finally:
        for bus in (a, b, a_too):
            bus.shutdown()


def test_python_cans_own_bus_would_leave_the_machine() -> None:
    """What the pinning is for: python-can's ``udp_multicast`` as it comes sends on the kernel's
    default interface with a TTL of 1 and joins on every interface the kernel picks, and the
    check in conftest would refuse it (its socket is checked here and closed, nothing sent)."""
    import conftest
    from can.interfaces.udp_multicast.bus import GeneralPurposeUdpMulticastBus

    group = _group()
    before = len(conftest._OFF_LOOPBACK)
    plain = GeneralPurposeUdpMulticastBus(group, UDP_MULTICAST_PORT, 1)
    try:
        interface, ttl = socket_pinning(plain._socket)
        assert (interface, ttl) == ("0.0.0.0", 1)  # the kernel's choice: the default route's interface
    finally:
        plain._socket.close()
        said = conftest._OFF_LOOPBACK[before:]
        del conftest._OFF_LOOPBACK[before:]  # this test's socket is the refused example, not a leak
    assert said and "sends on 0.0.0.0 with TTL 1" in said[0]


def test_zenoh_configurations_of_the_tests_are_checked() -> None:
    from armid.daq.stream import session_config

    assert zenoh_off_loopback(session_config(["tcp/127.0.0.1:0"], ["tcp/127.0.0.1:7447"])) == []
    assert zenoh_off_loopback(session_config(connect=["tcp/192.0.2.1:7447"])) == ["Zenoh connect endpoint tcp/192.0.2.1:7447 is not on loopback"]


def _interfaces() -> list[str]:
    """Every network interface that is up, loopback included."""
    out = []
    for folder in sorted(Path("/sys/class/net").iterdir()):
        try:
            if int((folder / "flags").read_text(), 16) & 0x1:
                out.append(folder.name)
        except OSError:
            continue
    return out


def _capture_allowed() -> str | None:
    try:
        s = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ALL))
        s.close()
        return None
    except (OSError, AttributeError) as err:
        return f"a packet capture needs CAP_NET_RAW on Linux ({err})"


class _Capture:
    """Every frame of one interface while it runs: IPv4 packets that belong to the exchange
    (to the group, to the bus's port, IGMP naming the group, TCP to or from the Zenoh port)."""

    def __init__(self, interface: str, group: str, zenoh_port: int) -> None:
        self.interface, self.hits, self.frames = interface, [], 0
        self._group, self._port = socket.inet_aton(group), zenoh_port
        self._sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ALL))
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 * 1024 * 1024)
        self._sock.bind((interface, 0))
        self._sock.settimeout(0.1)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"capture-{interface}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                frame = self._sock.recv(65535)
            except TimeoutError:
                continue
            self.frames += 1
            if len(frame) < 34 or frame[12:14] != b"\x08\x00":  # Ethernet II, IPv4 (loopback has the same header)
                continue
            ip = frame[14:]
            proto, dst, body = ip[9], ip[16:20], ip[(ip[0] & 0x0F) * 4:]
            ports = struct.unpack("!HH", body[:4]) if len(body) >= 4 else (0, 0)
            if (dst == self._group or (proto == 17 and ports[1] == UDP_MULTICAST_PORT) or (proto == 2 and self._group in body)
                    or (proto == 6 and self._port in ports)):
                self.hits.append((proto, socket.inet_ntoa(dst), ports))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self._sock.close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.realtime
@pytest.mark.skipif(_capture_allowed() is not None, reason=str(_capture_allowed()))
def test_a_cross_process_bus_and_its_stream_stay_on_loopback(tmp_path: Path) -> None:
    """``armid sim`` and ``armid record`` in two processes on one ``udp_multicast`` group, the
    record on Zenoh's local endpoint: the capture on ``lo`` sees the group's datagrams and
    Zenoh's TCP, every other interface sees none of either (nor an IGMP report for the group)."""
    group, zport = _group(), _free_port()
    rig = tmp_path / "rig.yaml"
    doc = yaml.safe_load(SIM_RIG.read_text())
    doc["robot"] = str(SIM_RIG.parent / doc["robot"])
    doc["bus"].update(interface="udp_multicast", channel=group)
    doc["period_s"] = 0.004  # two processes on a shared machine
    rig.write_text(yaml.safe_dump(doc))
    env = {**os.environ, "PYTHONPATH": str(ROOT), "ARMID_ZENOH_LOCAL": f"tcp/127.0.0.1:{zport}"}
    captures = [_Capture(name, group, zport) for name in _interfaces()]
    ready = tmp_path / "ready"
    sim = subprocess.Popen([sys.executable, "-m", "armid.cli", "sim", "--rig", str(rig), "--ready", str(ready), "--duration", "60"],
                           cwd=ROOT, env=env, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not ready.exists() and sim.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert ready.exists(), f"the simulator did not come up (exit code {sim.poll()})"
        record = subprocess.run([sys.executable, "-m", "armid.cli", "record", "--rig", str(rig), "--out", str(tmp_path / "run"),
                                 "--duration", "2"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
        assert record.returncode == 0, record.stderr
    finally:
        sim.terminate()
        _, sim_err = sim.communicate(timeout=20)
        time.sleep(0.2)
        for c in captures:
            c.stop()
    on = {c.interface: c for c in captures}
    assert "SYNC periods simulated" in sim_err and "the first SYNC came" in sim_err, sim_err
    lo = on.pop("lo")
    assert any(h[1] == group for h in lo.hits), f"the capture on lo saw none of the group's {lo.frames} frames"
    assert any(h[0] == 6 for h in lo.hits), "the capture on lo saw no Zenoh TCP"
    for name, c in on.items():
        assert c.hits == [], f"{name}: {len(c.hits)} packets of the exchange left the machine: {c.hits[:5]}"

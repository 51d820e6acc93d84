"""First contact with hardware: a bus or a serial port that will not open is said on one line
naming the interface, the channel, the cause and what to do (exit 1, a runtime fault), by the
real kernel's answer on this machine (no AF_CAN here: the shipped bench template's can0), a
channel that does not exist, a device that is not a serial port, a pty the user may not open;
``armid excite --dry-run`` checks what needs no bus and says what it could not check; the
shipped bench template passes its own checks; ``armid sim`` says what it waits for."""

from __future__ import annotations

import errno
import os
import re
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from cli_runs import run

from armid.drivers.pdo_plan import MAX_LOAD, PLANS, bus_load, check_bus_budget
from armid.drivers.port_errors import ARPHRD_CAN, LinkState, link_state, socketcan_link_problem
from armid.drivers.rig import open_bus
from armid.io.rig_file import load_rig
from armid.schema.errors import BusBudgetError, BusOpenError

ROOT = Path(__file__).resolve().parent.parent
BENCH = ROOT / "config" / "rigs" / "bench_template.yaml"
DXL_RIG = ROOT / "config" / "rigs" / "sim_dynamixel.yaml"
SIM_RIG = ROOT / "config" / "rigs" / "sim.yaml"


def one_error_line(code: int, err: str) -> str:
    """The one ``error:`` line of a runtime fault (exit 1), no traceback."""
    assert "Traceback" not in err and "internal error" not in err, err
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert code == 1, f"exit {code}, stderr:\n{err}"
    assert len(lines) == 1 and ": error: " in lines[0], err
    return lines[0]


def _socketcan_here(channel: str) -> str:
    """What this kernel says of a SocketCAN ``channel``, as a pattern of the expected line."""
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except (OSError, AttributeError) as err:
        if getattr(err, "errno", None) == errno.EAFNOSUPPORT or isinstance(err, AttributeError):
            return rf"socketcan {channel}: SocketCAN is not available in this kernel \(no AF_CAN\)"
        raise
    state = link_state(channel)
    if not state.exists:
        return rf"socketcan {channel}: no such interface"
    return rf"socketcan {channel}( is down|: not a CAN interface)"


# -- CAN ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("command", ["record", "excite"])
def test_the_bench_template_on_this_machine_names_socketcan_can0_and_the_cause(command: str, tmp_path: Path,
                                                                                capsys: pytest.CaptureFixture[str]) -> None:
    if _socketcan_here("can0").startswith("socketcan can0(") and link_state("can0").up and link_state("can0").link_type == ARPHRD_CAN:
        pytest.skip("can0 is a CAN interface and up here: the bench template would talk to real drives")
    argv = [command, "--rig", str(BENCH), "--out", str(tmp_path / "out"), "--no-zenoh"] + (["--duration", "1"] if command == "record" else [])
    line = one_error_line(*run(argv, capsys))
    assert re.search(_socketcan_here("can0"), line), line
    assert "`" in line.split(": ", 3)[-1] or "ip " in line, f"no remedy in {line!r}"


@pytest.mark.slow
def test_excite_dry_run_on_the_bench_template_checks_all_but_the_bus(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The shipped template passes every check that needs no drive: its trajectory against every
    limit, its PDO plan within the bus budget; the bus itself is said, on one line, as not checked."""
    if link_state("can0").up and link_state("can0").link_type == ARPHRD_CAN:
        pytest.skip("can0 is a CAN interface and up here: the dry run would read the drives' pose")
    code, err = run(["excite", "--rig", str(BENCH), "--out", str(tmp_path / "out"), "--dry-run", "--periods", "1"], capsys)
    assert code == 0, err
    assert "Traceback" not in err and "error" not in err, err
    cause = [line for line in err.splitlines() if "not checked: " in line and "socketcan can0" in line]
    assert len(cause) == 1 and re.search(_socketcan_here("can0"), cause[0]), err
    done = [line for line in err.splitlines() if line.startswith("armid excite: dry run")]
    load = bus_load("alternate_velocity", 7, load_rig(BENCH).period_s, 1_000_000).load
    assert len(done) == 1 and "checked against every limit" in done[0] and f"{load:.1%}" in done[0], err
    assert done[0].endswith("not checked: the bus and the drives"), done[0]


def test_the_bench_template_fits_its_bus_budget() -> None:
    rig = load_rig(BENCH)
    load = check_bus_budget(rig.pdo_plan, rig.n_joints, rig.period_s, rig.bus.bitrate, rig.heartbeat_ms).load
    assert rig.n_joints == 7 and load <= MAX_LOAD


@pytest.mark.parametrize("plan", list(PLANS))
def test_a_refused_plan_is_never_offered_as_its_own_remedy(plan: str) -> None:
    """Every refusal over 1..12 axes, 1-4 ms and three bit rates: the plan in use is not among
    the options, every plan offered fits, and the shortest period offered fits this plan."""
    refused = 0
    for n in range(1, 13):
        for period_s in (0.001, 0.002, 0.0025, 0.004):
            for bitrate in (250_000, 500_000, 1_000_000):
                try:
                    check_bus_budget(plan, n, period_s, bitrate)
                    continue
                except BusBudgetError as err:
                    text = str(err)
                refused += 1
                options = text.split("Options: ", 1)[1].split(". Beyond the limit", 1)[0]
                assert f"pdo_plan: {plan} " not in options, text
                for other in re.findall(r"pdo_plan: (\w+)", options):
                    assert bus_load(other, n, period_s, bitrate).load <= MAX_LOAD, text
                shortest = float(re.search(r"period_s: ([0-9.e-]+)\)", options).group(1))
                assert shortest > period_s and bus_load(plan, n, shortest, bitrate).load <= MAX_LOAD, text
    assert refused > 10


def test_socketcan_links_as_the_kernel_shows_them() -> None:
    """``/sys/class/net`` read for real: a name no interface has, loopback (up, not CAN), and
    any interface that is down here; the words for a CAN interface that is down."""
    missing = link_state("armidnosuch0")
    assert not missing.exists
    assert "socketcan armidnosuch0: no such interface" in str(socketcan_link_problem(missing, 1_000_000))
    lo = link_state("lo")
    assert lo.exists and lo.up and not lo.is_can
    assert "socketcan lo: not a CAN interface (link type 772)" in str(socketcan_link_problem(lo, 1_000_000))
    down = [s for s in map(link_state, sorted(p.name for p in Path("/sys/class/net").iterdir())) if s.exists and not s.up]
    for state in down:
        assert state.link_type is not None and socketcan_link_problem(state, 500_000) is not None
    can_down = LinkState("can0", exists=True, up=False, link_type=ARPHRD_CAN)
    assert socketcan_link_problem(can_down, 500_000) == (
        "socketcan can0 is down: `sudo ip link set can0 up type can bitrate 500000` (the drives' bit rate)")
    assert socketcan_link_problem(LinkState("can0", exists=True, up=True, link_type=ARPHRD_CAN), 500_000) is None
    assert socketcan_link_problem(LinkState("can0", exists=True, up=True, link_type=ARPHRD_CAN, bitrate=500_000), 500_000) is None
    assert socketcan_link_problem(LinkState("can0", exists=True, up=True, link_type=ARPHRD_CAN, bitrate=250_000), 500_000) == (
        "socketcan can0 runs at 250000 bit/s, the rig's bus.bitrate is 500000: "
        "`sudo ip link set can0 down && sudo ip link set can0 up type can bitrate 500000` (the drives' bit rate)")


@pytest.mark.parametrize("interface", ["pcan", "slcan", "udp_multicast"])
def test_other_interfaces_name_themselves_the_channel_and_the_cause(interface: str) -> None:
    """Interfaces a rig may name, failing as they really do on this machine: PCAN's library not
    installed, an slcan adapter's serial port not there, a multicast interface not of this machine."""
    kwargs = {"pcan": {"channel": "PCAN_USBBUS1", "bitrate": 1_000_000},
              "slcan": {"channel": "/dev/armid-no-such-tty", "bitrate": 1_000_000},
              "udp_multicast": {"channel": "239.74.1.1", "multicast_interface": "192.0.2.1"}}[interface]
    try:
        bus = open_bus(interface=interface, **kwargs)
    except BusOpenError as err:
        text = str(err)
    else:
        bus.shutdown()
        pytest.skip(f"{interface} {kwargs['channel']} opened here")
    assert "\n" not in text and text.startswith(f"{interface} {kwargs['channel']}"), text
    expect = {"pcan": r"pcanbasic library not found: install the adapter vendor's driver",
              "slcan": r"slcan /dev/armid-no-such-tty: no such device \(is the adapter plugged in",
              "udp_multicast": r"Cannot assign requested address.*bus\.multicast_interface an address of this machine"}[interface]
    assert re.search(expect, text), text


# -- serial ports ------------------------------------------------------------------------------

def _serial_argv(port: str, out: Path) -> list[str]:
    return ["record", "--rig", str(DXL_RIG), "--channel", port, "--out", str(out), "--duration", "1", "--no-zenoh"]


@pytest.mark.parametrize(("port", "expect"), [
    ("/dev/armid-no-such-tty", r"/dev/armid-no-such-tty: no such device \(is the adapter plugged in\? `ls /dev/serial/by-id/`"),
    ("/dev/null", r"/dev/null: not a serial port \(.*Inappropriate ioctl for device\); name the adapter's device"),
])
def test_a_serial_port_that_will_not_open(port: str, expect: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    line = one_error_line(*run(_serial_argv(port, tmp_path / "out"), capsys))
    assert re.search(expect, line), line


def _unprivileged() -> str | None:
    if os.geteuid() != 0:
        return None
    if shutil.which("setpriv") is None:
        return "running as root, and no setpriv to open the port as another user"
    return "setpriv"


def _hidden_from_others(path: Path) -> Path | None:
    """The first folder on ``path``'s way that other users may not pass (no o+x), if any: a
    checkout made in ``mktemp -d`` (mode 700) is one that ``nobody`` cannot import armid from."""
    for folder in reversed([path, *path.parents] if path.is_dir() else list(path.parents)):
        if not folder.stat().st_mode & 0o001:
            return folder
    return None


@pytest.mark.skipif(sys.platform != "linux", reason="a pty with Linux's permissions")
@pytest.mark.parametrize(("case", "expect"), [
    ("only root may open it", "permission denied on {port}: add the user to the dialout group (`sudo usermod -aG dialout $USER`"),
    ("another process holds it (TIOCEXCL)", "{port} is busy: another process holds it (`fuser -v {port}` names it)"),
])
def test_a_serial_port_the_user_may_not_open(case: str, expect: str) -> None:
    """A real pty opened by an unprivileged user (this test's user, or ``nobody`` through
    ``setpriv`` when the tests run as root): a slave only root may open (the kernel says EACCES),
    or one this process holds exclusively, as a running program holds its port (EBUSY)."""
    import fcntl
    import tempfile
    import termios

    master, slave = os.openpty()
    name = os.ttyname(slave)
    out = Path(tempfile.mkdtemp(prefix="armid-port-"))  # under /tmp: pytest's own folder is its user's only
    try:
        if case.startswith("only root"):
            os.chmod(name, 0o600)
        else:
            os.chmod(name, 0o666)
            fcntl.ioctl(slave, termios.TIOCEXCL)
        os.chmod(out, 0o777)
        argv = [sys.executable, "-m", "armid.cli", *_serial_argv(name, out / "run")]
        how = _unprivileged()
        if how is None:
            if case.startswith("only root") and os.stat(name).st_uid == os.geteuid():
                pytest.skip("this user owns its ptys: no port it may not open")
        else:
            unreachable = _hidden_from_others(ROOT) or _hidden_from_others(Path(sys.executable))
            if unreachable:
                pytest.skip(f"{unreachable} lets no other user in (mode {unreachable.stat().st_mode & 0o777:o}): "
                            "nobody could not run armid from this checkout")
            argv = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", *argv]
        env = {**os.environ, "PYTHONPATH": str(ROOT), "HOME": str(out), "NUMBA_CACHE_DIR": str(out / "numba")}
        done = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    finally:
        os.close(slave)
        os.close(master)
        shutil.rmtree(out, ignore_errors=True)
    lines = [line for line in done.stderr.strip().splitlines() if line.strip()]
    assert done.returncode == 1 and len(lines) == 1, done.stderr
    assert expect.format(port=name) in lines[0], lines[0]


# -- armid sim -----------------------------------------------------------------------------------

def test_sim_says_what_it_waits_for_and_that_nothing_came(tmp_path: Path) -> None:
    """On the shipped sim rig (python-can's virtual bus, which no other process reaches) nothing
    can come: it says what it waits for, on which bus, how long it waited, and why none came."""
    done = subprocess.run([sys.executable, "-m", "armid.cli", "sim", "--rig", str(SIM_RIG), "--duration", "1"], cwd=ROOT,
                          env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "waiting for a master's SYNC (COB-ID 0x080) on virtual:armid-sim" in done.stderr, done.stderr
    last = done.stderr.strip().splitlines()[-1]
    waited = re.search(r"no SYNC came on virtual:armid-sim in ([0-9.]+) s of waiting: 0 SYNC periods simulated", last)
    assert waited and 1.0 <= float(waited.group(1)) < 30, last
    assert "virtual bus stays inside this process" in last and "--interface udp_multicast" in last, last


def test_the_rig_file_checks_the_multicast_interface(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    doc = yaml.safe_load(SIM_RIG.read_text())
    doc["robot"] = str(SIM_RIG.parent / doc["robot"])
    doc["bus"].update(interface="udp_multicast", channel="239.74.1.2", multicast_interface="eth0")
    rig = tmp_path / "rig.yaml"
    rig.write_text(yaml.safe_dump(doc))
    code, err = run(["sim", "--rig", str(rig), "--duration", "0.5"], capsys)
    assert code == 2 and "bus.multicast_interface: must be an IPv4 address of this machine's interface" in err, err

"""A lab of many arms on one Zenoh router (config/zenoh/router.json5, config/zenoh/arm.json5)
really holds, on loopback: the shipped files opened with only the endpoints, the credentials
file and the user names changed; multicast scouting off.

The stations are the router's clients, opened as armid opens sessions (daq.stream.session_config
keeps the file's client mode). Arm cell1's session puts on its own joint_state and on cell2's;
cell2's on its own. The fleet's station, subscribed to ``armid/**``, receives both arms' own
records and none of cell1's under cell2's keys; the station's estimate reaches the arm. A
session whose password is wrong, or that gives none, does not reach the router.
"""

from __future__ import annotations

import json
import socket
import time
from pathlib import Path
from typing import Any

import pytest

from armid.daq.stream import session_config

ROOT = Path(__file__).resolve().parent.parent
ROUTER, ARM = ROOT / "config" / "zenoh" / "router.json5", ROOT / "config" / "zenoh" / "arm.json5"
PASSWORDS = {"cell1": "pw-cell1", "cell2": "pw-cell2", "station": "pw-station"}

zenoh = pytest.importorskip("zenoh")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _router(endpoint: str, credentials: Path) -> Any:
    config = zenoh.Config.from_file(str(ROUTER))
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    config.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(credentials)))
    return zenoh.open(config)


def _station(endpoint: str, user: str, password: str | None) -> Any:
    """A session as armid opens one (daq.stream.session_config) on the shipped arm file: a client."""
    config = session_config(None, [endpoint], str(ARM))
    if password is None:
        config.insert_json5("transport/auth/usrpwd", json.dumps({"user": None, "password": None}))
    else:
        config.insert_json5("transport/auth/usrpwd", json.dumps({"user": user, "password": password}))
    return zenoh.open(config)


def _wait(condition: Any, seconds: float = 5.0) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.05)
    return bool(condition())


@pytest.fixture
def credentials(tmp_path: Path) -> Path:
    path = tmp_path / "credentials.txt"
    path.write_text("".join(f"{user}:{password}\n" for user, password in PASSWORDS.items()))
    return path


def test_an_arm_cannot_publish_under_another_arms_keys(credentials: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    router = _router(endpoint, credentials)
    sessions: list[Any] = []
    try:
        station, cell1, cell2 = (_station(endpoint, u, PASSWORDS[u]) for u in ("station", "cell1", "cell2"))
        sessions += [station, cell1, cell2]
        assert all(list(x.info.routers_zid()) == [router.info.zid()] for x in sessions), "the three stations are the router's clients"
        got: list[tuple[str, bytes]] = []
        at_cell1: list[bytes] = []
        station.declare_subscriber("armid/**", lambda s: got.append((str(s.key_expr), bytes(s.payload.to_bytes()))))
        cell1.declare_subscriber("armid/cell1/estimate/**", lambda s: at_cell1.append(bytes(s.payload.to_bytes())))
        time.sleep(0.5)  # declarations travel
        for k in range(20):
            cell1.put("armid/cell1/joint_state", f"cell1 own {k}")
            cell1.put("armid/cell2/joint_state", f"cell1 as cell2 {k}")
            cell2.put("armid/cell2/joint_state", f"cell2 own {k}")
            station.put("armid/cell1/estimate/parameters", f"station estimate {k}")
            time.sleep(0.01)
        assert _wait(lambda: sum(p.startswith(b"cell1 own") for _, p in got) == 20 and sum(p.startswith(b"cell2 own") for _, p in got) == 20), \
            f"each arm's own records reach the station: {len(got)} received"
        assert _wait(lambda: len(at_cell1) == 20), "the station's estimate reaches the arm"
        time.sleep(0.3)
        forged = [(key, p) for key, p in got if p.startswith(b"cell1 as cell2")]
        print(f"\nat the station: {sum(p.startswith(b'cell1 own') for _, p in got)} of cell1's own, "
              f"{sum(p.startswith(b'cell2 own') for _, p in got)} of cell2's own, {len(forged)} of cell1's under cell2's keys")
        assert forged == [], f"arm cell1 published {len(forged)} records under armid/cell2/**"
        assert {key for key, _ in got} == {"armid/cell1/joint_state", "armid/cell2/joint_state", "armid/cell1/estimate/parameters"}
    finally:
        for session in reversed(sessions):
            session.close()
        router.close()


@pytest.mark.parametrize("password", ["wrong", None], ids=["wrong-password", "no-credentials"])
def test_a_session_without_the_right_password_cannot_connect(credentials: Path, password: str | None) -> None:
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    router = _router(endpoint, credentials)
    intruder = None
    try:
        try:
            intruder = _station(endpoint, "cell1", password)
        except Exception:  # a client whose router refuses it fails to open: that is the refusal
            intruder = None
        if intruder is not None:
            time.sleep(1.0)
            assert list(intruder.info.routers_zid()) == [], "a session without the right password reached the router"
        good = _station(endpoint, "cell1", PASSWORDS["cell1"])  # the same endpoint takes the right password
        try:
            assert list(good.info.routers_zid()) == [router.info.zid()]
        finally:
            good.close()
    finally:
        if intruder is not None:
            intruder.close()
        router.close()

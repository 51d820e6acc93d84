"""The lab's Zenoh configuration (config/zenoh/lab.json5) really holds, on loopback.

A test CA, the operator's and a viewer's certificates are generated here (``cryptography``),
and peers open the shipped file itself with only the certificate paths and endpoints
changed: TLS with client certificates, multicast scouting off. The operator's station
refuses the viewer's ``put`` on ``joint_state`` and on a command key, refuses its queryable
and liveliness token, and serves its subscription and its query. A second station with the
operator's certificate shows that a ``put`` that the policy allows does arrive, and a peer
whose certificate another CA signed cannot connect at all.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import socket
import time
from pathlib import Path
from typing import Any

import pytest

from armid.cli import main
from armid.daq.stream import session_config

ROOT = Path(__file__).resolve().parent.parent
LAB = ROOT / "config" / "zenoh" / "lab.json5"
OPERATOR, VIEWER = "operator.lab.local", "viewer.lab.local"

zenoh = pytest.importorskip("zenoh")
x509 = pytest.importorskip("cryptography.x509")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _name(cn: str) -> Any:
    from cryptography.x509.oid import NameOID

    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _key_pem(key: Any) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())


def _ca(folder: Path, label: str) -> tuple[Any, Any]:
    """A self-signed CA: (certificate, key), its PEM written to folder/<label>.pem."""
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    now = datetime.datetime.now(datetime.UTC)
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (x509.CertificateBuilder().subject_name(_name(label)).issuer_name(_name(label)).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=1))
            .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
                                         key_encipherment=False, data_encipherment=False, key_agreement=False,
                                         encipher_only=False, decipher_only=False), critical=True)
            .sign(key, hashes.SHA256()))
    (folder / f"{label}.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    return cert, key


def _station(folder: Path, ca: tuple[Any, Any], cn: str, label: str) -> None:
    """A station's certificate (common name ``cn``, valid for 127.0.0.1) and key: folder/<label>.pem/.key."""
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID

    now = datetime.datetime.now(datetime.UTC)
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (x509.CertificateBuilder().subject_name(_name(cn)).issuer_name(ca[0].subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=1))
            .add_extension(x509.SubjectAlternativeName([x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
                           critical=False)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .sign(ca[1], hashes.SHA256()))
    (folder / f"{label}.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    (folder / f"{label}.key").write_bytes(_key_pem(key))


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("pki")
    lab_ca = _ca(folder, "ca")
    _station(folder, lab_ca, OPERATOR, "operator")
    _station(folder, lab_ca, VIEWER, "viewer")
    _station(folder, _ca(folder, "rogue-ca"), OPERATOR, "rogue")  # the operator's name, signed by someone else
    return folder


def _open(pki: Path, label: str, listen: list[str], connect: list[str]) -> Any:
    """A peer on the shipped lab file, with this station's certificate and the test's endpoints."""
    config = session_config(listen, connect, str(LAB))
    for field in ("listen_private_key", "connect_private_key"):
        config.insert_json5(f"transport/link/tls/{field}", json.dumps(str(pki / f"{label}.key")))
    for field in ("listen_certificate", "connect_certificate"):
        config.insert_json5(f"transport/link/tls/{field}", json.dumps(str(pki / f"{label}.pem")))
    config.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(pki / "ca.pem")))
    return zenoh.open(config)


def _wait(condition: Any, seconds: float = 5.0) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.05)
    return bool(condition())


def _ask(session: Any, key: str) -> list[bytes]:
    """Every reply from every queryable (no consolidation, all targets), sorted."""
    replies = session.get(key, timeout=3.0, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE)
    return sorted(bytes(r.ok.payload.to_bytes()) for r in replies if r.ok is not None)


def test_viewer_may_subscribe_and_query_but_not_publish(pki: Path) -> None:
    endpoint = f"tls/127.0.0.1:{_free_port()}"
    robot = "aclbot"
    state, command = f"armid/{robot}/joint_state", f"armid/{robot}/command/start"
    at_operator: list[tuple[str, bytes]] = []
    at_viewer: list[bytes] = []
    operator = _open(pki, "operator", [endpoint], [])
    viewer = second = None
    try:
        for key in (state, command):
            operator.declare_subscriber(key, lambda s: at_operator.append((str(s.key_expr), bytes(s.payload.to_bytes()))))
        operator.declare_queryable(f"armid/{robot}/status", lambda q: q.reply(f"armid/{robot}/status", "operator status"))
        viewer = _open(pki, "viewer", [], [endpoint])
        second = _open(pki, "operator", [], [endpoint])  # another station holding the operator's certificate
        assert _wait(lambda: len(list(operator.info.peers_zid())) == 2), "both stations connect over TLS"
        viewer.declare_subscriber(state, lambda s: at_viewer.append(bytes(s.payload.to_bytes())))
        time.sleep(0.5)  # declarations travel
        # the viewer's query is answered by the operator
        assert _ask(viewer, f"armid/{robot}/status") == [b"operator status"]
        # ... but its own queryable answers no one else, and its liveliness token reaches no one
        fake_status = viewer.declare_queryable(f"armid/{robot}/status", lambda q: q.reply(f"armid/{robot}/status", "forged status"))
        viewer.liveliness().declare_token(f"armid/{robot}/alive/recorder")
        time.sleep(0.5)
        assert _ask(viewer, f"armid/{robot}/status") == [b"forged status", b"operator status"]  # its own, locally
        assert _ask(operator, f"armid/{robot}/status") == [b"operator status"]
        alive = [str(r.ok.key_expr) for r in operator.liveliness().get(f"armid/{robot}/alive/**", timeout=2.0) if r.ok is not None]
        assert alive == [], f"the viewer's liveliness token reached the operator: {alive}"
        fake_status.undeclare()
        for k in range(20):
            operator.put(state, f"operator {k}")
            viewer.put(state, f"viewer {k}")
            viewer.put(command, f"viewer command {k}")
            second.put(state, f"second {k}")
            time.sleep(0.01)
        # the viewer's subscription is served, and a put from the operator's certificate arrives
        assert _wait(lambda: sum(p.startswith(b"operator") for p in at_viewer) == 20), at_viewer[:5]
        assert _wait(lambda: sum(p.startswith(b"second") for _, p in at_operator) == 20), at_operator[:5]
        time.sleep(0.3)
        # ... while every put of the viewer's was refused by the operator's station
        from_viewer = [(k, p) for k, p in at_operator if p.startswith(b"viewer")]
        assert from_viewer == [], f"the viewer published {len(from_viewer)} records, e.g. {from_viewer[:2]}"
    finally:
        for session in (second, viewer, operator):
            if session is not None:
                session.close()


def test_certificate_from_another_ca_cannot_connect(pki: Path) -> None:
    endpoint = f"tls/127.0.0.1:{_free_port()}"
    operator = _open(pki, "operator", [endpoint], [])
    rogue = None
    try:
        got: list[bytes] = []
        operator.declare_subscriber("armid/aclbot/joint_state", lambda s: got.append(bytes(s.payload.to_bytes())))
        try:
            rogue = _open(pki, "rogue", [], [endpoint])
        except Exception:  # zenoh may refuse to open a session whose only endpoint fails
            rogue = None
        if rogue is not None:
            for k in range(5):
                rogue.put("armid/aclbot/joint_state", f"rogue {k}")
        time.sleep(1.0)
        assert list(operator.info.peers_zid()) == [] and got == []
    finally:
        if rogue is not None:
            rogue.close()
        operator.close()


def test_lab_file_without_its_certificates_is_one_clear_error(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["watch", "--robot", "puma560", "--duration", "0.1", "--zenoh-config", str(LAB)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err
    assert "lab.json5: transport.link.tls." in err and "no such file /etc/armid/tls/" in err

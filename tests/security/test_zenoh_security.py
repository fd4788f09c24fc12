"""Zenoh TLS and user/password authentication configured from the mission's ``zenoh`` section
(``missions.format.schema.ZenohSpec`` → ``comms.session``), on 127.0.0.1 with certificates made by
the test (tests/security/certs.py).

Two legitimate nodes (A listens, B connects, both built from the mission's settings) exchange
records; an attacker on the same endpoint — without a client certificate, with a certificate
of another CA, in plain TCP, without credentials, with a wrong password — can neither read
(its subscriber gets nothing while the legitimate records flow) nor publish (A never receives
its records), and has no zenoh peer at all. The legitimate traffic is the reference that
shows the window was long enough to see a leak.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import pytest

from comms.messages import Record, encode
from comms.session import SessionSettings, open_session, zenoh_config
from missions.format.schema import ZenohAuth, ZenohSpec, ZenohTls
from comms.errors import UsageError

from tests.security.certs import Authority, Node
from tests.support.net import free_port
from tests.support.zenoh import raw_session
from tests.support.wait import wait_for


pytestmark = pytest.mark.integration

MISSION = "sec"
KEY = f"fimnav/{MISSION}/record"


def record(sender: int, x: float) -> bytes:
    return encode(Record(sender, 1, 0.1, (x, 0.0, 10.0), True, False, True, 5.0, math.nan, math.nan), MISSION, 1)


def secret(path: Path, text: str) -> Path:
    path.write_text(text)
    path.chmod(0o600)
    return path


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    d = tmp_path_factory.mktemp("pki")
    ca = Authority(d / "ca", "swarm-ca")
    rogue = Authority(d / "rogue", "rogue-ca")
    return {"ca": ca, "a": ca.issue("node-a"), "b": ca.issue("node-b"), "rogue": rogue.issue("intruder")}


def check_isolated(spec: ZenohSpec, attacker: Any, port: int) -> None:
    """Legit A (listening on ``port``) and B exchange records; ``attacker`` (already opened,
    connecting to ``port``) gets none and gets none of its own in."""
    a = open_session(SessionSettings.from_mission(spec, listen=[f"tcp/127.0.0.1:{port}"]))
    b = open_session(SessionSettings.from_mission(spec, connect=[f"tcp/127.0.0.1:{port}"], listen=[]))
    got_a: list[bytes] = []
    heard_x: list[bytes] = []
    subs = [a.declare_subscriber(f"{KEY}/*", lambda s: got_a.append(bytes(s.payload.to_bytes()))),
            attacker.declare_subscriber("fimnav/**", lambda s: heard_x.append(bytes(s.payload.to_bytes())))]
    try:
        legit, evil = record(2, 1.0), record(2, 666.0)
        # B reaches A through the secured link
        wait_for(lambda: b.put(f"{KEY}/2", legit) or legit in got_a, 20.0, "the legitimate nodes to connect",
                 interval_s=0.05)
        n0 = len(got_a)
        window = time.monotonic() + 1.0  # the attacker has the same second to get in and out
        while time.monotonic() < window:
            b.put(f"{KEY}/2", legit)
            attacker.put(f"{KEY}/2", evil)
            time.sleep(0.05)
        assert len(got_a) - n0 >= 10, "legitimate records stopped flowing"
        assert evil not in got_a, "the attacker's record reached a legitimate node"
        foreign = [x for x in heard_x if x != evil]  # (its own puts come back to its own subscriber)
        assert foreign == [], f"the attacker read {len(foreign)} records"
        assert evil in heard_x  # the attacker's session works: it is the link that refuses it
        assert list(attacker.info.peers_zid()) == [], "the attacker has a zenoh peer"
    finally:
        for s in subs:
            s.undeclare()
        b.close()
        a.close()


def tls_spec(pki: dict[str, Any], node: Node) -> ZenohSpec:
    return ZenohSpec(tls=ZenohTls(root_ca_certificate=pki["ca"].certificate, certificate=node.certificate, private_key=node.private_key))


@pytest.mark.parametrize("attack", ["plain_tcp", "tls_without_client_certificate", pytest.param("certificate_of_another_ca", marks=pytest.mark.slow)])
def test_mutual_tls_keeps_out_a_peer_without_a_valid_certificate(pki: dict[str, Any], attack: str) -> None:
    port = free_port()
    ca = str(pki["ca"].certificate)
    rogue: Node = pki["rogue"]
    if attack == "plain_tcp":
        attacker = raw_session(connect=[f"tcp/127.0.0.1:{port}"])
    elif attack == "tls_without_client_certificate":
        attacker = raw_session(connect=[f"tls/127.0.0.1:{port}"], tls={"root_ca_certificate": ca})
    else:
        attacker = raw_session(connect=[f"tls/127.0.0.1:{port}"], tls={
            "root_ca_certificate": ca, "enable_mtls": True,
            "connect_certificate": str(rogue.certificate), "connect_private_key": str(rogue.private_key)})
    try:
        # A and B share one mission spec here, each with its own certificate in practice:
        check_isolated(tls_spec(pki, pki["a"]), attacker, port)
    finally:
        attacker.close()


@pytest.fixture
def password_file(tmp_path: Path) -> Path:
    return secret(tmp_path / "zenoh.password", "correct horse battery staple\n")


@pytest.mark.parametrize("attack", ["no_credentials", "wrong_password", pytest.param("wrong_user", marks=pytest.mark.slow)])
def test_user_password_keeps_out_a_peer_without_the_credentials(password_file: Path, attack: str) -> None:
    port = free_port()
    spec = ZenohSpec(auth=ZenohAuth(user="swarm", password_file=password_file))
    creds = {"no_credentials": None, "wrong_password": {"user": "swarm", "password": "correct horse"},
             "wrong_user": {"user": "intruder", "password": "correct horse battery staple"}}[attack]
    attacker = raw_session(connect=[f"tcp/127.0.0.1:{port}"], auth=creds)
    try:
        check_isolated(spec, attacker, port)
    finally:
        attacker.close()


def test_tls_and_password_together(pki: dict[str, Any], password_file: Path) -> None:
    port = free_port()
    spec = ZenohSpec(tls=tls_spec(pki, pki["b"]).tls, auth=ZenohAuth(user="swarm", password_file=password_file))
    # the attacker even holds a valid certificate (a stolen node key), but not the password
    b: Node = pki["b"]
    attacker = raw_session(connect=[f"tls/127.0.0.1:{port}"], tls={
        "root_ca_certificate": str(pki["ca"].certificate), "enable_mtls": True,
        "connect_certificate": str(b.certificate), "connect_private_key": str(b.private_key)})
    try:
        check_isolated(spec, attacker, port)
    finally:
        attacker.close()


def test_the_swarm_dictionary_is_private_and_removed(password_file: Path, tmp_path: Path) -> None:
    """The ``user:password`` file zenoh checks peers against exists only while the session
    opens (0600, its own directory): nothing is left in the temp directory afterwards."""
    import tempfile

    before = {p.name for p in Path(tempfile.gettempdir()).glob("fimnav-zenoh-*")}
    s = open_session(SessionSettings.from_mission(ZenohSpec(auth=ZenohAuth(user="swarm", password_file=password_file))))
    try:
        after = {p.name for p in Path(tempfile.gettempdir()).glob("fimnav-zenoh-*")}
        assert after == before
    finally:
        s.close()


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604])
def test_readable_password_file_is_refused(tmp_path: Path, mode: int) -> None:
    pw = secret(tmp_path / "pw", "hunter2-secret\n")
    pw.chmod(mode)
    with pytest.raises(UsageError, match="permissions") as err:
        open_session(SessionSettings.from_mission(ZenohSpec(auth=ZenohAuth(user="swarm", password_file=pw))))
    assert "hunter2" not in str(err.value) and str(pw) in str(err.value) and "chmod 600" in str(err.value)


def test_readable_tls_private_key_is_refused(pki: dict[str, Any], tmp_path: Path) -> None:
    node: Node = pki["a"]
    key = tmp_path / "open.key"
    key.write_bytes(node.private_key.read_bytes())
    key.chmod(0o644)
    spec = ZenohSpec(tls=ZenohTls(root_ca_certificate=pki["ca"].certificate, certificate=node.certificate, private_key=key))
    with pytest.raises(UsageError, match="private key.*permissions"):
        zenoh_config(SessionSettings.from_mission(spec))


@pytest.mark.parametrize("endpoint", ["udp/127.0.0.1:7447", "ws/127.0.0.1:7447", "127.0.0.1:7447"])
def test_tls_refuses_an_endpoint_that_would_bypass_it(pki: dict[str, Any], endpoint: str) -> None:
    spec = tls_spec(pki, pki["a"])
    with pytest.raises(UsageError, match="endpoint"):
        zenoh_config(SessionSettings.from_mission(spec, listen=[endpoint]))


def test_child_process_settings_carry_paths_not_secrets(password_file: Path, pki: dict[str, Any]) -> None:
    """What the launcher puts on a child's command line names the files, never their content."""
    spec = ZenohSpec(tls=tls_spec(pki, pki["a"]).tls, auth=ZenohAuth(user="swarm", password_file=password_file))
    settings = SessionSettings.from_mission(spec)
    cli = " ".join(settings.to_cli())
    assert "correct horse" not in cli and "PRIVATE KEY" not in cli
    assert SessionSettings.from_json(settings.to_json()) == settings


def test_without_tls_nor_auth_the_config_has_neither() -> None:
    """The reference for the checks above: the default session has no TLS and no auth keys."""
    cfg = json.loads(str(zenoh_config(SessionSettings())))  # zenoh.Config prints as JSON
    assert cfg["transport"]["auth"]["usrpwd"] == {"user": None, "password": None, "dictionary_file": None}
    assert cfg["transport"]["link"]["tls"]["root_ca_certificate"] is None


def test_mission_tls_and_auth_reach_the_zenoh_config(pki: dict[str, Any], password_file: Path) -> None:
    """The zenoh keys (transport/link/tls/..., transport/auth/usrpwd/...) carry the mission's
    files; endpoints are TLS; the password is in the config only (not in the settings)."""
    node: Node = pki["a"]
    spec = ZenohSpec(listen=("tcp/127.0.0.1:0",), connect=("tls/127.0.0.1:7447",), tls=tls_spec(pki, node).tls,
                     auth=ZenohAuth(user="swarm", password_file=password_file))
    cfg = json.loads(str(zenoh_config(SessionSettings.from_mission(spec), Path("/dev/null"))))
    tls = cfg["transport"]["link"]["tls"]
    assert tls["root_ca_certificate"] == str(pki["ca"].certificate) and tls["enable_mtls"] is True
    assert tls["listen_certificate"] == tls["connect_certificate"] == str(node.certificate)
    assert tls["listen_private_key"] == tls["connect_private_key"] == str(node.private_key)
    assert cfg["listen"]["endpoints"] == ["tls/127.0.0.1:0"] and cfg["connect"]["endpoints"] == ["tls/127.0.0.1:7447"]
    assert cfg["transport"]["auth"]["usrpwd"]["user"] == "swarm"
    assert cfg["transport"]["auth"]["usrpwd"]["password"] == "correct horse battery staple"

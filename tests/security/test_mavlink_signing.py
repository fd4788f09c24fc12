"""MAVLink 2 signing against a real ``fimnav vehicle`` process on 127.0.0.1, and the signing
key handled as a secret (issue 7, security).

* unsigned and wrongly-signed commands are refused (no ACK, no state change), correctly signed
  ones accepted, and everything the vehicle sends is signed;
* a replayed signed frame is refused (MAVLink 2 timestamps);
* the key file must not be readable by group or others (refused with a clear error);
* the key never appears in the vehicle's output (DEBUG logging) nor in its .tlog, in raw or
  hex form, even when a ground station provisions it with SETUP_SIGNING.
"""

from __future__ import annotations

import signal
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from pymavlink import mavutil

from tests.support.proc import Proc, fimnav

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
R = mavutil.mavlink
KEY = bytes.fromhex("5ec7e75ec7e70123456789abcdef0011223344556677889900aabbccddeeff42")
WRONG = bytes(32)


def key_file(tmp_path: Path, key: bytes = KEY, mode: int = 0o600, hex_text: bool = False) -> Path:
    path = tmp_path / ("key.hex" if hex_text else "key.bin")
    path.write_bytes(key.hex().encode() + b"\n" if hex_text else key)
    path.chmod(mode)
    return path


def client(port: int, source_system: int, key: bytes | None = None) -> Any:
    c = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=source_system, source_component=190, dialect="ardupilotmega")
    if key is not None:
        c.setup_signing(key, sign_outgoing=True)
    return c


def recv(c: Any, pred: Any, timeout_s: float) -> Any | None:
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        m = c.recv_match(blocking=True, timeout=min(left, 0.2))
        if m is not None and pred(m):
            return m
    return None


def mode_of(c: Any) -> int:
    """custom_mode of the vehicle's next (signed) heartbeat."""
    c.mav.heartbeat_send(6, 8, 0, 0, 0)
    hb = recv(c, lambda m: m.get_type() == "HEARTBEAT" and m.get_srcSystem() == 1, 5)
    assert hb is not None and hb.get_signed()
    return int(hb.custom_mode)


@pytest.fixture
def signed_vehicle(tmp_path: Path) -> Iterator[tuple[Proc, int, Path]]:
    tlog = tmp_path / "vehicle.tlog"
    proc = Proc(fimnav("vehicle", "--sysid", "1", "--mavlink", "udpin:127.0.0.1:0", "--signing-key", str(key_file(tmp_path)),
                        "--tlog", str(tlog), "--log-level", "DEBUG", "--speedup", "1"), cwd=ROOT)
    try:
        ready = proc.ready()
        port = int(ready["vehicles"][0]["mavlink"].rsplit(":", 1)[1])
        yield proc, port, tlog
    finally:
        proc.stop(signal.SIGINT, grace_s=20.0)


def test_unsigned_and_wrongly_signed_commands_are_refused(signed_vehicle: tuple[Proc, int, Path]) -> None:
    proc, port, tlog = signed_vehicle
    good = client(port, 250, KEY)
    unsigned = client(port, 251)
    wrong = client(port, 252, WRONG)
    try:
        assert mode_of(good) == 0  # STABILIZE
        for bad in (unsigned, wrong):
            bad.mav.heartbeat_send(6, 8, 0, 0, 0)
            bad.mav.command_long_send(1, 1, R.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0)
            bad.mav.set_mode_send(1, 1, 4)
            assert recv(bad, lambda m: m.get_type() == "COMMAND_ACK", 1.0) is None
        assert mode_of(good) == 0
        # the independent reference: the same command, correctly signed, is accepted
        good.mav.command_long_send(1, 1, R.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0)
        ack = recv(good, lambda m: m.get_type() == "COMMAND_ACK" and m.command == R.MAV_CMD_DO_SET_MODE, 5)
        assert ack is not None and ack.result == R.MAV_RESULT_ACCEPTED and ack.get_signed()
        assert mode_of(good) == 4
        # what the vehicle sends to a peer without the key is signed too (that peer cannot
        # verify it: the frame's incompat flags say "signed" and it carries the 13-byte block)
        hb = recv(unsigned, lambda m: m.get_type() == "HEARTBEAT" and m.get_srcSystem() == 1, 5)
        assert hb is not None and hb.get_msgbuf()[2] & R.MAVLINK_IFLAG_SIGNED
    finally:
        for c in (good, unsigned, wrong):
            c.close()


def _signed_frame(key: bytes, sysid: int, build: Any) -> bytes:
    enc = mavutil.mavlink.MAVLink(None, srcSystem=sysid, srcComponent=190)
    enc.signing.secret_key = key
    enc.signing.sign_outgoing = True
    enc.signing.link_id = 0
    enc.signing.timestamp = int((time.time() - 1420070400) * 100_000)
    return bytes(build(enc).pack(enc))


def _after_this_signing_tick() -> None:
    """Return once the signing clock (10 µs units) has moved on (microseconds of spinning)."""
    start = int(time.time() * 100_000)
    while int(time.time() * 100_000) <= start:
        pass


def test_replayed_signed_frame_on_the_same_stream_is_refused(signed_vehicle: tuple[Proc, int, Path]) -> None:
    proc, port, _ = signed_vehicle
    # signed before the client's own stream starts: the client's later frames are newer
    loiter = _signed_frame(KEY, 250, lambda e: e.command_long_encode(1, 1, R.MAV_CMD_DO_SET_MODE, 0, 1, 5, 0, 0, 0, 0, 0))
    _after_this_signing_tick()
    good = client(port, 250, KEY)
    try:
        good.port.sendto(loiter, ("127.0.0.1", port))
        assert recv(good, lambda m: m.get_type() == "COMMAND_ACK" and m.result == 0, 5) is not None
        assert mode_of(good) == 5
        good.mav.command_long_send(1, 1, R.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0)
        assert recv(good, lambda m: m.get_type() == "COMMAND_ACK" and m.result == 0, 5) is not None
        assert mode_of(good) == 4
        good.port.sendto(loiter, ("127.0.0.1", port))  # replay, same UDP stream
        assert recv(good, lambda m: m.get_type() == "COMMAND_ACK", 1.5) is None
        assert mode_of(good) == 4
    finally:
        good.close()


def test_replayed_signed_frame_from_another_port_is_refused(signed_vehicle: tuple[Proc, int, Path]) -> None:
    proc, port, _ = signed_vehicle
    loiter = _signed_frame(KEY, 250, lambda e: e.command_long_encode(1, 1, R.MAV_CMD_DO_SET_MODE, 0, 1, 5, 0, 0, 0, 0, 0))
    _after_this_signing_tick()
    good = client(port, 250, KEY)
    attacker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        good.port.sendto(loiter, ("127.0.0.1", port))
        assert recv(good, lambda m: m.get_type() == "COMMAND_ACK" and m.result == 0, 5) is not None
        good.mav.command_long_send(1, 1, R.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0)
        assert recv(good, lambda m: m.get_type() == "COMMAND_ACK" and m.result == 0, 5) is not None
        assert mode_of(good) == 4
        attacker.sendto(loiter, ("127.0.0.1", port))  # the captured frame, from another port
        deadline = time.monotonic() + 1.5
        while time.monotonic() < deadline:
            assert mode_of(good) == 4, "the replayed command was executed"
    finally:
        good.close()
        attacker.close()


def _secret_forms(key: bytes) -> list[bytes]:
    return [key, key.hex().encode(), key.hex().upper().encode(), key[:16], key[16:]]


def test_key_is_never_in_the_output_nor_in_the_tlog_of_normal_traffic(signed_vehicle: tuple[Proc, int, Path]) -> None:
    proc, port, tlog = signed_vehicle
    good = client(port, 250, KEY)
    try:
        for _ in range(3):
            assert mode_of(good) in (0, 4)
        good.mav.command_long_send(1, 1, R.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0)
        assert recv(good, lambda m: m.get_type() == "COMMAND_ACK", 5) is not None
    finally:
        good.close()
    assert proc.stop(signal.SIGINT, grace_s=20.0) in (0, 130)  # SIGINT
    data = tlog.read_bytes()
    assert len(data) > 500  # the tlog holds the traffic
    frames = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    assert frames.recv_match(type="HEARTBEAT") is not None
    logs = proc.out_bytes + proc.err_bytes
    assert b"DEBUG" in logs or b"INFO" in logs or len(logs) > 0
    for secret in _secret_forms(KEY):
        assert secret not in data, "signing key found in the .tlog"
        assert secret not in logs, "signing key found in the vehicle's output"


def test_setup_signing_frame_is_stripped_from_the_tlog(signed_vehicle: tuple[Proc, int, Path]) -> None:
    proc, port, tlog = signed_vehicle
    good = client(port, 250, KEY)
    try:
        assert mode_of(good) == 0
        good.mav.setup_signing_send(1, 1, list(KEY), 0)  # (re-)provisioning the same key, signed
        assert mode_of(good) == 0
    finally:
        good.close()
    assert proc.stop(signal.SIGINT, grace_s=20.0) in (0, 130)  # SIGINT
    assert KEY not in tlog.read_bytes(), "signing key found in the .tlog"


@pytest.mark.parametrize("mode", [0o640, 0o604])
def test_group_or_world_readable_key_is_refused(tmp_path: Path, mode: int) -> None:
    path = key_file(tmp_path, mode=mode)
    proc = Proc(fimnav("vehicle", "--sysid", "1", "--mavlink", "udpin:127.0.0.1:0", "--signing-key", str(path), "--duration", "0.5"), cwd=ROOT)
    try:
        code = proc.wait(30)
    finally:
        proc.stop(signal.SIGKILL)
    err = proc.err
    assert code == 2, f"exit {code}: {err[-500:]}"
    assert str(path) in err and "Traceback" not in err and ("permission" in err.lower() or "readable" in err.lower())
    assert KEY.hex() not in err


def test_owner_only_key_in_hex_is_accepted(tmp_path: Path) -> None:
    """The reference for the test above: a 0600 key file (64 hex digits) starts the vehicle."""
    proc = Proc(fimnav("vehicle", "--sysid", "1", "--mavlink", "udpin:127.0.0.1:0", "--signing-key",
                        str(key_file(tmp_path, mode=0o600, hex_text=True))), cwd=ROOT)
    try:
        ready = proc.ready()
        port = int(ready["vehicles"][0]["mavlink"].rsplit(":", 1)[1])
        good = client(port, 250, KEY)
        try:
            assert mode_of(good) == 0
        finally:
            good.close()
    finally:
        proc.stop(signal.SIGINT, grace_s=20.0)
    assert KEY.hex().encode() not in proc.out_bytes + proc.err_bytes

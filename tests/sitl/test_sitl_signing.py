"""MAVLink 2 signing against real ArduPilot SITL (copter).

ArduPilot takes its key from a SETUP_SIGNING message (as MAVProxy's ``signing setup`` sends
it), stores it, signs every frame it sends from then on and refuses unsigned or wrongly signed
frames on every port but SERIAL0 (its "secure" USB channel). The test sets SITL's key over
SERIAL0 and flies over SERIAL1, as a telemetry radio would:

* an unsigned command on SERIAL1 gets no answer while the same command signed with the key is
  acknowledged (SITL really enforces signing on that port);
* ``fimnav plan --signing-key`` with the key flies a short mission to its end (take-off, every
  step, land): every command the planner sends is signed and accepted;
* without a key the planner stops at once, naming ``--signing-key``; with another key it stops
  within seconds (not at its heartbeat timeout), naming the mismatched frames.

Needs FIMNAV_SITL_ARDUCOPTER and FIMNAV_SITL_ARDUCOPTER_DEFAULTS (tests/sitl/sitl.py); skipped
with a one-line reason otherwise.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path

import pytest
from pymavlink import mavutil

from tests.sitl.sitl import sitl_config
from tests.sitl.test_sitl_flight import START, home_below, sitl_with_serial1, write_mission
from tests.support.proc import Proc, fimnav

_CFG, _REASON = sitl_config()

pytestmark = [pytest.mark.sitl, pytest.mark.integration, pytest.mark.skipif(_CFG is None, reason=_REASON)]

SPEEDUP = 5.0
STEPS = 10
#: pymavlink counts signing time from 2015-01-01 in units of 10 µs.
EPOCH_2015 = 1420070400
MAV_CMD_REQUEST_MESSAGE = 512
AUTOPILOT_VERSION = 148


def key_file(path: Path, passphrase: bytes) -> Path:
    """A key file as the docs tell users to write one: SHA-256 of a passphrase, mode 600."""
    path.write_bytes(hashlib.sha256(passphrase).digest())
    os.chmod(path, 0o600)
    return path


def signed_heartbeat(conn: mavutil.mavfile, timeout_s: float) -> bool:
    """Whether a HEARTBEAT whose frame carries a signature (incompat flag) arrives in time."""
    end = time.monotonic() + timeout_s
    while (left := end - time.monotonic()) > 0:
        hb = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=left)
        if hb is not None and hb.get_header().incompat_flags & mavutil.mavlink.MAVLINK_IFLAG_SIGNED:
            return True
    return False


def ack_within(conn: mavutil.mavfile, timeout_s: float) -> object | None:
    """Send MAV_CMD_REQUEST_MESSAGE(AUTOPILOT_VERSION) to system 1 and return its COMMAND_ACK
    (None when none comes within ``timeout_s``)."""
    conn.mav.command_long_send(1, 1, MAV_CMD_REQUEST_MESSAGE, 0, AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0)
    end = time.monotonic() + timeout_s
    while (left := end - time.monotonic()) > 0:
        msg = conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=left)
        if msg is not None and msg.command == MAV_CMD_REQUEST_MESSAGE:
            return msg
    return None


def test_signed_sitl_accepts_the_planner_with_its_key_only(tmp_path: Path, procs: list[Proc]) -> None:
    assert _CFG is not None
    key = key_file(tmp_path / "key", b"fimnav sitl test")
    wrong = key_file(tmp_path / "wrong", b"another key")
    mission = write_mission(tmp_path / "m.yaml", steps=STEPS)
    with sitl_with_serial1(tmp_path / "sitl", SPEEDUP, home_below(mission, START), 1) as (sitl, serial1):
        # SERIAL0 (always accepts unsigned): give SITL its key, as MAVProxy's `signing setup` does.
        secure = mavutil.mavlink_connection(sitl.address, source_system=255, source_component=190)
        try:
            assert secure.wait_heartbeat(timeout=30) is not None, sitl.log_tail()
            secure.mav.setup_signing_send(1, 1, key.read_bytes(), int((time.time() - EPOCH_2015) * 1e5))

            # SERIAL1: unsigned commands are dropped; signed ones with the key are answered.
            radio = mavutil.mavlink_connection(serial1, source_system=255, source_component=191)
            try:
                assert signed_heartbeat(radio, 30.0), "SITL does not sign its frames after SETUP_SIGNING"
                assert ack_within(radio, 3.0) is None, "SITL answered an unsigned command on SERIAL1"
                radio.setup_signing(key.read_bytes(), sign_outgoing=True)
                ack = ack_within(radio, 5.0)
                assert ack is not None and ack.result == 0, ack
            finally:
                radio.close()

            # The planner with the key flies the mission (first: SITL's signing clock follows its
            # sped-up GPS time, and refuses a new stream whose time is more than 60 s behind).
            t0 = time.monotonic()
            plan = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--mavlink", serial1, "--speedup", f"{SPEEDUP:g}",
                               "--signing-key", str(key), "--preflight-timeout", "120"))
            procs.append(plan)
            assert plan.wait(200.0) == 0, plan.tail()
            flight_s = time.monotonic() - t0
            summary = json.loads(plan.out.strip().splitlines()[-1])
            assert summary["steps"] == STEPS and summary["late_steps"] <= 1, summary
            assert summary["end"] == {"action": "land", "confirmed": True, "mode": "LAND", "armed": False, "landed_state": "ON_GROUND"}
            assert "airborne in GUIDED" in plan.err and "sig mismatch" not in plan.err

            # Without a key: refused at once, naming the option.
            t0 = time.monotonic()
            nokey = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--mavlink", serial1, "--speedup", f"{SPEEDUP:g}"))
            procs.append(nokey)
            assert nokey.wait(30.0) == 1, nokey.tail()
            nokey_s = time.monotonic() - t0
            assert "uses MAVLink 2 signing" in nokey.err and "--signing-key" in nokey.err, nokey.tail()

            # Another key: refused within seconds, not at the 120 s heartbeat timeout.
            t0 = time.monotonic()
            other = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--mavlink", serial1, "--speedup", f"{SPEEDUP:g}",
                                "--signing-key", str(wrong), "--preflight-timeout", "120"))
            procs.append(other)
            assert other.wait(30.0) == 1, other.tail()
            wrong_s = time.monotonic() - t0
            assert "does not match our signing key" in other.err and "another key" in other.err, other.tail()
            for p in (plan, nokey, other):
                assert "Traceback" not in p.err and "sig mismatch" not in p.err
                assert key.read_bytes().hex() not in p.err + p.out
        finally:
            secure.close()
    print(f"\nsigned SITL x{SPEEDUP:g}: flight with the key {flight_s:.1f} s; no key refused after {nokey_s:.1f} s; "
          f"wrong key refused after {wrong_s:.1f} s")

"""PX4 flavour (OFFBOARD rules, offboard-loss failsafe), MAVLink 2 signing and the .tlog."""

from __future__ import annotations

import math
import os
import subprocess
from pathlib import Path
import sys
import time

import numpy as np
import pytest
from pymavlink import mavutil

from vehicle_sim.config import VehicleConfig

from tests.support.wait import wait_for
from tests.vehicle_sim.clients import connect_client, drain, mavlink as R, wait_msg

pytestmark = pytest.mark.integration

POS_MASK = 0b110111111000
VEL_MASK = 0b110111000111


def test_px4_identity_and_param_encoding(make_rig):
    rig = make_rig(VehicleConfig(flavour="px4", sysid=5))
    hb = wait_msg(rig.client, "HEARTBEAT", lambda m: m.get_srcSystem() == 5)
    assert hb.autopilot == R.MAV_AUTOPILOT_PX4 and hb.type == R.MAV_TYPE_QUADROTOR
    assert mavutil.mode_string_v10(hb) == "POSCTL"
    assert rig.command(R.MAV_CMD_REQUEST_MESSAGE, R.MAVLINK_MSG_ID_AUTOPILOT_VERSION) == 0
    av = wait_msg(rig.client, "AUTOPILOT_VERSION")
    assert av.capabilities & R.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    rig.client.mav.param_request_read_send(5, 1, b"MAV_SYS_ID", -1)
    pv = wait_msg(rig.client, "PARAM_VALUE", lambda m: m.param_id == "MAV_SYS_ID")
    assert pv.param_type == R.MAV_PARAM_TYPE_INT32
    # bytewise: the float's bits are the int32 5
    import struct

    assert struct.unpack("<i", struct.pack("<f", pv.param_value))[0] == 5


def test_px4_offboard_needs_stream_and_failsafe_on_loss(make_rig):
    # speed-up 2: the 1 s offboard-loss failsafe must not fire because a loaded machine
    # delays this test thread between two setpoints (0.5 s of wall time allowed)
    rig = make_rig(VehicleConfig(flavour="px4", profile="ideal"), speedup=2.0)
    c = rig.client
    v = rig.vehicle
    # no stream: OFFBOARD refused; one stale setpoint (> 0.5 s old) is no stream either
    assert rig.set_mode("OFFBOARD") == R.MAV_RESULT_FAILED
    c.mav.set_position_target_local_ned_send(0, 1, 1, R.MAV_FRAME_LOCAL_NED, POS_MASK, 0, 0, -3, 0, 0, 0, 0, 0, 0, 0, 0)
    wait_for(lambda t=v.t: v.t > t + 0.6, 5, "0.6 s of sim time", interval_s=0.005)
    assert rig.set_mode("OFFBOARD") == R.MAV_RESULT_FAILED
    # arm in POSCTL, take off (PX4: param7 is AMSL; NaN = MIS_TAKEOFF_ALT = 2.5 m)
    assert rig.arm() == 0
    assert rig.takeoff(float("nan")) == 0
    wait_msg(c, "STATUSTEXT", lambda m: "Takeoff complete" in m.text)
    wait_msg(c, "HEARTBEAT", lambda m: mavutil.mode_string_v10(m) == "LOITER", timeout=10)
    assert v.position[2] == pytest.approx(2.5, abs=0.11)
    # stream setpoints faster than 2 Hz (sim time), then OFFBOARD is accepted
    target_ned = (5.0, 2.0, -4.0)

    def send():
        c.mav.set_position_target_local_ned_send(0, 1, 1, R.MAV_FRAME_LOCAL_NED, POS_MASK, *target_ned, 0, 0, 0, 0, 0, 0, 0, 0)

    t0 = v.t
    send()
    wait_for(lambda: v.t > t0 + 0.2, 5, "sim time", interval_s=0.005)
    send()
    assert rig.set_mode("OFFBOARD") == 0
    deadline = time.monotonic() + 10
    while np.linalg.norm(v.position - np.array([2.0, 5.0, 4.0])) > 1e-6:  # ENU of the NED target
        assert time.monotonic() < deadline, "OFFBOARD target not reached"
        send()
        wait_for(lambda t=v.t: v.t > t + 0.1, 5, "sim time", interval_s=0.005)
    # stop streaming: after COM_OF_LOSS_T (1 s) the failsafe switches to hold (LOITER)
    wait_msg(c, "STATUSTEXT", lambda m: "offboard lost" in m.text, timeout=5)
    wait_msg(c, "HEARTBEAT", lambda m: mavutil.mode_string_v10(m) == "LOITER")
    np.testing.assert_allclose(v.position, [2.0, 5.0, 4.0], atol=1e-6)


def _write_key(tmp_path, key: bytes) -> str:
    path = tmp_path / "signing.key"
    path.write_bytes(key)
    path.chmod(0o600)  # a key readable by others is refused
    return str(path)


def test_signing_refuses_unsigned_and_accepts_signed(make_rig, tmp_path):
    key = bytes(range(32))
    rig = make_rig(VehicleConfig(signing_key_path=_write_key(tmp_path, key)), connect=False, speedup=1.0)
    addr = rig.vehicle.link.transport.address
    unsigned = connect_client(addr)
    signed = connect_client(addr, source_system=254)
    rig.clients += [unsigned, signed]
    signed.setup_signing(key, sign_outgoing=True)
    # the signed client hears signed heartbeats
    deadline = time.monotonic() + 5
    while True:
        signed.mav.heartbeat_send(R.MAV_TYPE_GCS, R.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        unsigned.mav.heartbeat_send(R.MAV_TYPE_GCS, R.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        hb = signed.recv_match(type="HEARTBEAT", blocking=True, timeout=0.3)
        if hb is not None:
            break
        assert time.monotonic() < deadline
    assert hb.get_signed()
    # unsigned arm: no ACK, nothing changes
    unsigned.mav.command_long_send(1, 1, R.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0)
    with pytest.raises(AssertionError):
        wait_msg(unsigned, "COMMAND_ACK", timeout=0.7)
    assert rig.vehicle.mode.name == "STABILIZE"
    assert rig.vehicle.link.bad_frames >= 1
    # signed: accepted
    drain(signed)
    signed.mav.command_long_send(1, 1, R.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0)
    ack = wait_msg(signed, "COMMAND_ACK", lambda m: m.command == R.MAV_CMD_DO_SET_MODE)
    assert ack.result == 0 and ack.get_signed()
    assert rig.vehicle.mode.name == "GUIDED"


def test_bad_signing_key_file_is_a_usage_error(tmp_path):
    from comms.errors import UsageError
    from vehicle_sim.host import build_vehicle

    bad = tmp_path / "short.key"
    bad.write_bytes(b"123")
    bad.chmod(0o600)
    with pytest.raises(UsageError, match="32 raw bytes or 64 hex"):
        build_vehicle(VehicleConfig(signing_key_path=str(bad)), "udpin:127.0.0.1:0")


def test_tlog_is_readable_by_mavlogdump(make_rig, tmp_path):
    tlog = tmp_path / "v1.tlog"
    rig = make_rig(VehicleConfig(tlog_path=str(tlog)), speedup=2.0)
    assert rig.set_mode("GUIDED") == 0
    assert rig.arm() == 0
    wait_msg(rig.client, "LOCAL_POSITION_NED")
    rig.host.close()
    import sysconfig

    script = Path(sysconfig.get_path("scripts")) / "mavlogdump.py"  # the installed script, no shim
    cmd = [sys.executable, str(script)] if script.exists() else [sys.executable, "-m", "pymavlink.tools.mavlogdump"]
    env = dict(os.environ, MAVLINK20="1")
    out = subprocess.run(
        [*cmd, "--dialect", "ardupilotmega", "--types", "HEARTBEAT,COMMAND_LONG,COMMAND_ACK", str(tlog)],
        capture_output=True, text=True, timeout=60, env=env,
    )
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    # frames out (our heartbeats and ACKs) and in (the client's heartbeat and commands)
    assert any("HEARTBEAT" in ln and "type : 2," in ln for ln in lines)
    assert any("HEARTBEAT" in ln and "type : 6," in ln for ln in lines)
    assert sum("COMMAND_LONG" in ln for ln in lines) >= 2
    acks = [ln for ln in lines if "COMMAND_ACK" in ln]
    assert len(acks) >= 2 and all("result : 0" in ln for ln in acks)
    # timestamps are monotonic wall time within this test
    mlog = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    stamps = []
    while (msg := mlog.recv_match()) is not None:
        stamps.append(msg._timestamp)
    assert stamps and np.all(np.diff(stamps) >= -1e-3)
    assert abs(stamps[-1] - time.time()) < 120 and math.isfinite(stamps[0])

"""Failsafe parameters of the simulated vehicle, set over the parameter protocol and then
observed over MAVLink (pymavlink client, loopback UDP):

* ArduPilot: FS_GCS_ENABLE / FS_GCS_TIMEOUT / SYSID_MYGCS, the copter GCS failsafe (heartbeat
  loss of the ground station -> RTL or LAND; disarm on the ground; nothing when disabled);
* PX4: COM_OF_LOSS_T / COM_OBL_RC_ACT, the offboard-loss failsafe (timeout and action).

Times are compared in sim seconds (the vehicle's clock, read from the vehicle's own time
stamps where the protocol carries them) against the parameter values the test set.
"""

from __future__ import annotations

import math
import struct
import time
from typing import Any

import pytest

from vehicle_sim.config import VehicleConfig

from tests.support.proc import Proc, fimnav
from tests.vehicle_sim.clients import connect_client, drain, hello, mavlink, wait_msg

SPEEDUP = 10.0
ARDUPILOT_GUIDED, ARDUPILOT_RTL, ARDUPILOT_LAND = 4, 6, 9
PX4_OFFBOARD, PX4_LOITER, PX4_RTL, PX4_LAND = 6 << 16, (4 << 16) | (3 << 24), (4 << 16) | (5 << 24), (4 << 16) | (6 << 24)


def param_set(conn: Any, sysid: int, name: str, value: float, integer: bool = False, bytewise: bool = False) -> float:
    """PARAM_SET and the value the vehicle reports back (PARAM_VALUE), decoded."""
    ptype = mavlink.MAV_PARAM_TYPE_INT32 if integer else mavlink.MAV_PARAM_TYPE_REAL32
    raw = struct.unpack("<f", struct.pack("<i", int(value)))[0] if integer and bytewise else float(value)
    drain(conn)
    conn.mav.param_set_send(sysid, 1, name.encode(), raw, ptype)
    pv = wait_msg(conn, "PARAM_VALUE", lambda m: m.param_id == name)
    if integer and bytewise:
        return float(struct.unpack("<i", struct.pack("<f", pv.param_value))[0])
    return float(pv.param_value)


def gcs_heartbeat(conn: Any) -> None:
    conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)


def wait_mode(conn: Any, custom_mode: int, timeout: float = 10.0) -> Any:
    return wait_msg(conn, "HEARTBEAT", lambda m: m.get_srcComponent() == 1 and m.custom_mode == custom_mode, timeout)


def keep_gcs_alive(rig: Any, sim_s: float) -> list[str]:
    """Send GCS heartbeats every 0.1 wall s for ``sim_s`` sim seconds; return the STATUSTEXTs seen."""
    v, c = rig.vehicle, rig.client
    texts: list[str] = []
    t_end = v.t + sim_s
    while v.t < t_end:
        gcs_heartbeat(c)
        m = c.recv_match(type="STATUSTEXT", blocking=True, timeout=0.1)
        if m is not None:
            texts.append(m.text)
    return texts


@pytest.mark.parametrize(("enable", "mode", "text"), [(1, ARDUPILOT_RTL, "GCS Failsafe"), pytest.param(5, ARDUPILOT_LAND, "GCS Failsafe", marks=pytest.mark.slow),
                                                 (0, None, None)])
def test_ardupilot_gcs_failsafe(make_rig, enable: int, mode: int | None, text: str | None) -> None:
    rig = make_rig(VehicleConfig(), speedup=SPEEDUP)
    c, v = rig.client, rig.vehicle
    assert param_set(c, v.sysid, "FS_GCS_TIMEOUT", 1.0) == 5.0  # out of range (2..120): unchanged
    assert param_set(c, v.sysid, "FS_GCS_ENABLE", 9, integer=True) == 0.0
    timeout_s = 3.0
    assert param_set(c, v.sysid, "FS_GCS_TIMEOUT", timeout_s) == timeout_s
    rig.fly_up(4.0)  # (failsafe still off: the climb sends no heartbeats)
    gcs_heartbeat(c)
    assert param_set(c, v.sysid, "FS_GCS_ENABLE", enable, integer=True) == enable
    # Heartbeats every 1 sim s for twice the timeout: no failsafe.
    texts = keep_gcs_alive(rig, 2 * timeout_s)
    assert not [t for t in texts if "Failsafe" in t], texts
    t_last = v.t  # the vehicle receives the last heartbeat at or after this sim time
    gcs_heartbeat(c)
    drain(c)
    if mode is None:  # disabled: silence for twice the timeout changes nothing
        attitude = wait_msg(c, "ATTITUDE")
        wait_msg(c, "ATTITUDE", lambda m: m.time_boot_ms >= attitude.time_boot_ms + 2000 * timeout_s)
        assert not v.failsafes.gcs_failsafe
        assert wait_msg(c, "HEARTBEAT", lambda m: m.get_srcComponent() == 1).custom_mode == ARDUPILOT_GUIDED
        return
    st = wait_msg(c, "STATUSTEXT", lambda m: m.text == text, timeout=10.0)
    fired_after_s = v.t - t_last
    assert timeout_s - 0.05 <= fired_after_s <= timeout_s + 1.0, fired_after_s
    assert st.severity == mavlink.MAV_SEVERITY_WARNING
    wait_mode(c, mode)
    if mode == ARDUPILOT_LAND:  # landed and disarmed itself
        wait_msg(c, "HEARTBEAT", lambda m: m.get_srcComponent() == 1 and m.custom_mode == mode and not m.base_mode & 128, 20.0)
    else:  # RTL climbs to RTL_ALT (15 m) first
        rig.local(lambda p: p.z < -6.0, timeout=10.0)
    # The GCS comes back: the failsafe clears, the vehicle stays in the failsafe's mode.
    gcs_heartbeat(c)
    wait_msg(c, "STATUSTEXT", lambda m: m.text == "GCS Failsafe Cleared", timeout=5.0)
    assert wait_msg(c, "HEARTBEAT", lambda m: m.get_srcComponent() == 1).custom_mode == mode


def test_ardupilot_gcs_failsafe_on_the_ground_disarms_and_only_sysid_mygcs_counts(make_rig) -> None:
    """Armed on the ground with FS_GCS_ENABLE = 1 and heartbeats from a system that is not
    SYSID_MYGCS: they do not count, the failsafe disarms ("GCS Failsafe - Disarming")."""
    rig = make_rig(VehicleConfig(), speedup=SPEEDUP)
    c, v = rig.client, rig.vehicle  # the client is system 255
    assert param_set(c, v.sysid, "FS_GCS_TIMEOUT", 60.0) == 60.0
    assert param_set(c, v.sysid, "FS_GCS_ENABLE", 1, integer=True) == 1.0
    gcs_heartbeat(c)  # seen once as SYSID_MYGCS (255, the default)
    assert rig.set_mode("GUIDED") == mavlink.MAV_RESULT_ACCEPTED
    assert rig.arm() == mavlink.MAV_RESULT_ACCEPTED
    assert param_set(c, v.sysid, "SYSID_MYGCS", 42, integer=True) == 42.0
    assert param_set(c, v.sysid, "FS_GCS_TIMEOUT", 2.0) == 2.0
    deadline = time.monotonic() + 10.0
    texts: list[str] = []
    while "GCS Failsafe - Disarming" not in texts:  # our heartbeats keep coming, and do not count
        assert time.monotonic() < deadline, texts
        gcs_heartbeat(c)
        m = c.recv_match(type="STATUSTEXT", blocking=True, timeout=0.05)
        if m is not None:
            texts.append(m.text)
    wait_msg(c, "HEARTBEAT", lambda m: m.get_srcComponent() == 1 and not m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)


def offboard_flight(rig: Any, alt_m: float = 4.0) -> None:
    """PX4: stream a position setpoint alt_m above the start, OFFBOARD, arm, wait until there."""
    c, v = rig.client, rig.vehicle
    mask = 0b0000_1101_1111_1000  # position only

    def setpoint() -> None:
        c.mav.set_position_target_local_ned_send(0, v.sysid, 1, mavlink.MAV_FRAME_LOCAL_NED, mask, 0, 0, -alt_m, 0, 0, 0, 0, 0, 0, 0, 0)

    setpoint()
    assert rig.set_mode("OFFBOARD") == mavlink.MAV_RESULT_ACCEPTED
    assert rig.arm() == mavlink.MAV_RESULT_ACCEPTED
    deadline = time.monotonic() + 20.0
    while True:  # a stream at 20 Hz of wall time (2 Hz of sim time at x10)
        setpoint()
        m = c.recv_match(type="LOCAL_POSITION_NED", blocking=True, timeout=0.05)
        if m is not None and abs(m.z + alt_m) < 0.2:
            return
        assert time.monotonic() < deadline, "no climb in OFFBOARD"


@pytest.mark.parametrize(
    ("action", "mode", "text"),
    [(4, PX4_LAND, "Failsafe: offboard lost, landing"), (3, PX4_RTL, "Failsafe: offboard lost, returning"),
     pytest.param(0, PX4_LOITER, "Failsafe: offboard lost, holding", marks=pytest.mark.slow)],
)
def test_px4_offboard_loss_timeout_and_action(make_rig, action: int, mode: int, text: str) -> None:
    rig = make_rig(VehicleConfig(flavour="px4"), speedup=SPEEDUP)
    c, v = rig.client, rig.vehicle
    assert param_set(c, v.sysid, "COM_OBL_RC_ACT", 0, integer=True, bytewise=True) == 0.0  # PX4's default
    assert param_set(c, v.sysid, "COM_OBL_RC_ACT", 8, integer=True, bytewise=True) == 0.0  # out of range
    loss_s = 2.5
    assert param_set(c, v.sysid, "COM_OF_LOSS_T", loss_s) == loss_s
    assert param_set(c, v.sysid, "COM_OBL_RC_ACT", action, integer=True, bytewise=True) == action
    offboard_flight(rig)
    t_last = v.t  # the vehicle receives the last setpoint at or after this sim time
    c.mav.set_position_target_local_ned_send(0, v.sysid, 1, mavlink.MAV_FRAME_LOCAL_NED, 0b0000_1101_1111_1000, 0, 0, -4.0, 0, 0, 0, 0, 0, 0, 0, 0)
    drain(c)
    wait_msg(c, "STATUSTEXT", lambda m: m.text == text, timeout=10.0)
    fired_after_s = v.t - t_last
    assert loss_s - 0.05 <= fired_after_s <= loss_s + 1.0, fired_after_s
    wait_mode(c, mode)
    if mode == PX4_LAND:  # landed and disarmed itself, then back in the user's mode (OFFBOARD), as PX4
        wait_msg(c, "HEARTBEAT", lambda m: m.get_srcComponent() == 1 and m.custom_mode == 6 << 16 and not m.base_mode & 128, 20.0)
    elif mode == PX4_LOITER:
        hb = wait_msg(c, "HEARTBEAT", lambda m: m.get_srcComponent() == 1)
        assert hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        p = rig.local()
        assert math.isclose(p.z, -4.0, abs_tol=0.3)


def test_boot_parameters_from_the_command_line() -> None:
    """``fimnav vehicle --param NAME=VALUE`` (as a SITL parameter file): the values are read
    back over PARAM_REQUEST_READ, integer parameters in the flavour's encoding (PX4 bytewise)."""
    p = Proc(fimnav("vehicle", "--flavour", "px4", "--mavlink", "udpin:127.0.0.1:0", "--speedup", "5",
                    "--param", "COM_OF_LOSS_T=2.5", "--param", "com_obl_rc_act=4"))
    conn = None
    try:
        ready = p.ready(20.0)
        conn = connect_client(ready["vehicles"][0]["mavlink"])
        hello(conn, 1)
        values = {}
        for name in ("COM_OF_LOSS_T", "COM_OBL_RC_ACT"):
            conn.mav.param_request_read_send(1, 1, name.encode(), -1)
            pv = wait_msg(conn, "PARAM_VALUE", lambda m, n=name: m.param_id == n)
            values[name] = pv
        assert values["COM_OF_LOSS_T"].param_value == 2.5
        raw = values["COM_OBL_RC_ACT"]
        assert raw.param_type == mavlink.MAV_PARAM_TYPE_INT32
        assert struct.unpack("<i", struct.pack("<f", raw.param_value))[0] == 4
    finally:
        if conn is not None:
            conn.close()
        p.stop()

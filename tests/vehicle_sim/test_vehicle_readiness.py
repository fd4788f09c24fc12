"""Readiness start-up of the simulated vehicle (``ready_after_s`` / ``--ready-after``), seen by a
pymavlink client over loopback UDP, in both flavours: before ready no GPS fix, an EKF without
position, no home and no EKF origin, position modes and arming refused with the autopilot's
reason; at ready the fix, the EKF flags, HOME_POSITION and GPS_GLOBAL_ORIGIN appear and the
same commands are accepted.

Independent expectations: the planner's own readiness rule (comms.mavlink_client's
EKF_READY_FLAGS / EKF_CONST_POS_MODE, SYS_STATUS bits from pymavlink's enums) and the home's
geodetic position from comms.geodesy (not the vehicle's frame code)."""

from __future__ import annotations

import math
from typing import Any

import pytest

from comms.geodesy import MissionFrame
from comms.mavlink_client import EKF_CONST_POS_MODE, EKF_READY_FLAGS
from vehicle_sim.config import Origin, VehicleConfig

from tests.support.proc import Proc, fimnav
from tests.vehicle_sim.clients import mavlink, wait_msg

#: 8 sim s at x4: 2 s of wall time (aligned after 1 s).
READY_AFTER_S = 8.0
SPEEDUP = 4.0
START = (12.0, -7.0, 0.0)
ORIGIN = Origin(47.397742, 8.545594, 488.0)


def ekf_good(flags: int) -> bool:
    """The planner's rule: attitude, velocities, absolute position, not constant-position mode."""
    return (flags & EKF_READY_FLAGS) == EKF_READY_FLAGS and not flags & EKF_CONST_POS_MODE


def text_after(conn: Any, cmd: int, want: str, timeout: float = 5.0) -> tuple[int, str]:
    """COMMAND_ACK result of ``cmd`` and the first STATUSTEXT containing ``want``."""
    ack = wait_msg(conn, "COMMAND_ACK", lambda m: m.command == cmd, timeout)
    st = wait_msg(conn, "STATUSTEXT", lambda m: want in m.text, timeout)
    return int(ack.result), st.text


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_not_ready_then_ready(make_rig, flavour: str) -> None:
    rig = make_rig(VehicleConfig(flavour=flavour, ready_after_s=READY_AFTER_S, start_enu_m=START, origin=ORIGIN), speedup=SPEEDUP)
    c, v = rig.client, rig.vehicle
    m = mavlink

    # --- before ready -------------------------------------------------------------------
    gps = wait_msg(c, "GPS_RAW_INT")
    assert gps.fix_type < 3 and gps.satellites_visible == 0
    sys_status = wait_msg(c, "SYS_STATUS")
    assert sys_status.onboard_control_sensors_present & m.MAV_SYS_STATUS_SENSOR_GPS
    assert not sys_status.onboard_control_sensors_health & m.MAV_SYS_STATUS_SENSOR_GPS
    assert not sys_status.onboard_control_sensors_health & m.MAV_SYS_STATUS_PREARM_CHECK

    prearm = "Arm: " if flavour == "ardupilot" else "Preflight Fail: "  # ArduPilot: "Arm: " on the command
    c.mav.command_long_send(v.sysid, 1, m.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    result, text = text_after(c, m.MAV_CMD_COMPONENT_ARM_DISARM, prearm)
    assert result == m.MAV_RESULT_FAILED
    expected = {"Arm: EKF attitude is bad", "Arm: Need 3D Fix"} if flavour == "ardupilot" else {
        "Preflight Fail: Attitude not valid", "Preflight Fail: GPS fix too low"}
    assert text in expected
    assert rig.takeoff(5.0) == (m.MAV_RESULT_FAILED if flavour == "ardupilot" else m.MAV_RESULT_TEMPORARILY_REJECTED)
    # ArduCopter skips its mode checks while disarmed (arming checks instead): GUIDED is
    # accepted before ready, and arming in it refused; PX4 refuses OFFBOARD.
    guided = "GUIDED" if flavour == "ardupilot" else "OFFBOARD"
    assert rig.set_mode(guided) == (m.MAV_RESULT_ACCEPTED if flavour == "ardupilot" else m.MAV_RESULT_FAILED)
    if flavour == "ardupilot":  # armed (forced), the mode checks apply: GUIDED needs a position
        assert rig.set_mode("STABILIZE") == m.MAV_RESULT_ACCEPTED
        assert rig.command(m.MAV_CMD_COMPONENT_ARM_DISARM, 1, 2989) == m.MAV_RESULT_ACCEPTED
        c.mav.command_long_send(v.sysid, 1, m.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0)
        assert text_after(c, m.MAV_CMD_DO_SET_MODE, "GUIDED") == (m.MAV_RESULT_FAILED, "Mode change to GUIDED failed: requires position")
        assert rig.command(m.MAV_CMD_COMPONENT_ARM_DISARM, 0) == m.MAV_RESULT_ACCEPTED

    # HOME_POSITION / GPS_GLOBAL_ORIGIN not available yet: ArduPilot accepts the request and
    # sends nothing (GET_HOME_POSITION: FAILED); PX4 denies it.
    home_result = rig.command(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_HOME_POSITION)
    origin_result = rig.command(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)
    get_home = rig.command(m.MAV_CMD_GET_HOME_POSITION)
    if flavour == "ardupilot":
        assert (home_result, origin_result, get_home) == (m.MAV_RESULT_ACCEPTED, m.MAV_RESULT_ACCEPTED, m.MAV_RESULT_FAILED)
        assert rig.command(m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAVLINK_MSG_ID_EKF_STATUS_REPORT, 250_000) == m.MAV_RESULT_ACCEPTED
    else:
        assert (home_result, origin_result, get_home) == (m.MAV_RESULT_DENIED,) * 3
        # PX4 has no EKF_STATUS_REPORT stream
        assert rig.command(m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAVLINK_MSG_ID_EKF_STATUS_REPORT, 250_000) == m.MAV_RESULT_FAILED  # as PX4 1.15

    # --- the start-up, message by message, until home ------------------------------------
    seen: dict[str, list[Any]] = {}
    while "HOME_POSITION" not in seen:
        msg = wait_msg(c, ["GPS_RAW_INT", "EKF_STATUS_REPORT", "HOME_POSITION", "GPS_GLOBAL_ORIGIN", "STATUSTEXT",
                           "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"], timeout=3 * READY_AFTER_S / SPEEDUP)
        seen.setdefault(msg.get_type(), []).append(msg)
        fixed = any(g.fix_type >= 3 for g in seen.get("GPS_RAW_INT", []))
        if msg.get_type() == "GLOBAL_POSITION_INT" and not fixed:
            # before ready: ArduPilot's never-set location (zeros); PX4 sends none at all
            assert flavour == "ardupilot" and (msg.lat, msg.lon, msg.relative_alt) == (0, 0, 0)
        if msg.get_type() == "LOCAL_POSITION_NED":
            assert fixed  # no local position before the EKF has one
    fixes = [g for g in seen["GPS_RAW_INT"] if g.fix_type >= 3]
    assert fixes and fixes[0].satellites_visible > 0
    # The fix came READY_AFTER_S of sim time after boot (GPS_RAW_INT.time_usec is sim time).
    assert READY_AFTER_S <= fixes[0].time_usec * 1e-6 <= READY_AFTER_S + 0.05
    if flavour == "ardupilot":
        flags = [e.flags for e in seen["EKF_STATUS_REPORT"]]
        assert not ekf_good(flags[0]) and ekf_good(flags[-1]), [hex(f) for f in flags]
        assert flags[0] in (0, 1 | 128) and 1 | 128 in flags  # initialising, then attitude only
        texts = [t.text for t in seen.get("STATUSTEXT", [])]
        assert "EKF3 IMU0 is using GPS" in texts, texts
    else:
        assert "EKF_STATUS_REPORT" not in seen
    home = seen["HOME_POSITION"][0]
    expect = MissionFrame(ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.alt_m).to_global(START[0], START[1], 0.0)
    assert home.latitude == round(expect.lat_deg * 1e7) and home.longitude == round(expect.lon_deg * 1e7)
    assert math.isclose(home.altitude * 1e-3, expect.alt_amsl_m, abs_tol=1e-3)
    origin = wait_msg(c, "GPS_GLOBAL_ORIGIN", timeout=5.0)
    assert (origin.latitude, origin.longitude) == (round(ORIGIN.lat_deg * 1e7), round(ORIGIN.lon_deg * 1e7))
    health = wait_msg(c, "SYS_STATUS").onboard_control_sensors_health
    assert health & m.MAV_SYS_STATUS_SENSOR_GPS and health & m.MAV_SYS_STATUS_PREARM_CHECK and health & m.MAV_SYS_STATUS_AHRS

    # --- ready: the same requests and commands now succeed ------------------------------
    assert rig.command(m.MAV_CMD_REQUEST_MESSAGE, m.MAVLINK_MSG_ID_HOME_POSITION) == m.MAV_RESULT_ACCEPTED
    assert wait_msg(c, "HOME_POSITION").latitude == home.latitude
    assert rig.command(m.MAV_CMD_GET_HOME_POSITION) == m.MAV_RESULT_ACCEPTED
    if flavour == "ardupilot":
        rig.fly_up(4.0)
    else:
        assert rig.set_mode("LOITER") == m.MAV_RESULT_ACCEPTED
        assert rig.arm() == m.MAV_RESULT_ACCEPTED
        assert rig.takeoff(float("nan")) == m.MAV_RESULT_ACCEPTED
        rig.local(lambda p: p.z < -2.0, timeout=20.0)


def test_ekf_status_report_rate_and_ready_at_boot(make_rig) -> None:
    """The default EKF_STATUS_REPORT stream runs at 2 Hz of sim time (counted between two
    ATTITUDE stamps); ready_after_s = 0 (the default) is ready at once: good flags, 3D fix."""
    rig = make_rig(VehicleConfig(), speedup=10.0)
    c = rig.client
    first = wait_msg(c, "ATTITUDE")
    count, flags = 0, set()
    while True:
        msg = wait_msg(c, ["ATTITUDE", "EKF_STATUS_REPORT"])
        if msg.get_type() == "EKF_STATUS_REPORT":
            count += 1
            flags.add(msg.flags)
        elif msg.time_boot_ms - first.time_boot_ms >= 4000:
            span_s = (msg.time_boot_ms - first.time_boot_ms) / 1000.0
            break
    assert abs(count - 2.0 * span_s) <= 1.5, (count, span_s)
    assert flags and all(ekf_good(f) for f in flags)
    assert wait_msg(c, "GPS_RAW_INT").fix_type == mavlink.GPS_FIX_TYPE_3D_FIX


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--ready-after", "-1"], "--ready-after: expected a number >= 0, found -1.0"),
        (["--ready-after", "2", "--airborne"], "--ready-after: a vehicle booting --airborne is ready at boot"),
        (["--ready-after", "2", "--lockstep", "--mission-id", "x"], "--ready-after: needs the real-time clock"),
        (["--ekf-status-hz", "nan"], "--ekf-status-hz: expected a number >= 0, found nan"),
        (["--param", "FS_GCS_ENABL=1"], "parameter 'FS_GCS_ENABL' is not a parameter of the simulated ardupilot vehicle; did you mean FS_GCS_ENABLE"),
        (["--param", "FS_GCS_ENABLE=7"], "parameter FS_GCS_ENABLE = 7: must be an integer in 0..6"),
        (["--param", "COM_OF_LOSS_T"], "--param: expected NAME=VALUE with a finite number, found 'COM_OF_LOSS_T'"),
    ],
)
def test_bad_readiness_options_are_refused_clearly(args: list[str], message: str) -> None:
    p = Proc(fimnav("vehicle", "--mavlink", "udpin:127.0.0.1:0", "--duration", "5", *args))
    try:
        assert p.wait(30.0) == 2
    finally:
        p.stop()
    assert message in p.err and "Traceback" not in p.err, p.err

"""A real pymavlink client against in-process simulated vehicles over UDP and TCP on 127.0.0.1.

Expectations come from the MAVLink / ArduPilot / PX4 rules (message fields, ACK results) and
from kinematics computed here (targets, frames through pyproj's geodesic, not the vehicle's code).
"""

from __future__ import annotations

import math
import statistics
import struct

import numpy as np
import pytest
from pymavlink.generator.mavcrc import x25crc
from pyproj import Geod

from vehicle_sim.config import Geofence, Origin, VehicleConfig

from tests.support.wait import wait_for
from tests.vehicle_sim.clients import hello, mavlink, wait_msg

pytestmark = pytest.mark.integration

R = mavlink  # short alias for enums
GEOD = Geod(ellps="WGS84")


@pytest.mark.parametrize("kind", ["udpin", "tcpin"])
def test_heartbeat_fields_and_identity(make_rig, kind):
    rig = make_rig(VehicleConfig(sysid=7), kind=kind)
    hb = wait_msg(rig.client, "HEARTBEAT", lambda m: m.get_srcSystem() == 7)
    assert hb.get_srcComponent() == 1
    assert hb.type == R.MAV_TYPE_QUADROTOR
    assert hb.autopilot == R.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert hb.base_mode & R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not hb.base_mode & R.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb.system_status == R.MAV_STATE_STANDBY
    assert hb.mavlink_version == 3
    assert rig.client.WIRE_PROTOCOL_VERSION == "2.0" or hb.get_header().incompat_flags is not None


@pytest.mark.slow  # waits out heartbeats in real time (5 s)
def test_heartbeat_about_one_hertz_and_stops_when_unhealthy(make_rig):
    rig = make_rig()
    c = rig.client
    times = []
    for _ in range(3):
        wait_msg(c, "HEARTBEAT", lambda m: m.get_srcSystem() == 1, timeout=3)
        times.append(c.messages["HEARTBEAT"]._timestamp)
    gaps = np.diff(times)
    assert np.all((gaps > 0.6) & (gaps < 1.6)), gaps  # 1 Hz wall (a loaded 2-core machine delays some)
    assert 0.8 < float(np.mean(gaps)) < 1.25, gaps
    rig.vehicle.healthy = False
    # the link still answers (pre-arm check names the reason) but heartbeats stop
    assert rig.arm() == mavlink.MAV_RESULT_FAILED
    wait_msg(c, "STATUSTEXT", lambda m: "unhealthy" in m.text)
    with pytest.raises(AssertionError):
        wait_msg(c, "HEARTBEAT", lambda m: m.get_srcSystem() == 1, timeout=1.6)


def test_autopilot_version_protocol_version_and_mission_count(make_rig):
    rig = make_rig()
    c = rig.client
    assert rig.command(R.MAV_CMD_REQUEST_MESSAGE, R.MAVLINK_MSG_ID_AUTOPILOT_VERSION) == R.MAV_RESULT_ACCEPTED
    av = wait_msg(c, "AUTOPILOT_VERSION")
    for cap in (
        R.MAV_PROTOCOL_CAPABILITY_MAVLINK2,
        R.MAV_PROTOCOL_CAPABILITY_MISSION_INT,
        R.MAV_PROTOCOL_CAPABILITY_COMMAND_INT,
        R.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED,
        R.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT,
        R.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST,
    ):
        assert av.capabilities & cap, cap
    assert av.flight_sw_version >> 24 == 4  # ArduPilot 4.x
    assert rig.command(R.MAV_CMD_REQUEST_MESSAGE, 300) == R.MAV_RESULT_ACCEPTED
    # pymavlink 2.4.50 has no PROTOCOL_VERSION class: decode the raw frame here, CRC included
    raw = bytes(wait_msg(c, "UNKNOWN_300").data)
    assert raw[0] == 0xFD and raw[7:10] == (300).to_bytes(3, "little")
    plen = raw[1]
    payload = raw[10 : 10 + plen] + bytes(22 - plen)
    crc = x25crc(raw[1 : 10 + plen])
    crc.accumulate([217])
    assert int.from_bytes(raw[10 + plen : 12 + plen], "little") == crc.crc
    assert struct.unpack("<HHH", payload[:6]) == (200, 100, 200)
    assert rig.command(R.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 1) == R.MAV_RESULT_ACCEPTED
    wait_msg(c, "AUTOPILOT_VERSION")
    for mission_type in (R.MAV_MISSION_TYPE_MISSION, R.MAV_MISSION_TYPE_FENCE, R.MAV_MISSION_TYPE_RALLY):
        c.mav.mission_request_list_send(1, 1, mission_type)
        mc = wait_msg(c, "MISSION_COUNT", lambda m: m.mission_type == mission_type)
        assert mc.count == 0 and mc.target_system == 255
    c.mav.mission_count_send(1, 1, 0, R.MAV_MISSION_TYPE_MISSION)
    assert wait_msg(c, "MISSION_ACK").type == R.MAV_MISSION_ACCEPTED
    c.mav.mission_count_send(1, 1, 3, R.MAV_MISSION_TYPE_MISSION)
    assert wait_msg(c, "MISSION_ACK").type == R.MAV_MISSION_UNSUPPORTED


def _period_ms(c, mtype: str, n: int = 8) -> float:
    c.recv_match(type=mtype, blocking=True, timeout=1)
    stamps = [wait_msg(c, mtype).time_boot_ms for _ in range(n)]
    return statistics.median(np.diff(stamps))


def test_telemetry_rates_follow_set_message_interval_and_request_data_stream(make_rig):
    # speed-up 2, not the rig's 20: at 20 a 10 Hz stream is 200 Hz of wall time, and a host
    # loop woken late on a loaded machine skips messages (the period measured in sim time grows)
    rig = make_rig(speedup=2.0)
    c = rig.client
    for mtype in ("SYS_STATUS", "GLOBAL_POSITION_INT", "LOCAL_POSITION_NED", "ATTITUDE", "GPS_RAW_INT",
                  "HOME_POSITION", "EXTENDED_SYS_STATE", "BATTERY_STATUS"):
        wait_msg(c, mtype, timeout=8)
    assert _period_ms(c, "LOCAL_POSITION_NED") == pytest.approx(250, abs=25)  # default 4 Hz, sim time
    assert rig.command(R.MAV_CMD_SET_MESSAGE_INTERVAL, R.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 100_000) == 0
    assert _period_ms(c, "LOCAL_POSITION_NED") == pytest.approx(100, abs=21)
    c.mav.request_data_stream_send(1, 1, R.MAV_DATA_STREAM_EXTRA1, 10, 1)  # ATTITUDE at 10 Hz
    wait_msg(c, "ATTITUDE")
    assert _period_ms(c, "ATTITUDE") == pytest.approx(100, abs=21)
    assert rig.command(R.MAV_CMD_GET_MESSAGE_INTERVAL, R.MAVLINK_MSG_ID_ATTITUDE) == 0
    assert wait_msg(c, "MESSAGE_INTERVAL", lambda m: m.message_id == R.MAVLINK_MSG_ID_ATTITUDE).interval_us == 100_000
    # disable: -1
    assert rig.command(R.MAV_CMD_SET_MESSAGE_INTERVAL, R.MAVLINK_MSG_ID_ATTITUDE, -1) == 0
    wait_msg(c, "LOCAL_POSITION_NED")
    c.recv_match(type="ATTITUDE", blocking=False)
    with pytest.raises(AssertionError):
        wait_msg(c, "ATTITUDE", timeout=0.6)
    # cannot stream AUTOPILOT_VERSION
    assert rig.command(R.MAV_CMD_SET_MESSAGE_INTERVAL, R.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 1e5) == R.MAV_RESULT_DENIED


def test_bad_commands_get_the_right_ack(make_rig):
    rig = make_rig()
    # unknown command
    assert rig.command(R.MAV_CMD_DO_SET_SERVO, 1, 1500) == R.MAV_RESULT_UNSUPPORTED
    # takeoff while disarmed: FAILED, as ArduCopter (do_user_takeoff refuses)
    assert rig.set_mode("GUIDED") == R.MAV_RESULT_ACCEPTED
    assert rig.takeoff(5.0) == R.MAV_RESULT_FAILED
    # AUTO with an empty mission: FAILED + STATUSTEXT
    assert rig.command(R.MAV_CMD_DO_SET_MODE, 1, 3) == R.MAV_RESULT_FAILED
    wait_msg(rig.client, "STATUSTEXT", lambda m: "no mission" in m.text)
    # unknown mode number: FAILED + "No such mode", as ArduCopter
    assert rig.command(R.MAV_CMD_DO_SET_MODE, 1, 99) == R.MAV_RESULT_FAILED
    wait_msg(rig.client, "STATUSTEXT", lambda m: m.text == "No such mode 99")
    # arming refused in a non-armable mode (pre-arm check) with a reason
    assert rig.set_mode("BRAKE") == R.MAV_RESULT_ACCEPTED
    assert rig.arm() == R.MAV_RESULT_FAILED
    wait_msg(rig.client, "STATUSTEXT", lambda m: m.text == "Arm: BRAKE mode not armable")
    assert not rig.vehicle.armed
    # bad param1 of ARM_DISARM
    assert rig.command(R.MAV_CMD_COMPONENT_ARM_DISARM, 7) == R.MAV_RESULT_DENIED
    # land / RTL while on the ground
    assert rig.command(R.MAV_CMD_NAV_LAND) == R.MAV_RESULT_TEMPORARILY_REJECTED
    assert rig.command(R.MAV_CMD_NAV_RETURN_TO_LAUNCH) == R.MAV_RESULT_TEMPORARILY_REJECTED
    # takeoff with a NaN altitude, and in the wrong mode
    assert rig.set_mode("GUIDED") == 0 and rig.arm() == 0
    assert rig.takeoff(float("nan")) == R.MAV_RESULT_DENIED
    assert rig.set_mode("LOITER") == 0
    assert rig.takeoff(5.0) == R.MAV_RESULT_FAILED
    # REQUEST_MESSAGE of something we do not produce
    assert rig.command(R.MAV_CMD_REQUEST_MESSAGE, R.MAVLINK_MSG_ID_CAMERA_INFORMATION) == R.MAV_RESULT_DENIED
    # commands for another system id are ignored (no ACK)
    rig.client.mav.command_long_send(42, 1, R.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 0, 0, 0, 0, 0, 0)
    with pytest.raises(AssertionError):
        wait_msg(rig.client, "COMMAND_ACK", timeout=0.5)


def test_set_mode_message_is_acknowledged(make_rig):
    rig = make_rig()
    c = rig.client
    c.mav.set_mode_send(1, R.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 5)
    ack = wait_msg(c, "COMMAND_ACK", lambda m: m.command == R.MAVLINK_MSG_ID_SET_MODE)
    assert ack.result == R.MAV_RESULT_ACCEPTED
    hb = wait_msg(c, "HEARTBEAT", lambda m: m.custom_mode == 5 and m.get_srcSystem() == 1)
    assert mavutilmode(hb) == "LOITER"


def mavutilmode(hb) -> str:
    from pymavlink import mavutil

    return mavutil.mode_string_v10(hb)


@pytest.mark.parametrize("kind", ["udpin", "tcpin"])
def test_arm_takeoff_guided_position_and_disarm_refused_in_flight(make_rig, kind):
    rig = make_rig(kind=kind)
    c = rig.client
    rig.fly_up(5.0)
    wait_msg(c, "HEARTBEAT", lambda m: m.base_mode & R.MAV_MODE_FLAG_SAFETY_ARMED and m.get_srcSystem() == 1)
    wait_msg(c, "EXTENDED_SYS_STATE", lambda m: m.landed_state == R.MAV_LANDED_STATE_IN_AIR)
    assert rig.command(R.MAV_CMD_COMPONENT_ARM_DISARM, 0) == R.MAV_RESULT_FAILED
    # LOCAL_NED position target: N=10, E=-4, D=-8
    c.mav.set_position_target_local_ned_send(0, 1, 1, R.MAV_FRAME_LOCAL_NED, 0b110111111000, 10, -4, -8, 0, 0, 0, 0, 0, 0, 0, 0)
    m = rig.local(lambda m: math.dist((m.x, m.y, m.z), (10, -4, -8)) < 0.1, timeout=10)
    assert abs(m.vx) < 0.5
    # truth in ENU: x = E, y = N, z = -D
    np.testing.assert_allclose(rig.vehicle.position, [-4, 10, 8], atol=0.1)


def test_guided_velocity_then_timeout_holds(make_rig):
    rig = make_rig(VehicleConfig(profile="ideal"))
    rig.fly_up(5.0)
    c = rig.client
    t0 = rig.vehicle.t
    c.mav.set_position_target_local_ned_send(0, 1, 1, R.MAV_FRAME_LOCAL_NED, 0b110111000111, 0, 0, 0, 2.0, 0, 0, 0, 0, 0, 0, 0)
    wait_msg(c, "STATUSTEXT", lambda m: "timeout" in m.text, timeout=5)
    # after the 3 s guided timeout the vehicle holds where it was: ~2 m/s * 3 s north of start
    p_stop = rig.vehicle.position.copy()
    assert p_stop[1] == pytest.approx(6.0, abs=0.1)
    assert rig.vehicle.t - t0 >= 3.0
    t_hold = rig.vehicle.t
    wait_until_sim(rig, t_hold + 2.0)
    np.testing.assert_allclose(rig.vehicle.position, p_stop, atol=1e-9)
    m = rig.local(lambda m: m.time_boot_ms >= t_hold * 1000 + 500)
    assert (m.vx, m.vy, m.vz) == (0.0, 0.0, 0.0)


def wait_until_sim(rig, t_s: float, timeout: float = 5.0) -> None:
    wait_for(lambda: rig.vehicle.t >= t_s, timeout, f"sim time {t_s}", interval_s=0.005)


def test_guided_position_velocity_target_moves_until_the_guided_timeout(make_rig):
    """ArduPilot GUIDED: a position+velocity target moves with its velocity; GUID_TIMEOUT (3 s)
    after the last setpoint the velocity is zeroed and the vehicle holds where the target got
    to, q + 3 v. With zero velocity the target is a fixed point, reached and held."""
    rig = make_rig()
    rig.fly_up(4.0)
    c = rig.client
    c.mav.set_position_target_local_ned_send(0, 1, 1, R.MAV_FRAME_LOCAL_NED, 0b110111000000, 6, 3, -6, 0, 0, 0, 0, 0, 0, 0, 0)
    rig.local(lambda m: math.dist((m.x, m.y, m.z), (6, 3, -6)) < 0.1, timeout=10)
    c.mav.set_position_target_local_ned_send(0, 1, 1, R.MAV_FRAME_LOCAL_NED, 0b110111000000, 6, 3, -6, 2, 1, -0.6, 0, 0, 0, 0, 0)
    end = (6 + 3 * 2, 3 + 3 * 1, -6 - 3 * 0.6)
    m = rig.local(lambda m: math.dist((m.x, m.y, m.z), end) < 0.15 and math.hypot(m.vx, m.vy) < 0.05, timeout=15)
    assert m.time_boot_ms / 1000.0 > 3.0


@pytest.mark.parametrize("frame", ["LOCAL_OFFSET_NED", "BODY_NED", "BODY_OFFSET_NED"])
def test_relative_frames(make_rig, frame):
    rig = make_rig(VehicleConfig(profile="ideal"))
    rig.fly_up(5.0)
    c = rig.client
    v = rig.vehicle
    start = v.position.copy()
    yaw = 0.0 if frame == "LOCAL_OFFSET_NED" else math.pi / 2  # facing east
    if frame != "LOCAL_OFFSET_NED":
        # set the heading first with a zero offset (yaw not ignored)
        c.mav.set_position_target_local_ned_send(0, 1, 1, getattr(R, "MAV_FRAME_" + frame), 0b100111111000, 0, 0, 0, 0, 0, 0, 0, 0, 0, yaw, 0)
        wait_until_sim(rig, v.t + 0.5)
        start = v.position.copy()
    # 3 m forward, 1 m right, 2 m up
    c.mav.set_position_target_local_ned_send(0, 1, 1, getattr(R, "MAV_FRAME_" + frame), 0b110111111000, 3, 1, -2, 0, 0, 0, 0, 0, 0, 0, 0)
    # independent expectation in ENU: forward/right rotated by the heading
    n_off = 3 * math.cos(yaw) - 1 * math.sin(yaw)
    e_off = 3 * math.sin(yaw) + 1 * math.cos(yaw)
    expect = start + np.array([e_off, n_off, 2.0])
    wait_for(lambda: np.linalg.norm(v.position - expect) < 1e-6, 5, f"{frame} target", interval_s=0.005)


@pytest.mark.parametrize("frame", ["GLOBAL_INT", "GLOBAL_RELATIVE_ALT_INT"])
def test_global_int_setpoints(make_rig, frame):
    origin = Origin(45.0, 7.0, 300.0)
    rig = make_rig(VehicleConfig(origin=origin, profile="ideal"))
    rig.fly_up(5.0)
    c = rig.client
    # a point 30 m away at azimuth 60 deg (geodesic, independent of the vehicle's pyproj pipeline)
    lon, lat, _ = GEOD.fwd(origin.lon_deg, origin.lat_deg, 60.0, 30.0)
    alt = 12.0 if frame == "GLOBAL_RELATIVE_ALT_INT" else origin.alt_m + 12.0
    c.mav.set_position_target_global_int_send(0, 1, 1, getattr(R, "MAV_FRAME_" + frame), 0b110111111000,
                                              int(round(lat * 1e7)), int(round(lon * 1e7)), alt, 0, 0, 0, 0, 0, 0, 0, 0)
    # arrived: the straight leg (7 m up, 30 m across) ends at exactly 12 m, so 1 mm of height
    # left is < 5 mm of the leg (a looser test raced the vehicle still moving under load)
    gp = wait_msg(c, "GLOBAL_POSITION_INT", lambda m: abs(m.relative_alt - 12000) <= 1, timeout=10)
    az, _, dist = GEOD.inv(origin.lon_deg, origin.lat_deg, gp.lon * 1e-7, gp.lat * 1e-7)
    assert dist == pytest.approx(30.0, abs=0.05)
    assert az == pytest.approx(60.0, abs=0.2)
    assert gp.alt == pytest.approx((origin.alt_m + 12.0) * 1000, abs=20)
    # ENU truth: east = 30 sin 60, north = 30 cos 60 (tangent plane, < 1 mm error at 30 m)
    np.testing.assert_allclose(rig.vehicle.position[:2], [30 * math.sin(math.radians(60)), 15.0], atol=0.02)


def test_reposition_and_mission_item_guided(make_rig):
    origin = Origin()
    rig = make_rig(VehicleConfig(profile="ideal"))
    rig.fly_up(5.0)
    lon, lat, _ = GEOD.fwd(origin.lon_deg, origin.lat_deg, 0.0, 20.0)  # 20 m north
    res = rig.command(R.MAV_CMD_DO_REPOSITION, -1, R.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE, 0, 0,
                      int(round(lat * 1e7)), int(round(lon * 1e7)), 7.0, use_int=True,
                      frame=R.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
    assert res == R.MAV_RESULT_ACCEPTED
    rig.local(lambda m: abs(m.x - 20) < 0.05 and abs(m.z + 7) < 0.05, timeout=10)
    # MAVProxy's "guided LAT LON ALT": MISSION_ITEM_INT with current = 2
    lon2, lat2, _ = GEOD.fwd(origin.lon_deg, origin.lat_deg, 90.0, 10.0)
    rig.client.mav.mission_item_int_send(1, 1, 0, R.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, R.MAV_CMD_NAV_WAYPOINT, 2, 0,
                                         0, 0, 0, 0, int(round(lat2 * 1e7)), int(round(lon2 * 1e7)), 6.0)
    assert wait_msg(rig.client, "MISSION_ACK").type == R.MAV_MISSION_ACCEPTED
    rig.local(lambda m: abs(m.y - 10) < 0.05 and abs(m.x) < 0.05 and abs(m.z + 6) < 0.05, timeout=10)


def test_modes_land_rtl_and_brake(make_rig):
    rig = make_rig(VehicleConfig(start_enu_m=(3.0, 4.0, 0.0)))
    rig.fly_up(4.0)
    c = rig.client
    c.mav.set_position_target_local_ned_send(0, 1, 1, R.MAV_FRAME_LOCAL_NED, 0b110111111000, 14, 13, -6, 0, 0, 0, 0, 0, 0, 0, 0)
    rig.local(lambda m: math.dist((m.x, m.y, m.z), (14, 13, -6)) < 0.2, timeout=10)
    assert rig.set_mode("BRAKE") == 0
    assert rig.command(R.MAV_CMD_NAV_RETURN_TO_LAUNCH) == R.MAV_RESULT_ACCEPTED
    wait_msg(c, "HEARTBEAT", lambda m: m.custom_mode == 6 and m.get_srcSystem() == 1)
    # RTL climbs to 15 m, returns home (N=4, E=3) and lands, then disarms
    rig.local(lambda m: m.z < -14.8, timeout=10)
    wait_msg(c, "EXTENDED_SYS_STATE", lambda m: m.landed_state == R.MAV_LANDED_STATE_ON_GROUND, timeout=20)
    np.testing.assert_allclose(rig.vehicle.position, [3.0, 4.0, 0.0], atol=0.15)
    wait_msg(c, "HEARTBEAT", lambda m: not m.base_mode & R.MAV_MODE_FLAG_SAFETY_ARMED and m.get_srcSystem() == 1)
    # LAND from a hover
    rig.fly_up(3.0)
    assert rig.command(R.MAV_CMD_NAV_LAND) == R.MAV_RESULT_ACCEPTED
    wait_msg(c, "EXTENDED_SYS_STATE", lambda m: m.landed_state == R.MAV_LANDED_STATE_ON_GROUND, timeout=10)
    assert not rig.vehicle.armed


def test_params_list_read_set(make_rig):
    rig = make_rig()
    c = rig.client
    c.mav.param_request_list_send(1, 1)
    seen = {}
    count = None
    while count is None or len(seen) < count:
        pv = wait_msg(c, "PARAM_VALUE")
        count = pv.param_count
        seen[pv.param_id] = pv
    assert {"SYSID_THISMAV", "WPNAV_SPEED", "WPNAV_ACCEL", "GUID_TIMEOUT", "FENCE_ENABLE", "FENCE_ALT_MAX"} <= set(seen)
    assert sorted(p.param_index for p in seen.values()) == list(range(count))
    assert seen["SYSID_THISMAV"].param_value == 1.0
    assert seen["WPNAV_SPEED"].param_value == pytest.approx(1000.0)  # cm/s
    c.mav.param_set_send(1, 1, b"WPNAV_SPEED", 350.0, R.MAV_PARAM_TYPE_REAL32)
    pv = wait_msg(c, "PARAM_VALUE", lambda m: m.param_id == "WPNAV_SPEED")
    assert pv.param_value == pytest.approx(350.0)
    assert rig.vehicle.flight.limits.speed_max_h_mps == pytest.approx(3.5)
    c.mav.param_set_send(1, 1, b"GUID_TIMEOUT", -1.0, R.MAV_PARAM_TYPE_REAL32)  # invalid: unchanged value returned
    pv = wait_msg(c, "PARAM_VALUE", lambda m: m.param_id == "GUID_TIMEOUT")
    assert pv.param_value == pytest.approx(3.0)
    c.mav.param_request_read_send(1, 1, b"WPNAV_ACCEL", -1)
    assert wait_msg(c, "PARAM_VALUE", lambda m: m.param_id == "WPNAV_ACCEL").param_value == pytest.approx(500.0)
    c.mav.param_set_send(1, 1, b"NO_SUCH_PARAM", 1.0, R.MAV_PARAM_TYPE_REAL32)
    wait_msg(c, "STATUSTEXT", lambda m: "NO_SUCH_PARAM" in m.text)


def test_timesync_and_sys_time_are_sim_time(make_rig):
    rig = make_rig()
    c = rig.client
    c.mav.timesync_send(0, 123456789)
    ts = wait_msg(c, "TIMESYNC", lambda m: m.ts1 == 123456789)
    t = rig.vehicle.t
    assert 0 < ts.tc1 <= t * 1e9 + 1


def test_gps_global_origin(make_rig):
    rig = make_rig()
    c = rig.client
    o = Origin()
    # new EKF origin 100 m from the mission origin at azimuth 30 deg, 16 m higher
    lon, lat, _ = GEOD.fwd(o.lon_deg, o.lat_deg, 30.0, 100.0)
    lat_i, lon_i = int(round(lat * 1e7)), int(round(lon * 1e7))
    c.mav.set_gps_global_origin_send(1, lat_i, lon_i, int((o.alt_m + 16.0) * 1000))
    go = wait_msg(c, "GPS_GLOBAL_ORIGIN")
    assert (go.latitude, go.longitude, go.altitude) == (lat_i, lon_i, int((o.alt_m + 16.0) * 1000))
    # the vehicle (at the mission origin) is now 100 m away at azimuth 210 deg, 16 m below
    t = rig.vehicle.t
    m = rig.local(lambda m: m.time_boot_ms > t * 1000 + 300)
    assert m.x == pytest.approx(100 * math.cos(math.radians(210)), abs=0.02)
    assert m.y == pytest.approx(100 * math.sin(math.radians(210)), abs=0.02)
    assert m.z == pytest.approx(16.0, abs=0.01)
    assert rig.command(R.MAV_CMD_REQUEST_MESSAGE, R.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN) == 0
    wait_msg(c, "GPS_GLOBAL_ORIGIN")
    # refused while armed
    assert rig.set_mode("GUIDED") == 0 and rig.arm() == 0
    c.mav.set_gps_global_origin_send(1, int(o.lat_deg * 1e7), int(o.lon_deg * 1e7), 0)
    wait_msg(c, "STATUSTEXT", lambda m: "armed" in m.text)
    assert rig.vehicle.frames.ekf_origin.alt_m == pytest.approx(o.alt_m + 16.0)


def test_geofence_clamps_and_rejects(make_rig):
    fence = Geofence(z_min_m=2.0, z_max_m=10.0, x_min_m=-20, x_max_m=20, y_min_m=-20, y_max_m=20)
    rig = make_rig(VehicleConfig(geofence=fence, profile="ideal"))
    assert rig.set_mode("GUIDED") == 0 and rig.arm() == 0
    assert rig.takeoff(12.0) == R.MAV_RESULT_DENIED  # above FENCE_ALT_MAX
    assert rig.takeoff(5.0) == 0
    rig.local(lambda m: abs(m.z + 5) < 0.05, timeout=10)
    c = rig.client
    c.mav.set_position_target_local_ned_send(0, 1, 1, R.MAV_FRAME_LOCAL_NED, 0b110111111000, 50, 0, -30, 0, 0, 0, 0, 0, 0, 0, 0)
    wait_msg(c, "STATUSTEXT", lambda m: "Fence" in m.text and "clamped" in m.text)
    rig.local(lambda m: abs(m.x - 20) < 1e-3 and abs(m.z + 10) < 1e-3, timeout=10)
    # a velocity command out of the box stops at the boundary (10 m/s * 3 s guided timeout > 20 m)
    c.mav.set_position_target_local_ned_send(0, 1, 1, R.MAV_FRAME_LOCAL_NED, 0b110111000111, 0, 0, 0, 0, -10, 0, 0, 0, 0, 0, 0)
    wait_for(lambda: rig.vehicle.position[0] <= -20 + 1e-9, 5, "west boundary", interval_s=0.005)
    wait_until_sim(rig, rig.vehicle.t + 1.0)
    assert rig.vehicle.position[0] == pytest.approx(-20.0, abs=1e-9)
    # reject action
    rig2 = make_rig(VehicleConfig(sysid=2, geofence=Geofence(z_max_m=10.0, radius_m=15.0, action="reject"), profile="ideal"))
    rig2.fly_up(5.0)
    wait_for(lambda: rig2.vehicle.position[2] == 5.0, 5, "take-off altitude", interval_s=0.005)
    here = rig2.vehicle.position.copy()
    rig2.clients[0].mav.set_position_target_local_ned_send(0, 2, 1, R.MAV_FRAME_LOCAL_NED, 0b110111111000, 30, 0, -5, 0, 0, 0, 0, 0, 0, 0, 0)
    wait_msg(rig2.clients[0], "STATUSTEXT", lambda m: "refused" in m.text)
    t = rig2.vehicle.t
    wait_for(lambda: rig2.vehicle.t > t + 1.0, 5, "1 s of sim time", interval_s=0.005)
    np.testing.assert_allclose(rig2.vehicle.position, here, atol=1e-9)


def test_several_vehicles_distinct_ports_and_ids(make_rig):
    configs = [VehicleConfig(sysid=i, start_enu_m=(2.0 * i, 0.0, 0.0), profile="ideal") for i in (1, 2, 3)]
    rig = make_rig(configs)
    addrs = {v.link.transport.address for v in rig.vehicles}
    assert len(addrs) == 3
    for i, v in enumerate(rig.vehicles):
        assert rig.set_mode("GUIDED", index=i) == 0
    # arm only vehicle 2; vehicles 1 and 3 stay disarmed
    assert rig.arm(index=1) == 0
    assert rig.takeoff(3.0, index=1) == 0
    rig.local(lambda m: abs(m.z + 3) < 0.05, index=1, timeout=10)
    hb1 = wait_msg(rig.clients[0], "HEARTBEAT", lambda m: m.get_srcSystem() == 1)
    hb3 = wait_msg(rig.clients[2], "HEARTBEAT", lambda m: m.get_srcSystem() == 3)
    assert not hb1.base_mode & R.MAV_MODE_FLAG_SAFETY_ARMED and not hb3.base_mode & R.MAV_MODE_FLAG_SAFETY_ARMED
    assert rig.vehicles[0].position[2] == 0.0 and rig.vehicles[2].position[2] == 0.0
    m = rig.local(index=1)
    assert m.get_srcSystem() == 2 and m.y == pytest.approx(4.0)  # E of vehicle 2


def test_tcp_several_clients(make_rig):
    rig = make_rig(kind="tcpin")
    from tests.vehicle_sim.clients import connect_client

    second = connect_client(rig.vehicle.link.transport.address, source_system=254)
    try:
        hello(second, 1)
        assert rig.set_mode("GUIDED") == 0
        wait_msg(second, "HEARTBEAT", lambda m: m.custom_mode == 4)
    finally:
        second.close()


@pytest.mark.parametrize("kind", ["udpout", "tcp"])
def test_vehicle_dials_out_to_a_listening_gcs(kind):
    """The SITL-style direction: the ground station listens (udpin / tcpin), the vehicle sends."""
    from pymavlink import mavutil

    from vehicle_sim.clock import RealTimeClock
    from vehicle_sim.host import VehicleHost, build_vehicle

    listen = "udpin" if kind == "udpout" else "tcpin"
    gcs = mavutil.mavlink_connection(f"{listen}:127.0.0.1:0", source_system=255, dialect="ardupilotmega")
    sock = gcs.port if kind == "udpout" else gcs.listen
    port = sock.getsockname()[1]
    v = build_vehicle(VehicleConfig(sysid=9), f"{kind}:127.0.0.1:{port}")
    host = VehicleHost([v], RealTimeClock(5.0))
    host.start()
    try:
        hb = wait_msg(gcs, "HEARTBEAT", lambda m: m.get_srcSystem() == 9)
        assert hb.autopilot == R.MAV_AUTOPILOT_ARDUPILOTMEGA
        gcs.mav.command_long_send(9, 1, R.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        assert wait_msg(gcs, "COMMAND_ACK", lambda m: m.command == R.MAV_CMD_COMPONENT_ARM_DISARM).result == 0
        assert v.armed
        if kind == "udpout":
            # bound to loopback, and deaf to anyone but the ground station it dials
            local = v.link.transport.sock.getsockname()
            assert local[0] == "127.0.0.1", local
            import socket

            intruder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                enc = R.MAVLink(None, srcSystem=250, srcComponent=190)
                intruder.sendto(enc.command_long_encode(9, 1, R.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196, 0, 0, 0, 0, 0)
                                .pack(enc), local)
                gcs.mav.command_long_send(9, 1, R.MAV_CMD_REQUEST_MESSAGE, 0, R.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0)
                wait_msg(gcs, "AUTOPILOT_VERSION")  # the ground station's later command is handled ...
                assert v.armed  # ... the intruder's earlier disarm never arrived
            finally:
                intruder.close()
    finally:
        host.close()
        gcs.close()

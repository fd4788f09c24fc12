"""Telemetry encoders of a simulated vehicle: one MAVLink message each, from the true state
(plus the reported-position noise), stamped with sim time."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from comms.autopilot import (
    EKF_ATTITUDE,
    EKF_CONST_POS_MODE,
    EKF_POS_HORIZ_ABS,
    EKF_POS_HORIZ_REL,
    EKF_POS_VERT_ABS,
    EKF_PRED_POS_HORIZ_ABS,
    EKF_PRED_POS_HORIZ_REL,
    EKF_VELOCITY_HORIZ,
    EKF_VELOCITY_VERT,
    FlavourInfo,
)
from vehicle_sim.config import VehicleConfig
from vehicle_sim.dynamics import FloatArray
from vehicle_sim.flight_state import FlightState
from vehicle_sim.frames import VehicleFrames
from vehicle_sim.geofence import FenceGuard
from vehicle_sim.link import protocol_version_message
from vehicle_sim.readiness import ArmingChecks, Readiness

#: Flags of an EKF that has aligned its attitude but has no position (no GPS yet).
EKF_FLAGS_ALIGNED = EKF_ATTITUDE | EKF_CONST_POS_MODE
#: Flags of an EKF using GPS on the ground (no terrain height: no POS_VERT_AGL).
EKF_FLAGS_READY = (
    EKF_ATTITUDE
    | EKF_VELOCITY_HORIZ
    | EKF_VELOCITY_VERT
    | EKF_POS_HORIZ_REL
    | EKF_POS_HORIZ_ABS
    | EKF_POS_VERT_ABS
    | EKF_PRED_POS_HORIZ_REL
    | EKF_PRED_POS_HORIZ_ABS
)


def _i16(v: float) -> int:
    return max(-32768, min(32767, int(round(v))))


def _heading_cdeg(yaw_rad: float) -> int:
    return int(round(math.degrees(yaw_rad) % 360.0 * 100)) % 36000


class TelemetryEncoder:
    """Builds the vehicle's telemetry messages (``msg_<name>`` for each MAVLink name).

    Args:
        config: the vehicle configuration (flavour, sysid, noise, origin altitude).
        info: the autopilot profile. state: the flight state. readiness: the start-up stage.
        arming: the pre-arm checks (SYS_STATUS). fence: the fence (SYS_STATUS).
        frames: the vehicle's frames. gcs_failsafe: whether the GCS failsafe is active.
        wall: wall clock (s), for SYSTEM_TIME only. mavlink: pymavlink's dialect module.
    """

    def __init__(
        self,
        config: VehicleConfig,
        info: FlavourInfo,
        state: FlightState,
        readiness: Readiness,
        arming: ArmingChecks,
        fence: FenceGuard,
        frames: VehicleFrames,
        gcs_failsafe: Callable[[], bool],
        wall: Callable[[], float],
        mavlink: Any,
    ) -> None:
        self.config = config
        self.info = info
        self.state = state
        self.readiness = readiness
        self.arming = arming
        self.fence = fence
        self.frames = frames
        self.gcs_failsafe = gcs_failsafe
        self.wall = wall
        self.mavlink = mavlink
        self.noise_rng = np.random.default_rng(np.random.SeedSequence([config.seed, config.sysid, 0x5E45]))
        #: (custom mode, armed) of the last HEARTBEAT built (a lockstep tick report repeats
        #: the heartbeat when the state changed since).
        self.heartbeat_state: tuple[int, bool] | None = None

    def builder(self, name: str) -> Callable[[], Any]:
        """The encoder of MAVLink message ``name`` (e.g. ``"GLOBAL_POSITION_INT"``)."""
        fn: Callable[[], Any] = getattr(self, "msg_" + name.lower())
        return fn

    def _reported_position(self) -> FloatArray:
        p = self.state.position
        sigma = self.config.position_noise_m
        if sigma > 0.0:
            return p + self.noise_rng.normal(0.0, sigma, 3)
        return p

    def _base_mode(self) -> int:
        m = self.mavlink
        s = self.state
        base = m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | m.MAV_MODE_FLAG_STABILIZE_ENABLED
        if self.info.base_mode_manual_input:  # ArduPilot's GCS_MAVLINK_Copter::base_mode
            base |= m.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        if s.mode.name in self.info.guided_flag_modes:
            base |= m.MAV_MODE_FLAG_GUIDED_ENABLED
        if s.armed:
            base |= m.MAV_MODE_FLAG_SAFETY_ARMED
        return base

    def msg_heartbeat(self) -> Any:
        """HEARTBEAT: QUADROTOR, ArduPilot or PX4, custom mode, armed flag, system status."""
        m = self.mavlink
        s = self.state
        if not s.healthy:
            status = m.MAV_STATE_CRITICAL
        elif self.info.heartbeat_active_when_armed:  # PX4
            status = m.MAV_STATE_ACTIVE if s.armed else m.MAV_STATE_STANDBY
        else:
            # GCS_MAVLINK_Copter::vehicle_system_status: CRITICAL in a failsafe, STANDBY while
            # landed (armed or not), ACTIVE in the air.
            status = m.MAV_STATE_CRITICAL if self.gcs_failsafe() else (m.MAV_STATE_ACTIVE if s.flying else m.MAV_STATE_STANDBY)
        self.heartbeat_state = (s.mode.custom_mode, s.armed)
        return m.MAVLink_heartbeat_message(m.MAV_TYPE_QUADROTOR, self.info.autopilot, self._base_mode(), s.mode.custom_mode, status, 3)

    def msg_sys_status(self) -> Any:
        """SYS_STATUS: sensors present/enabled/healthy, battery."""
        m = self.mavlink
        s = self.state
        sensors = (
            m.MAV_SYS_STATUS_SENSOR_3D_GYRO
            | m.MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | m.MAV_SYS_STATUS_SENSOR_3D_MAG
            | m.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
            | m.MAV_SYS_STATUS_SENSOR_GPS
            | m.MAV_SYS_STATUS_AHRS
            | m.MAV_SYS_STATUS_SENSOR_BATTERY
        )
        fence_on = self.fence.fence.enabled
        present = sensors | m.MAV_SYS_STATUS_PREARM_CHECK
        if fence_on:
            present |= m.MAV_SYS_STATUS_GEOFENCE
        health = sensors | (m.MAV_SYS_STATUS_GEOFENCE if fence_on else 0)
        if not self.readiness.ready:  # no GPS fix; the EKF (AHRS) is unhealthy until its attitude aligns
            health &= ~m.MAV_SYS_STATUS_SENSOR_GPS
            if self.readiness.stage == "init":
                health &= ~m.MAV_SYS_STATUS_AHRS
        if self.arming.prearm_failure() is None or s.armed:
            health |= m.MAV_SYS_STATUS_PREARM_CHECK
        if not s.healthy:
            health = 0
        volt_mv = int(self._voltage() * 1000)
        return m.MAVLink_sys_status_message(present, present, health, 100, volt_mv, self._current_ca(), int(s.battery * 100), 0, 0, 0, 0, 0, 0)

    def _voltage(self) -> float:
        return 16.8 * (0.85 + 0.15 * self.state.battery)

    def _current_ca(self) -> int:
        return 1500 if self.state.flying else 50

    def msg_global_position_int(self) -> Any:
        """GLOBAL_POSITION_INT: lat/lon 1e7 deg, alt mm AMSL, relative_alt mm above home,
        velocity cm/s NED, heading cdeg. Before the vehicle is ready (ArduPilot only; PX4
        sends none): all zeros, as ArduPilot sends its never-set location."""
        s = self.state
        if not self.readiness.ready:
            return self.mavlink.MAVLink_global_position_int_message(s.time_boot_ms(), 0, 0, 0, 0, 0, 0, 0, _heading_cdeg(s.yaw_rad))
        p = self._reported_position()
        lat, lon, alt = self.frames.to_geodetic(p)
        vn, ve, vd = self.frames.vel_enu_to_ned(s.pm.velocity)
        rel = float(p[2] - s.home[2])
        return self.mavlink.MAVLink_global_position_int_message(
            s.time_boot_ms(),
            int(round(lat * 1e7)),
            int(round(lon * 1e7)),
            int(round(alt * 1000)),
            int(round(rel * 1000)),
            _i16(vn * 100),
            _i16(ve * 100),
            _i16(vd * 100),
            _heading_cdeg(s.yaw_rad),
        )

    def msg_local_position_ned(self) -> Any:
        """LOCAL_POSITION_NED about the EKF origin (m, m/s)."""
        p = self._reported_position()
        n, e, d = self.frames.enu_to_local_ned(p)
        vn, ve, vd = self.frames.vel_enu_to_ned(self.state.pm.velocity)
        return self.mavlink.MAVLink_local_position_ned_message(self.state.time_boot_ms(), n, e, d, vn, ve, vd)

    def msg_attitude(self) -> Any:
        """ATTITUDE (rad) from the horizontal acceleration and the held yaw."""
        s = self.state
        roll, pitch = s.pm.attitude(s.yaw_rad)
        return self.mavlink.MAVLink_attitude_message(s.time_boot_ms(), roll, pitch, s.yaw_rad, 0.0, 0.0, 0.0)

    def msg_gps_raw_int(self) -> Any:
        """GPS_RAW_INT: 3D fix, 16 satellites; before the vehicle is ready no fix and no
        satellites (fix_type 0 while the EKF initialises, then 1), position unknown (0)."""
        m = self.mavlink
        t_us = int(round(self.state.t_s * 1e6))
        if not self.readiness.ready:
            fix = m.GPS_FIX_TYPE_NO_GPS if self.readiness.stage == "init" else m.GPS_FIX_TYPE_NO_FIX
            return m.MAVLink_gps_raw_int_message(t_us, fix, 0, 0, 0, 65535, 65535, 0, 65535, 0)
        p = self._reported_position()
        lat, lon, alt = self.frames.to_geodetic(p)
        v = self.state.pm.velocity
        gs = math.hypot(float(v[0]), float(v[1]))
        cog = int(round(math.degrees(math.atan2(float(v[0]), float(v[1]))) % 360.0 * 100)) % 36000
        lat_e7, lon_e7, alt_mm = int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000))
        return m.MAVLink_gps_raw_int_message(t_us, m.GPS_FIX_TYPE_3D_FIX, lat_e7, lon_e7, alt_mm, 70, 100, min(int(gs * 100), 65534), cog, 16)

    def msg_ekf_status_report(self) -> Any:
        """EKF_STATUS_REPORT (ArduPilot): flags (EKF_STATUS_FLAGS) and normalised variances
        (test ratios, 1 = at the innovation gate): 0 while the EKF initialises, attitude with
        constant-position mode once aligned, everything but terrain height when ready."""
        stage = self.readiness.stage
        if stage == "ready":
            flags, var = EKF_FLAGS_READY, 0.05
        elif stage == "aligned":
            flags, var = EKF_FLAGS_ALIGNED, 0.5
        else:
            flags, var = 0, 0.0
        return self.mavlink.MAVLink_ekf_status_report_message(flags, var, var, var, var, 0.0)

    def msg_home_position(self) -> Any:
        """HOME_POSITION: geodetic and local NED."""
        home = self.state.home
        lat, lon, alt = self.frames.to_geodetic(home)
        n, e, d = self.frames.enu_to_local_ned(home)
        return self.mavlink.MAVLink_home_position_message(
            int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)), n, e, d, [1.0, 0.0, 0.0, 0.0], 0, 0, 0
        )

    def msg_extended_sys_state(self) -> Any:
        """EXTENDED_SYS_STATE: landed state."""
        return self.mavlink.MAVLink_extended_sys_state_message(self.mavlink.MAV_VTOL_STATE_UNDEFINED, self.state.landed_state)

    def msg_battery_status(self) -> Any:
        """BATTERY_STATUS: a 4S LiPo draining while flying."""
        m = self.mavlink
        battery = self.state.battery
        cell_mv = int(self._voltage() * 1000 / 4)
        cells = [cell_mv] * 4 + [65535] * 6
        return m.MAVLink_battery_status_message(
            0,
            m.MAV_BATTERY_FUNCTION_ALL,
            m.MAV_BATTERY_TYPE_LIPO,
            32767,
            cells,
            self._current_ca(),
            int((1.0 - battery) * 5000),
            -1,
            int(battery * 100),
        )

    def msg_vfr_hud(self) -> Any:
        """VFR_HUD: ground speed, heading, altitude AMSL, climb rate."""
        s = self.state
        v = s.pm.velocity
        gs = math.hypot(float(v[0]), float(v[1]))
        alt = self.config.origin.alt_m + float(s.position[2])
        hdg = int(math.degrees(s.yaw_rad) % 360.0)
        return self.mavlink.MAVLink_vfr_hud_message(gs, gs, hdg, 50 if s.flying else 0, alt, float(v[2]))

    def msg_system_time(self) -> Any:
        """SYSTEM_TIME: wall UNIX time (µs) and sim time since boot (ms)."""
        return self.mavlink.MAVLink_system_time_message(int(self.wall() * 1e6), self.state.time_boot_ms())

    def msg_gps_global_origin(self) -> Any:
        """GPS_GLOBAL_ORIGIN: the EKF origin."""
        o = self.frames.ekf_origin
        return self.mavlink.MAVLink_gps_global_origin_message(
            int(round(o.lat_deg * 1e7)), int(round(o.lon_deg * 1e7)), int(round(o.alt_m * 1000)), int(self.state.t_s * 1e6)
        )

    def msg_autopilot_version(self) -> Any:
        """AUTOPILOT_VERSION with the capabilities MAVSDK and QGroundControl look for."""
        m = self.mavlink
        caps = (
            m.MAV_PROTOCOL_CAPABILITY_MAVLINK2
            | m.MAV_PROTOCOL_CAPABILITY_MISSION_INT
            | m.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
            | m.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
            | m.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
            | m.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
            | m.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
            | (m.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE if self.info.param_bytewise else m.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST)
        )
        uid2 = 0x46494D0000000000 | self.config.sysid
        return m.MAVLink_autopilot_version_message(caps, self.info.flight_sw_version, 0, 0, 0, list(b"fimnavsm"), [0] * 8, [0] * 8, 0, 0, uid2)

    def msg_protocol_version(self) -> Any:
        """PROTOCOL_VERSION: MAVLink 2 (200), minimum 100."""
        return protocol_version_message(200, 100, 200)

"""The simulated vehicle's frames: the mission ENU frame (physics, fence, home) and the
LOCAL_NED frame about its EKF origin (the mission origin until SET_GPS_GLOBAL_ORIGIN moves it)."""

from __future__ import annotations

from typing import Any

import numpy as np

from comms.geodesy import MissionFrame, Origin
from vehicle_sim.dynamics import FloatArray


class VehicleFrames:
    """ENU <-> LOCAL_NED conversions about the current EKF origin, through
    :class:`comms.geodesy.MissionFrame` in its topocentric convention (the vehicle's physics
    run in the flat ENU tangent frame at the mission origin).

    Args:
        origin: the mission origin (the EKF origin at boot).
        home: the home position (3,), ENU m. ground_z_m: ENU height of the ground (m).
        mavlink: pymavlink's dialect module (MAV_FRAME_* numbers).
    """

    def __init__(self, origin: Origin, home: FloatArray, ground_z_m: float, mavlink: Any) -> None:
        self.mission_origin = origin
        self.home = home
        self.ground_z_m = ground_z_m
        self.mavlink = mavlink
        self.world = MissionFrame.of_origin(origin)
        self.ekf = self.world
        self.ekf_origin = origin

    def set_ekf_origin(self, origin: Origin) -> None:
        """Move the EKF origin (LOCAL_NED) to ``origin``."""
        self.ekf = self.world if origin == self.mission_origin else MissionFrame.of_origin(origin)
        self.ekf_origin = origin

    def enu_to_local_ned(self, p: FloatArray) -> tuple[float, float, float]:
        """Mission ENU (m) -> LOCAL_NED about the EKF origin (m)."""
        if self.ekf is self.world:
            return self.world.enu_to_ned(float(p[0]), float(p[1]), float(p[2]))
        lat, lon, alt = self.world.topocentric_to_geodetic(float(p[0]), float(p[1]), float(p[2]))
        return self.ekf.enu_to_ned(*self.ekf.geodetic_to_topocentric(lat, lon, alt))

    def local_ned_to_enu(self, n: float, e: float, d: float) -> FloatArray:
        """LOCAL_NED about the EKF origin (m) -> mission ENU (m)."""
        if self.ekf is self.world:
            return np.array(self.world.ned_to_enu(n, e, d))
        lat, lon, alt = self.ekf.topocentric_to_geodetic(*self.ekf.ned_to_enu(n, e, d))
        return np.array(self.world.geodetic_to_topocentric(lat, lon, alt))

    def vel_enu_to_ned(self, v: FloatArray) -> tuple[float, float, float]:
        """Velocity ENU -> NED (m/s) (the frames are parallel up to the axis swap)."""
        return self.world.enu_to_ned(float(v[0]), float(v[1]), float(v[2]))

    def vel_ned_to_enu(self, vn: float, ve: float, vd: float) -> FloatArray:
        """Velocity NED -> ENU (m/s), or an offset NED -> ENU (m)."""
        return np.array(self.world.ned_to_enu(vn, ve, vd))

    def horizontal_enu(self, lat_deg: float, lon_deg: float) -> tuple[float, float]:
        """(x, y) ENU (m) of a latitude/longitude (deg) at the mission origin's altitude."""
        x, y, _ = self.world.geodetic_to_topocentric(lat_deg, lon_deg, self.mission_origin.alt_m)
        return x, y

    def alt_to_z(self, alt: float, frame: int | None, *, amsl_default: bool) -> float:
        """Altitude of a command (m) -> ENU z (m): AMSL for GLOBAL frames (and PX4 takeoff),
        above the terrain (the ground) for TERRAIN frames, above home otherwise."""
        m = self.mavlink
        amsl = frame in (m.MAV_FRAME_GLOBAL, m.MAV_FRAME_GLOBAL_INT) if frame is not None else amsl_default
        if amsl:
            return alt - self.mission_origin.alt_m
        if frame in (m.MAV_FRAME_GLOBAL_TERRAIN_ALT, m.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT):
            return self.ground_z_m + alt
        return float(self.home[2]) + alt

    def to_geodetic(self, p: FloatArray) -> tuple[float, float, float]:
        """Mission ENU (m) -> (latitude deg, longitude deg, altitude m AMSL) as the vehicle
        reports it (topocentric: the height includes the earth's curvature)."""
        return self.world.topocentric_to_geodetic(float(p[0]), float(p[1]), float(p[2]))

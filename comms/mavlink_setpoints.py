"""The setpoints the planner's MAVLink link sends: one position and/or velocity target in the
mission ENU frame, encoded as SET_POSITION_TARGET_LOCAL_NED or SET_POSITION_TARGET_GLOBAL_INT
by the link's frame (see :mod:`comms.mavlink_client`), and the stream that re-sends the current
setpoint on a fixed period."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from comms.geodesy import MissionFrame
from comms.mavlink_telemetry import AUTOPILOT_COMPONENT, AltitudeReference, Frame

#: SET_POSITION_TARGET type masks (POSITION_TARGET_TYPEMASK: bits set = ignored). Always
#: ignore acceleration (bits 6-8), yaw (10) and yaw rate (11); ArduPilot and PX4 accept
#: position, velocity and position + velocity with these (ArduPilot: "all 3 axes must be
#: provided"). Position + velocity = 0b1101_1100_0000 = 3520.
MASK_POSITION_VELOCITY = 0b0000_1100_0000_0000 | 0b0000_0001_1100_0000  # use pos + vel
MASK_POSITION = MASK_POSITION_VELOCITY | 0b0000_0000_0011_1000
MASK_VELOCITY = MASK_POSITION_VELOCITY | 0b0000_0000_0000_0111

#: A setpoint source: wall time (s) → (position ENU m | None, velocity ENU m/s | None).
SetpointFunction = Callable[[float], tuple[np.ndarray | None, np.ndarray | None]]


def enu_to_ned(v: Iterable[float]) -> tuple[float, float, float]:
    """(x east, y north, z up) → (north, east, down)."""
    x, y, z = v
    return float(y), float(x), float(-z)


def type_mask(position: bool, velocity: bool) -> int:
    """The SET_POSITION_TARGET type mask of a setpoint with a position and/or a velocity."""
    return MASK_POSITION_VELOCITY if position and velocity else (MASK_POSITION if not velocity else MASK_VELOCITY)


class SetpointEncoder:
    """Sends setpoints to one vehicle in the link's frame.

    Args:
        mavlink: pymavlink's dialect module (``mavutil.mavlink``).
        target_system: the vehicle's system id.
        frame: ``"local_ned"`` or ``"global"``.
        mission_frame: the mission's frame (required for ``"global"``).
        altitude_reference: ``"amsl"`` or ``"relative"`` (global frame only).
    """

    def __init__(
        self, mavlink: Any, target_system: int, frame: Frame, mission_frame: MissionFrame | None, altitude_reference: AltitudeReference
    ) -> None:
        self.mavlink = mavlink
        self.target_system = target_system
        self.frame: Frame = frame
        self.mission_frame = mission_frame
        self.altitude_reference: AltitudeReference = altitude_reference
        #: Setpoints sent so far.
        self.sent = 0

    def send(
        self,
        mav: Any,
        position_enu_m: Iterable[float] | None,
        velocity_enu_mps: Iterable[float] | None,
        relative_alt_as_amsl: bool,
        home_global: tuple[float, float, float] | None,
    ) -> None:
        """One setpoint with position and/or velocity (mission ENU, m and m/s), as
        SET_POSITION_TARGET_LOCAL_NED (MAV_FRAME_LOCAL_NED) or SET_POSITION_TARGET_GLOBAL_INT
        (MAV_FRAME_GLOBAL_INT or MAV_FRAME_GLOBAL_RELATIVE_ALT_INT) by the frame. With ``relative_alt_as_amsl``
        (:attr:`comms.autopilot.FlavourInfo.relative_alt_as_amsl`, PX4) and ``home_global``
        (lat deg, lon deg, alt m AMSL), relative altitudes are sent as AMSL ones (see below)."""
        m = self.mavlink
        mask = type_mask(position_enu_m is not None, velocity_enu_mps is not None)
        vn, ve, vd = enu_to_ned(velocity_enu_mps) if velocity_enu_mps is not None else (0.0, 0.0, 0.0)
        self.sent += 1
        if self.frame == "local_ned":
            n, e, d = enu_to_ned(position_enu_m) if position_enu_m is not None else (0.0, 0.0, 0.0)
            mav.set_position_target_local_ned_send(
                0, self.target_system, AUTOPILOT_COMPONENT, m.MAV_FRAME_LOCAL_NED, mask, n, e, d, vn, ve, vd, 0, 0, 0, 0, 0
            )
            return
        if self.mission_frame is None:
            raise RuntimeError("frame 'global' without a mission frame (checked when the link is made)")
        lat_e7 = lon_e7 = 0
        alt = 0.0
        if position_enu_m is not None:
            x, y, z = (float(v) for v in position_enu_m)
            g = self.mission_frame.to_global(x, y, z)
            lat_e7, lon_e7 = g.lat_e7, g.lon_e7
            alt = g.alt_amsl_m if self.altitude_reference == "amsl" else z
        frame = m.MAV_FRAME_GLOBAL_INT if self.altitude_reference == "amsl" else m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
        if relative_alt_as_amsl and frame == m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT and home_global is not None:
            # PX4 (v1.15 and earlier) converts a GLOBAL_RELATIVE_ALT_INT altitude to local z as
            # home − alt − EKF-origin altitude, i.e. with the sign of (home − origin altitude)
            # reversed: off by twice the local z of home (1-4 m on PX4 SITL). The same target
            # as an AMSL altitude (home's AMSL altitude from HOME_POSITION + z) is converted right.
            frame = m.MAV_FRAME_GLOBAL_INT
            alt = home_global[2] + alt
        mav.set_position_target_global_int_send(
            0, self.target_system, AUTOPILOT_COMPONENT, frame, mask, lat_e7, lon_e7, alt, vn, ve, vd, 0, 0, 0, 0, 0
        )


class SetpointStream:
    """The current setpoint function and when it is next due: every ``period_s`` wall seconds
    on a grid of the period (a late wake-up does not slow the average rate down), but never
    more than one period behind (no burst after a stall)."""

    def __init__(self, period_s: float = 0.25) -> None:
        self.fn: SetpointFunction | None = None
        self.period_s = period_s
        self._last = -math.inf

    def set(self, fn: SetpointFunction | None, period_s: float | None = None) -> None:
        """Stream ``fn`` from now on (due at once); None stops the stream."""
        self.fn = fn
        if period_s is not None:
            self.period_s = period_s
        self._last = -math.inf

    def due(self, now: float) -> tuple[np.ndarray | None, np.ndarray | None] | None:
        """The setpoint to send at wall time ``now`` (s), or None when none is due."""
        if self.fn is None:
            return None
        if now - self._last < self.period_s:
            return None
        last = self._last
        self._last = now if last == -math.inf else max(last + self.period_s, now - self.period_s)
        return self.fn(now)

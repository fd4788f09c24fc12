"""What the planner's MAVLink link hears of its vehicle: the telemetry state each message
updates, the rate of the autopilot's clock, and what the vehicle still lacks to fly.

Positions are in the mission ENU frame (m), converted from LOCAL_POSITION_NED (NED about the
vehicle's EKF origin, ``frame="local_ned"``) or from GLOBAL_POSITION_INT (``frame="global"``,
with :mod:`comms.geodesy`), see :mod:`comms.mavlink_client`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from comms.autopilot import EKF_CONST_POS_MODE, EKF_READY_FLAGS, FlavourInfo
from comms.geodesy import MissionFrame

Frame = Literal["local_ned", "global"]
AltitudeReference = Literal["amsl", "relative"]

#: The autopilot's component id (MAV_COMP_ID_AUTOPILOT1).
AUTOPILOT_COMPONENT = 1
#: The autopilot's clock rate is measured over at least this many wall seconds of its
#: ``time_boot_ms`` stamps (:class:`ClockWatch`).
CLOCK_WINDOW_S: float = 1.5

MAV_SYS_STATUS_AHRS = 0x200000
MAV_SYS_STATUS_PREARM_CHECK = 0x10000000
MAV_LANDED_STATE_NAMES = {0: "UNDEFINED", 1: "ON_GROUND", 2: "IN_AIR", 3: "TAKEOFF", 4: "LANDING"}

#: Message ids.
MSG_SYS_STATUS = 1
MSG_GPS_RAW_INT = 24
MSG_LOCAL_POSITION_NED = 32
MSG_GLOBAL_POSITION_INT = 33
MSG_GPS_GLOBAL_ORIGIN = 49
MSG_EKF_STATUS_REPORT = 193
MSG_HOME_POSITION = 242
MSG_EXTENDED_SYS_STATE = 245


def ned_to_enu(n: float, e: float, d: float) -> np.ndarray:
    """(north, east, down) → (x east, y north, z up)."""
    return np.array([e, n, -d], dtype=float)


class ClockWatch:
    """The rate of the autopilot's clock against the wall clock: ``time_boot_ms`` of its
    messages against our wall clock on receipt, over a sliding window.

    The rate is the median of the slopes between pairs of samples at least half the window
    apart (Theil-Sen): a message delayed by a stalled process or a burst read at once moves
    a few slopes, not the median. A ``time_boot_ms`` that goes back (a reboot) starts over.
    ArduPilot SITL's and fimnav's simulated vehicle's ``time_boot_ms`` run on simulated time,
    so the rate is their speed-up; a real autopilot's is 1."""

    def __init__(self, keep_s: float = 10.0) -> None:
        self.keep_s = keep_s
        self.samples: list[tuple[float, float]] = []  # (wall s, boot s)

    def add(self, wall_s: float, time_boot_ms: int) -> None:
        """One message's ``time_boot_ms`` received at wall time ``wall_s`` (s)."""
        boot = time_boot_ms * 1e-3
        if self.samples:
            last_wall, last_boot = self.samples[-1]
            if boot < last_boot - 1.0:
                self.samples.clear()  # the autopilot rebooted
            elif wall_s - last_wall < 0.02:
                return  # a burst read at once: one sample of it is enough
        self.samples.append((wall_s, boot))
        while self.samples and wall_s - self.samples[0][0] > self.keep_s:
            self.samples.pop(0)

    def span_s(self) -> float:
        """Wall seconds covered by the samples."""
        return self.samples[-1][0] - self.samples[0][0] if len(self.samples) > 1 else 0.0

    def rate(self, min_span_s: float = CLOCK_WINDOW_S) -> float | None:
        """Autopilot seconds per wall second, or None until ``min_span_s`` wall seconds of
        samples are in."""
        if self.span_s() < min_span_s or len(self.samples) < 4:
            return None
        pts = self.samples
        if len(pts) > 40:
            step = len(pts) / 40.0
            pts = [pts[int(i * step)] for i in range(40)] + [pts[-1]]
        half = 0.5 * min_span_s
        slopes = [(b2 - b1) / (w2 - w1) for i, (w1, b1) in enumerate(pts) for (w2, b2) in pts[i + 1 :] if w2 - w1 >= half]
        return float(np.median(slopes)) if slopes else None


@dataclass
class Telemetry:
    """What the link has heard of the vehicle (updated by :meth:`VehicleLink.pump`).

    Positions are in the mission ENU frame (m), converted from LOCAL_POSITION_NED or from
    GLOBAL_POSITION_INT according to the link's frame; ``position_time_ms`` is the vehicle's
    ``time_boot_ms`` of that message and ``position_wall_s`` our wall clock on receipt.
    """

    heartbeat_wall_s: float = -math.inf
    heartbeats: int = 0
    autopilot: int | None = None
    custom_mode: int | None = None
    armed: bool = False
    position_enu_m: np.ndarray | None = None
    velocity_enu_mps: np.ndarray | None = None
    position_time_ms: int = -1
    position_wall_s: float = -math.inf
    home_known: bool = False
    home_global: tuple[float, float, float] | None = None  # lat deg, lon deg, alt m AMSL
    origin_global: tuple[float, float, float] | None = None  # EKF origin, same units
    gps_fix_type: int | None = None
    satellites: int | None = None
    sensors_present: int | None = None
    sensors_health: int | None = None
    sys_status_count: int = 0
    ekf_flags: int | None = None
    landed_state: int | None = None
    signed_seen: bool = False
    statustexts: list[str] = field(default_factory=list)


class TelemetryReceiver:
    """Updates :attr:`telemetry`, :attr:`clock` and the command acknowledgements
    (:attr:`acks`: {command: result}) from each message of the vehicle ``target_system``.

    Args:
        target_system: the vehicle's system id (other systems' messages are ignored).
        wall: monotonic clock (s) stamping receipts.
        frame: ``"local_ned"`` (positions from LOCAL_POSITION_NED) or ``"global"`` (from
            GLOBAL_POSITION_INT, converted with ``mission_frame``).
        mission_frame: the mission's frame (required for ``"global"``).
        altitude_reference: ``"amsl"`` or ``"relative"`` (global frame only: z from the AMSL
            altitude, or the altitude above home).
    """

    def __init__(
        self,
        target_system: int,
        wall: Callable[[], float],
        frame: Frame,
        mission_frame: MissionFrame | None,
        altitude_reference: AltitudeReference,
    ) -> None:
        self.target_system = target_system
        self.wall = wall
        self.frame: Frame = frame
        self.mission_frame = mission_frame
        self.altitude_reference: AltitudeReference = altitude_reference
        self.telemetry = Telemetry()
        self.clock = ClockWatch()
        self.acks: dict[int, int] = {}

    def handle(self, msg: Any, signed_frames: int) -> bool:
        """Take one parsed message in; False when it is not for us (another system, or bad
        data). ``signed_frames``: how many frames with a signature block the parser has seen."""
        if msg.get_srcSystem() != self.target_system:
            return False
        kind = msg.get_type()
        if kind == "BAD_DATA":
            return False
        tel = self.telemetry
        boot_ms = getattr(msg, "time_boot_ms", None)
        if boot_ms is not None and msg.get_srcComponent() == AUTOPILOT_COMPONENT:
            self.clock.add(self.wall(), int(boot_ms))
        if signed_frames:
            tel.signed_seen = True  # (frames with a signature block, checked or not)
        if kind == "HEARTBEAT" and msg.get_srcComponent() == AUTOPILOT_COMPONENT:
            tel.heartbeat_wall_s = self.wall()
            tel.heartbeats += 1
            tel.autopilot = msg.autopilot
            tel.custom_mode = msg.custom_mode
            tel.armed = bool(msg.base_mode & 128)
        elif kind in ("LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"):
            self._position(kind, msg)
        elif kind == "COMMAND_ACK":
            self.acks[msg.command] = msg.result
        else:
            self._status(kind, msg)
        return True

    def _position(self, kind: str, msg: Any) -> None:
        """LOCAL_POSITION_NED (frame ``local_ned``) or GLOBAL_POSITION_INT (frame ``global``):
        the vehicle's position and velocity, unless older than the last one."""
        tel = self.telemetry
        if kind == "LOCAL_POSITION_NED":
            if self.frame == "local_ned" and msg.time_boot_ms >= tel.position_time_ms:
                tel.position_time_ms = msg.time_boot_ms
                tel.position_wall_s = self.wall()
                tel.position_enu_m = ned_to_enu(msg.x, msg.y, msg.z)
                tel.velocity_enu_mps = ned_to_enu(msg.vx, msg.vy, msg.vz)
            return
        if msg.lat == 0 and msg.lon == 0:
            pass  # no position yet (ArduPilot reports 0, 0 before its first fix)
        elif self.frame == "global" and (msg.time_boot_ms >= tel.position_time_ms or msg.time_boot_ms < tel.position_time_ms - 10_000):
            # (a time_boot_ms far behind the last one: the autopilot rebooted)
            if self.mission_frame is None:
                raise RuntimeError("frame 'global' without a mission frame (checked when the link is made)")
            x, y, z = self.mission_frame.to_enu(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)
            if self.altitude_reference == "relative":
                z = msg.relative_alt * 1e-3
            tel.position_time_ms = msg.time_boot_ms
            tel.position_wall_s = self.wall()
            tel.position_enu_m = np.array([x, y, z], dtype=float)
            tel.velocity_enu_mps = ned_to_enu(msg.vx * 0.01, msg.vy * 0.01, msg.vz * 0.01)

    def _status(self, kind: str, msg: Any) -> None:
        """Home, EKF origin, GPS, system and EKF status, landed state, status texts."""
        tel = self.telemetry
        if kind == "HOME_POSITION":
            tel.home_known = True
            tel.home_global = (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
        elif kind == "GPS_GLOBAL_ORIGIN":
            tel.origin_global = (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
        elif kind == "GPS_RAW_INT":
            tel.gps_fix_type = msg.fix_type
            tel.satellites = msg.satellites_visible
        elif kind == "SYS_STATUS":
            tel.sys_status_count += 1
            tel.sensors_present = msg.onboard_control_sensors_present
            tel.sensors_health = msg.onboard_control_sensors_health
        elif kind == "EKF_STATUS_REPORT":
            tel.ekf_flags = msg.flags
        elif kind == "EXTENDED_SYS_STATE":
            tel.landed_state = msg.landed_state
        elif kind == "STATUSTEXT":
            text = msg.text if isinstance(msg.text, str) else bytes(msg.text).decode("utf-8", "replace")
            tel.statustexts.append(text.rstrip("\x00"))


def missing_to_fly(t: Telemetry, profile: FlavourInfo, in_guided: bool, frame: Frame, require_gps: bool = True) -> list[str]:
    """What the vehicle still lacks to fly by setpoints, in words (empty: ready), from its
    telemetry ``t``; ``profile``: the autopilot's profile, ``in_guided``: in its guided mode
    (PX4 OFFBOARD).

    GPS 3D fix (GPS_RAW_INT.fix_type ≥ 3; only with ``require_gps``: a vehicle flown in
    LOCAL_NED may navigate without GPS, e.g. on motion capture); EKF: EKF_STATUS_REPORT with
    attitude, velocity and absolute position and not in constant-position mode (ArduPilot), or,
    where the autopilot sends no such report (PX4, vehicle_sim), SYS_STATUS with the AHRS
    healthy; the pre-arm checks passed where SYS_STATUS reports them; home position
    (HOME_POSITION); EKF origin (GPS_GLOBAL_ORIGIN)."""
    missing = []
    if not require_gps:
        pass
    elif t.gps_fix_type is None:
        missing.append("GPS status (no GPS_RAW_INT yet)")
    elif t.gps_fix_type < 3:
        missing.append(f"GPS 3D fix (fix_type {t.gps_fix_type}, {t.satellites} satellites)")
    if t.ekf_flags is not None:
        if (t.ekf_flags & EKF_READY_FLAGS) != EKF_READY_FLAGS or t.ekf_flags & EKF_CONST_POS_MODE:
            missing.append(f"EKF position estimate (EKF_STATUS_REPORT flags {t.ekf_flags:#06x})")
    elif t.sensors_present is None:
        missing.append("system status (no SYS_STATUS yet)")
    elif t.sensors_present & MAV_SYS_STATUS_AHRS and not (t.sensors_health or 0) & MAV_SYS_STATUS_AHRS:
        missing.append("EKF/AHRS healthy (SYS_STATUS)")
    # PX4 reports its pre-arm result as the PREARM_CHECK health bit alone (never present or
    # enabled, profile.prearm_health_only): set while the vehicle could arm in its current
    # mode. Disarmed in OFFBOARD (PX4 returns to it after landing a flight flown in OFFBOARD)
    # it stays clear until a setpoint stream runs, which the planner starts only once ready:
    # not awaited there.
    if profile.prearm_health_only:
        prearm_reported = t.sensors_present is not None and not in_guided
    else:
        prearm_reported = t.sensors_present is not None and bool(t.sensors_present & MAV_SYS_STATUS_PREARM_CHECK)
    if prearm_reported and not t.armed and not ((t.sensors_health or 0) & MAV_SYS_STATUS_PREARM_CHECK):
        reason = next((s for s in reversed(t.statustexts) if s.lower().startswith("prearm")), "")
        missing.append("pre-arm checks" + (f" ({reason})" if reason else ""))
    if profile.home_before_position and t.position_enu_m is None:
        # PX4 sends HOME_POSITION before its EKF has aligned, and no GLOBAL_POSITION_INT
        # (no LOCAL_POSITION_NED with a valid position) until it has.
        missing.append("position estimate (no GLOBAL_POSITION_INT yet)" if frame == "global" else "position estimate (no LOCAL_POSITION_NED yet)")
    if not t.home_known:
        missing.append("home position (HOME_POSITION)")
    if t.origin_global is None:
        missing.append("EKF origin (GPS_GLOBAL_ORIGIN)")
    return missing

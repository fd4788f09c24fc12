"""One simulated MAVLink vehicle: protocol, modes, guided setpoints, geofence, telemetry.

The vehicle owns no thread and no clock. Its driver (:class:`vehicle_sim.host.VehicleHost` or
a test) calls:

* :meth:`SimVehicle.advance_to` ``(t_s)``: drain pending MAVLink input, integrate the physics
  up to sim time ``t_s`` at the fixed physics rate, then send the telemetry that is due,
  stamped with sim time (``time_boot_ms`` = sim ms since boot);
* :meth:`SimVehicle.heartbeat` once per wall second (stops when :attr:`healthy` is False).

Frames: physics, fence and home live in the mission ENU frame (see :mod:`vehicle_sim.geo`);
LOCAL_NED is NED about the EKF origin (the mission origin until SET_GPS_GLOBAL_ORIGIN moves it).
"""

from __future__ import annotations

import difflib
import logging
import math
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, Literal

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
    Mode,
    flavour_info,
)
from planner.geometry import vec3
from vehicle_sim.config import Geofence, Origin, VehicleConfig, VehicleLimits
from vehicle_sim.dynamics import Command, FloatArray, PointMass
from vehicle_sim.geo import LocalFrame
from vehicle_sim.link import PROTOCOL_VERSION_ID, MavlinkLink, protocol_version_message
from vehicle_sim.payload import Measurement, Payload

log = logging.getLogger(__name__)

FORCE_MAGIC = 21196  # param2 of ARM_DISARM that forces disarm (ArduPilot)
FORCE_ARM_MAGIC = 2989  # param2 that forces arming (ArduPilot)
ARRIVAL_TOL_M = 0.1  # take-off / RTL phase completion distance (m)
STATUSTEXT_MIN_GAP_S = 1.0  # repeated warnings of the same key are rate limited (wall s)
OFFBOARD_STREAM_GAP_S = 0.5  # PX4: OFFBOARD needs setpoints faster than 2 Hz
RTL_ALT_DEFAULT_M = 15.0
PX4_TAKEOFF_ALT_DEFAULT_M = 2.5
#: MAV_CMD_DO_SET_GLOBAL_ORIGIN (common.xml, not yet in pymavlink's ardupilotmega dialect).
MAV_CMD_DO_SET_GLOBAL_ORIGIN = 611
ORIGIN_ALT_MAX_M = (2**31 - 1) / 1000.0  # GPS_GLOBAL_ORIGIN.altitude is int32 mm

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
#: Start-up stages: EKF initialising, attitude aligned (no GPS fix), ready (GPS, home, origin).
STAGES: tuple[str, ...] = ("init", "aligned", "ready")
#: ArduPilot copter FS_GCS_ENABLE -> action on GCS heartbeat loss (no SmartRTL path and no
#: DO_LAND_START in the simulator: SmartRTL falls back as ArduPilot does, 6 is RTL).
FS_GCS_ACTIONS: dict[int, str | None] = {0: None, 1: "rtl", 2: "rtl", 3: "rtl", 4: "land", 5: "land", 6: "rtl"}
#: PX4 COM_OBL_RC_ACT -> action on offboard loss. Position/Altitude/Manual need an RC
#: transmitter, which a simulated vehicle has not: PX4 then falls back to Hold.
PX4_OBL_ACTIONS: dict[int, str] = {0: "hold", 1: "hold", 2: "hold", 3: "rtl", 4: "land", 5: "hold", 6: "terminate", 7: "terminate"}
FS_GCS_TIMEOUT_DEFAULT_S = 5.0
SYSID_MYGCS_DEFAULT = 255
PREARM_DISPLAY_PERIOD_S = 30.0  # ArduPilot reports a failing pre-arm check this often (sim s)
#: ArduCopter modes whose HEARTBEAT base_mode carries MAV_MODE_FLAG_GUIDED_ENABLED.
ARDUPILOT_GUIDED_FLAG_MODES = frozenset({"AUTO", "RTL", "LOITER", "GUIDED", "POSHOLD", "BRAKE"})

# REQUEST_DATA_STREAM groups (ArduPilot's assignment of our messages).
#: As ArduCopter 4.5's STREAM_*_msgs (GCS_Mavlink.cpp); EXTENDED_SYS_STATE and HOME_POSITION
#: are in no stream there (SET_MESSAGE_INTERVAL / REQUEST_MESSAGE only): here they keep their rate.
DATA_STREAMS: dict[int, tuple[str, ...]] = {
    2: ("SYS_STATUS", "GPS_RAW_INT"),  # EXTENDED_STATUS
    6: ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED"),  # POSITION
    10: ("ATTITUDE",),  # EXTRA1
    11: ("VFR_HUD",),  # EXTRA2
    12: ("SYSTEM_TIME", "BATTERY_STATUS", "EKF_STATUS_REPORT"),  # EXTRA3
}


@dataclass(frozen=True)
class VehicleState:
    """Snapshot of what a test or a supervisor may check (true values, ENU frame).

    Attributes:
        t_s: sim time (s). armed, mode (custom_mode), mode_name, landed_state (MAV_LANDED_STATE_*).
        position_enu_m, velocity_enu_mps: true state (3,) each.
        params: every parameter value. intervals_s: telemetry intervals (None = off).
        origin: EKF origin. fence_enabled: fence on.
        stage: start-up stage (``"init"``, ``"aligned"``, ``"ready"``, see :data:`STAGES`).
        gcs_failsafe: the ArduPilot GCS failsafe is active.
    """

    t_s: float
    armed: bool
    mode: int
    mode_name: str
    landed_state: int
    position_enu_m: tuple[float, float, float]
    velocity_enu_mps: tuple[float, float, float]
    params: tuple[tuple[str, float], ...]
    intervals_s: tuple[tuple[str, float | None], ...]
    origin: Origin
    fence_enabled: bool
    stage: str = "ready"
    gcs_failsafe: bool = False


@dataclass
class _Param:
    name: str
    integer: bool
    get: Callable[[], float]
    set: Callable[[float], str | None]


class SimVehicle:
    """A simulated ArduPilot-copter or PX4 vehicle behind one MAVLink link.

    Args:
        config: the vehicle configuration.
        link: the MAVLink endpoint (sockets, parser, encoder, .tlog).
        wall: wall clock (s) used only for STATUSTEXT rate limiting and SYSTEM_TIME.
        payload: the simulated RSS payload (:meth:`measure`), or None.
    """

    def __init__(
        self,
        config: VehicleConfig,
        link: MavlinkLink,
        wall: Callable[[], float] = time.time,
        payload: Payload | None = None,
    ) -> None:
        self.config = config
        self.payload = payload
        self.link = link
        self.m = link.mavlink
        self.wall = wall
        self.info: FlavourInfo = flavour_info(config.flavour)
        self.sysid = config.sysid
        self.world = LocalFrame(config.origin)
        self.ekf = self.world
        self.limits: VehicleLimits = config.limits
        self.fence: Geofence = config.geofence
        self.guided_timeout_s = config.guided_timeout_s
        self.offboard_loss_s = config.offboard_loss_s
        self.rtl_alt_m = RTL_ALT_DEFAULT_M
        self.ready_after_s = config.ready_after_s
        self.stage = "ready" if config.ready_after_s <= 0.0 else "init"
        self.origin_set = self.stage == "ready"  # EKF origin known (ready, or set by a GCS)
        # Failsafe parameters (ArduPilot FS_GCS_*, SYSID_MYGCS; PX4 COM_OBL_RC_ACT).
        self.fs_gcs_enable = 0.0
        self.fs_gcs_timeout_s = FS_GCS_TIMEOUT_DEFAULT_S
        self.sysid_mygcs = float(SYSID_MYGCS_DEFAULT)
        self.gcs_last_seen_t: float | None = None  # sim time of the last SYSID_MYGCS heartbeat
        self.gcs_failsafe = False
        self._prearm_next_t = PREARM_DISPLAY_PERIOD_S
        #: PX4: the mode restored when the vehicle disarms (the last armable mode chosen).
        self._mode_after_disarm: Mode | None = None
        self.offboard_loss_action = 0.0
        self.takeoff_alt_m = PX4_TAKEOFF_ALT_DEFAULT_M
        self.sysid_param = float(config.sysid)
        self.h = 1.0 / config.physics_hz
        self.t = 0.0
        self._n = 0  # physics grid index: the last grid point reached is n*h
        self.healthy = True
        start = np.array(config.start_enu_m, dtype=float)
        self.home = np.array([start[0], start[1], config.ground_z_m])
        if not config.airborne:
            start[2] = config.ground_z_m
        self.pm = PointMass(
            start,
            self.limits,
            config.profile,
            lag_s=config.lag_s,
            wind_enu_mps=np.array(config.wind_enu_mps),
            drag_per_s=config.drag_per_s,
            ground_z_m=config.ground_z_m,
        )
        self.yaw_rad = 0.0
        self.armed = bool(config.airborne)
        self.flying = bool(config.airborne)
        self.mode: Mode = self.info.require_mode(self.info.air_boot_mode if config.airborne else self.info.boot_mode)
        self.landed_state = self.m.MAV_LANDED_STATE_IN_AIR if config.airborne else self.m.MAV_LANDED_STATE_ON_GROUND
        if config.airborne:
            self._hold_here()
        self.phase = ""  # takeoff / rtl sub-phase
        self.takeoff_target_z = 0.0
        self.guided_kind = ""  # kind of the last guided setpoint ("position", "velocity", "posvel")
        self.last_setpoint_t = -math.inf
        self.setpoint_times: list[float] = []
        self.speed_override_mps: float | None = None
        self.battery = 1.0
        self.noise_rng = np.random.default_rng(np.random.SeedSequence([config.seed, config.sysid, 0x5E45]))
        self._text_last: dict[str, float] = {}
        self.intervals: dict[str, float | None] = {}
        self.defaults: dict[str, float | None] = {}
        for name, hz in config.rates_hz:
            self.defaults[name] = 1.0 / hz if hz > 0 else None
        if config.flavour == "ardupilot":  # ArduPilot's EXTRA3 stream; PX4 has no such message
            self.defaults["EKF_STATUS_REPORT"] = 1.0 / config.ekf_status_hz if config.ekf_status_hz > 0 else None
        self.intervals = dict(self.defaults)
        self._due: dict[str, float] = dict.fromkeys(self.intervals, 0.0)
        #: (custom mode, armed) of the last HEARTBEAT built: a lockstep tick report repeats the
        #: heartbeat when the state changed since (:meth:`emit_due`).
        self._heartbeat_state: tuple[int, bool] | None = None
        self.params = self._build_params()
        for name, value in config.params:
            self._boot_param(name, value)
        self.commands_handled = 0
        self.ignored_messages = 0
        self.acks_sent = 0

    # ------------------------------------------------------------------ frames and helpers

    @property
    def position(self) -> FloatArray:
        """True position (3,), ENU m."""
        return self.pm.position

    def time_boot_ms(self) -> int:
        """Sim time since boot in ms (uint32 wrap)."""
        return int(round(self.t * 1000.0)) & 0xFFFFFFFF

    def enu_to_local_ned(self, p: FloatArray) -> tuple[float, float, float]:
        """Mission ENU (m) -> LOCAL_NED about the EKF origin (m)."""
        if self.ekf is self.world:
            return self.world.enu_to_ned(float(p[0]), float(p[1]), float(p[2]))
        lat, lon, alt = self.world.enu_to_geodetic(float(p[0]), float(p[1]), float(p[2]))
        return self.ekf.enu_to_ned(*self.ekf.geodetic_to_enu(lat, lon, alt))

    def local_ned_to_enu(self, n: float, e: float, d: float) -> FloatArray:
        """LOCAL_NED about the EKF origin (m) -> mission ENU (m)."""
        if self.ekf is self.world:
            return np.array(self.world.ned_to_enu(n, e, d))
        lat, lon, alt = self.ekf.enu_to_geodetic(*self.ekf.ned_to_enu(n, e, d))
        return np.array(self.world.geodetic_to_enu(lat, lon, alt))

    def vel_enu_to_ned(self, v: FloatArray) -> tuple[float, float, float]:
        """Velocity ENU -> NED (m/s) (the frames are parallel up to the axis swap)."""
        return self.world.enu_to_ned(float(v[0]), float(v[1]), float(v[2]))

    def statustext(self, severity: int, text: str, key: str | None = None) -> None:
        """Send a STATUSTEXT (≤ 50 chars); with ``key``, at most one per second of wall time."""
        if key is not None:
            now = self.wall()
            if now - self._text_last.get(key, -math.inf) < STATUSTEXT_MIN_GAP_S:
                return
            self._text_last[key] = now
        log.info("sysid %d: %s", self.sysid, text)
        self.link.send(self.m.MAVLink_statustext_message(severity, text[:50].encode("utf-8")))

    def _ack(self, msg: Any, command: int, result: int, text: str | None = None, severity: int = 4) -> int:
        """COMMAND_ACK to the sender, then the STATUSTEXT reason if any."""
        self.acks_sent += 1
        self.link.send(self.m.MAVLink_command_ack_message(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))
        if text:
            self.statustext(severity, text)
        return result

    # ------------------------------------------------------------------ readiness

    @property
    def ready(self) -> bool:
        """True once the vehicle can fly: GPS 3D fix, EKF position, home and EKF origin set."""
        return self.stage == "ready"

    def _update_readiness(self) -> None:
        """Advance the start-up stages with sim time: EKF attitude aligned at half of
        ``ready_after_s``, GPS fix, EKF position, home and origin at ``ready_after_s``."""
        if self.stage == "ready":
            return
        if self.t + 1e-9 >= self.ready_after_s:
            self._become_ready()
        elif self.stage == "init" and self.t + 1e-9 >= 0.5 * self.ready_after_s:
            self.stage = "aligned"
            if self.config.flavour == "ardupilot":
                self.statustext(6, "EKF3 IMU0 tilt alignment complete")
                self.statustext(6, "EKF3 IMU0 MAG0 initial yaw alignment complete")

    def _become_ready(self) -> None:
        """GPS fix, EKF position, home and origin set: report them at once, position first
        (a planner that sees home and origin then already has a valid position), then
        HOME_POSITION and GPS_GLOBAL_ORIGIN (ArduPilot's AP_AHRS::set_home sends both)."""
        self.stage = "ready"
        self.origin_set = True
        names = ["GPS_RAW_INT", "GLOBAL_POSITION_INT", "LOCAL_POSITION_NED", "SYS_STATUS"]
        if "EKF_STATUS_REPORT" in self.defaults:
            names.append("EKF_STATUS_REPORT")
        for name in names:
            self.link.send(self._telemetry_builder(name)())
        if self.config.flavour == "ardupilot":
            self.statustext(6, "EKF3 IMU0 origin set")
            self.statustext(6, "EKF3 IMU0 is using GPS")
        self.link.send(self.msg_home_position())
        self.link.send(self.msg_gps_global_origin())

    def _not_ready_reason(self) -> str | None:
        """The pre-arm failure of a vehicle that is not ready yet (ArduPilot "PreArm: ...",
        PX4 "Preflight Fail: ..."), or None when ready."""
        if self.stage == "ready":
            return None
        if self.config.flavour == "px4":
            if self.stage == "init":
                return "Preflight Fail: Attitude not valid"
            return "Preflight Fail: GPS fix too low"
        if self.stage == "init":
            return "PreArm: EKF attitude is bad"
        return "PreArm: Need 3D Fix"

    def _available(self, name: str) -> bool:
        """Whether telemetry message ``name`` can be sent now: before the vehicle is ready
        there is no home, no local position and (unless a GCS set one) no EKF origin; PX4
        publishes no global position either (ArduPilot sends GLOBAL_POSITION_INT with zeros)."""
        if self.stage == "ready":
            return True
        if name in ("HOME_POSITION", "LOCAL_POSITION_NED"):
            return False
        if name == "GPS_GLOBAL_ORIGIN":
            return self.origin_set
        if name == "GLOBAL_POSITION_INT":
            return self.config.flavour == "ardupilot"
        return True

    # ------------------------------------------------------------------ fence

    def fence_clamp(self, p: FloatArray, floor: FloatArray | None = None) -> FloatArray:
        """Move ``p`` (ENU m) into the fence. With ``floor`` (a reference position, normally
        the vehicle's own), the fence is widened to include it, so a vehicle already outside
        (e.g. below FENCE_ALT_MIN after take-off) is never teleported."""
        f = self.fence
        if not f.enabled:
            return p
        q = np.array(p, dtype=float)

        def lim(lo: float, hi: float, axis: int) -> tuple[float, float]:
            if floor is None:
                return lo, hi
            r = float(floor[axis])
            return min(lo, r), max(hi, r)

        zlo, zhi = lim(f.z_min_m, f.z_max_m, 2)
        q[2] = min(max(q[2], zlo), zhi)
        box = f.box
        if box is not None:
            xlo, xhi = lim(box[0], box[1], 0)
            ylo, yhi = lim(box[2], box[3], 1)
            q[0] = min(max(q[0], xlo), xhi)
            q[1] = min(max(q[1], ylo), yhi)
        if f.radius_m is not None:
            r_max = f.radius_m
            if floor is not None:
                r_max = max(r_max, math.hypot(float(floor[0] - self.home[0]), float(floor[1] - self.home[1])))
            dx, dy = q[0] - self.home[0], q[1] - self.home[1]
            r = math.hypot(dx, dy)
            if r > r_max:
                q[0] = self.home[0] + dx * r_max / r
                q[1] = self.home[1] + dy * r_max / r
        return q

    def inside_fence(self, p: FloatArray, check_floor: bool = True) -> bool:
        """True when ``p`` (ENU m) is inside the fence; ``check_floor=False`` ignores the
        altitude floor (a vehicle on the ground)."""
        if not self.fence.enabled:
            return True
        q = np.array(p, dtype=float)
        if not check_floor and q[2] < self.fence.z_min_m:
            q[2] = self.fence.z_min_m
        return bool(np.allclose(self.fence_clamp(q), q, atol=1e-9, rtol=0))

    def _motion_fence(self) -> Callable[[FloatArray], FloatArray]:
        ref = self.position.copy()
        return lambda p: self.fence_clamp(p, floor=ref)

    # ------------------------------------------------------------------ mode logic

    def _command(self, cmd: Command) -> None:
        self.pm.set_command(cmd, self.t)

    def _hold_here(self) -> None:
        self.pm.set_command(Command("hold", position=self.position.copy()), self.t)

    def set_mode(self, mode: Mode) -> str | None:
        """Switch to ``mode``; return None or the reason for refusing."""
        if mode.behaviour == "mission":
            return "Mode change failed: no mission"
        # ArduPilot copter skips its mode checks while disarmed (Copter::set_mode: "allow
        # switching to any mode if disarmed; we rely on the arming check"); PX4 does not.
        checks = self.config.flavour == "px4" or self.armed
        if checks and mode.needs_position and not self.ready and mode.custom_mode != self.mode.custom_mode:
            if self.config.flavour == "px4":
                return f"Switching to {mode.name} is currently not possible"
            return f"Mode change to {mode.name} failed: requires position"
        if mode.behaviour == "guided" and self.config.flavour == "px4" and not self._offboard_stream_ok():
            return "Offboard: no setpoint stream >2Hz"
        if mode.behaviour in ("land", "rtl") and not self.flying and not self.armed:
            self.mode = mode
            return None
        if mode.behaviour == "takeoff" and not self.armed:
            return "Takeoff: arm first"
        previous = self.mode
        self.mode = mode
        if mode.armable:
            self._mode_after_disarm = mode
        if mode.custom_mode == previous.custom_mode:
            return None
        self.phase = ""
        self.guided_kind = ""
        if not self.flying:
            self.pm.set_command(Command("idle"), self.t)
            if mode.behaviour == "takeoff":
                self._start_takeoff(self.home[2] + self.takeoff_alt_m)
            return None
        if mode.behaviour in ("hold", "guided"):
            self._hold_here()
        elif mode.behaviour == "land":
            self._start_land()
        elif mode.behaviour == "rtl":
            self._start_rtl()
        elif mode.behaviour == "takeoff":
            self._start_takeoff(max(float(self.position[2]), self.home[2] + self.takeoff_alt_m))
        if self.config.flavour == "px4":
            self.statustext(6, f"Mode {mode.name}")
        return None

    def _start_takeoff(self, z_target: float) -> None:
        self.flying = True
        self.phase = "takeoff"
        self.takeoff_target_z = z_target
        self.landed_state = self.m.MAV_LANDED_STATE_TAKEOFF
        target = np.array([self.position[0], self.position[1], z_target])
        self._command(Command("position", position=target, speed_mps=self.limits.takeoff_speed_mps))

    def _start_land(self) -> None:
        self.phase = "land"
        self.landed_state = self.m.MAV_LANDED_STATE_LANDING
        self._command(Command("velocity", velocity=np.array([0.0, 0.0, -self.limits.land_speed_mps])))

    def _start_rtl(self) -> None:
        z_rtl = max(float(self.position[2]), self.home[2] + self.rtl_alt_m)
        self.phase = "rtl_climb"
        self._command(Command("position", position=np.array([self.position[0], self.position[1], z_rtl])))

    def _touchdown(self) -> None:
        self.flying = False
        self.phase = ""
        self.landed_state = self.m.MAV_LANDED_STATE_ON_GROUND
        self.pm.set_command(Command("idle"), self.t)
        if self.armed:
            self.armed = False
            self.statustext(6, "Disarming motors" if self.config.flavour == "ardupilot" else "Landed: disarmed")
            if self.config.flavour == "px4" and self._mode_after_disarm is not None:
                # PX4 (commander's UserModeIntention::onDisarm) returns to the last armable
                # mode chosen, e.g. OFFBOARD after AUTO.LAND.
                self.mode = self._mode_after_disarm

    def _update_logic(self) -> None:
        """Mode transitions evaluated at every physics step (sim time ``self.t``)."""
        beh = self.mode.behaviour
        p = self.position
        if self.phase == "takeoff" and abs(float(p[2]) - self.takeoff_target_z) <= ARRIVAL_TOL_M:
            self.phase = ""
            self.landed_state = self.m.MAV_LANDED_STATE_IN_AIR
            if self.config.flavour == "px4":  # ArduPilot's GUIDED take-off ends silently
                self.statustext(6, "Takeoff complete")
            if beh == "takeoff":  # PX4: AUTO.TAKEOFF ends in AUTO.LOITER at the take-off point
                self.mode = self.info.require_mode(self.info.hold_mode)
                target = self.pm.command.position
                self._command(Command("hold", position=None if target is None else target.copy()))
        elif self.phase == "land" and self.flying and float(p[2]) <= self.config.ground_z_m + 1e-6:
            self._touchdown()
        elif self.phase == "rtl_climb":
            target = self.pm.command.position
            if target is not None and abs(float(p[2] - target[2])) <= ARRIVAL_TOL_M:
                self.phase = "rtl_return"
                self._command(Command("position", position=np.array([self.home[0], self.home[1], float(p[2])])))
        elif self.phase == "rtl_return" and math.hypot(float(p[0] - self.home[0]), float(p[1] - self.home[1])) <= ARRIVAL_TOL_M:
            self._start_land()
        if beh == "guided" and self.flying and self.phase == "":
            age = self.t - self.last_setpoint_t
            if self.config.flavour == "ardupilot":
                if self.guided_kind in ("velocity", "posvel") and age > self.guided_timeout_s:
                    if self.guided_kind == "velocity":
                        self._hold_here()
                    else:
                        # ArduPilot zeroes the velocity: the moving target stops where it got to.
                        cmd = self.pm.command
                        target = cmd.position
                        if cmd.moving and target is not None and cmd.velocity is not None:
                            target = target + np.asarray(cmd.velocity, dtype=float) * age
                        self._command(Command("position", position=target, fence=self._motion_fence()))
                    self.guided_kind = "position"
                    self.statustext(4, "Guided: velocity timeout, holding")
            elif self.t - (self.setpoint_times[-1] if self.setpoint_times else -math.inf) > self.offboard_loss_s:
                self.guided_kind = ""
                self._offboard_failsafe()
        self._check_gcs_failsafe()
        self._report_prearm()
        if self.flying:
            self.battery = max(0.0, self.battery - self.config.battery_drain_per_s * self.h)

    def _report_prearm(self) -> None:
        """ArduPilot's periodic pre-arm report (AP_Arming::update): while disarmed and not ready,
        the failing check as ``PreArm: ...`` every PREARM_DISPLAY_PERIOD (30 s of sim time,
        the first at 30 s after boot)."""
        if self.config.flavour != "ardupilot" or self.armed or self.t < self._prearm_next_t:
            return
        self._prearm_next_t = self.t + PREARM_DISPLAY_PERIOD_S
        reason = self._not_ready_reason()
        if reason:
            self.statustext(2, reason)

    def _offboard_failsafe(self) -> None:
        """PX4 offboard loss (no setpoint for COM_OF_LOSS_T): the COM_OBL_RC_ACT action."""
        action = PX4_OBL_ACTIONS.get(int(self.offboard_loss_action), "hold")
        if action == "hold":
            self.mode = self.info.require_mode(self.info.hold_mode)
            self._hold_here()
            self.statustext(2, "Failsafe: offboard lost, holding")
        elif action == "terminate":
            self.statustext(0, "Failsafe: offboard lost, motors off")
            self._motors_off()
        else:
            self.statustext(2, f"Failsafe: offboard lost, {'returning' if action == 'rtl' else 'landing'}")
            self.set_mode(self.info.require_mode(self.info.rtl_mode if action == "rtl" else self.info.land_mode))

    def _motors_off(self) -> None:
        """Disarm now, in the air too (flight termination): the mass drops to the ground."""
        self.armed = False
        if self.flying:
            self.position[2] = self.config.ground_z_m
            self._touchdown()

    def _on_heartbeat(self, msg: Any) -> None:
        """ArduPilot: a heartbeat from SYSID_MYGCS keeps the GCS failsafe away (or clears it)."""
        if self.config.flavour != "ardupilot" or msg.get_srcSystem() != int(self.sysid_mygcs):
            return
        self.gcs_last_seen_t = self.t
        if self.gcs_failsafe:
            self.gcs_failsafe = False
            self.statustext(4, "GCS Failsafe Cleared")

    def _check_gcs_failsafe(self) -> None:
        """ArduPilot copter GCS failsafe: FS_GCS_ENABLE set, a SYSID_MYGCS heartbeat seen once,
        none for FS_GCS_TIMEOUT (sim s): disarmed, nothing; landed, disarm; landing, go on
        landing; otherwise the FS_GCS_ENABLE action (RTL or LAND). Once per loss."""
        if self.config.flavour != "ardupilot" or self.gcs_failsafe or self.gcs_last_seen_t is None:
            return
        action = FS_GCS_ACTIONS.get(int(self.fs_gcs_enable))
        if action is None or self.t - self.gcs_last_seen_t <= self.fs_gcs_timeout_s:
            return
        self.gcs_failsafe = True
        if not self.armed:
            self.statustext(4, "GCS Failsafe")
        elif not self.flying:
            self.statustext(4, "GCS Failsafe - Disarming")
            self._motors_off()
            self.statustext(6, "Disarming motors")
        elif self.mode.behaviour == "land":
            self.statustext(4, "GCS Failsafe - Continuing Landing")
        else:
            self.statustext(4, "GCS Failsafe")
            self.set_mode(self.info.require_mode(self.info.rtl_mode if action == "rtl" else self.info.land_mode))

    def _physics_to(self, t_next: float) -> None:
        h = t_next - self.t
        if h <= 0.0:
            return
        self.pm.step(h, t_next)
        self.t = t_next
        self._update_readiness()
        if self.pm.fenced:
            self.statustext(4, "Fence: stopped at boundary", key="fence_motion")
        self._update_logic()

    # ------------------------------------------------------------------ time

    def advance_to(self, t_s: float, *, report_position: bool = False) -> None:
        """Drain MAVLink input, integrate to sim time ``t_s`` (s) on the fixed physics grid
        (plus one partial step when ``t_s`` is off the grid), then send the telemetry due.

        Args:
            t_s: target sim time (s); earlier than the current time is a no-op for physics.
            report_position: also send GLOBAL_POSITION_INT and LOCAL_POSITION_NED now, whatever
                their rate (lockstep: the planner learns the step is done from them).
        """
        self.poll()
        if t_s > self.t:
            eps = 1e-9 * max(1.0, t_s)
            while (self._n + 1) * self.h <= t_s + eps:
                self._n += 1
                self._physics_to(self._n * self.h)
            if t_s > self.t + eps:
                self._physics_to(t_s)
            else:
                self.t = max(self.t, t_s)
        self.emit_due(report_position=report_position)

    def next_due_s(self) -> float:
        """Earliest sim time (s) at which a telemetry message is due."""
        due = [self._due[n] for n, iv in self.intervals.items() if iv is not None]
        return min(due) if due else self.t + 1.0

    # ------------------------------------------------------------------ input

    def poll(self) -> int:
        """Drain and handle pending MAVLink input; return the number of messages handled."""
        msgs = self.link.receive()
        if self.link.transport.new_peers:
            self.link.transport.new_peers = 0
            self.heartbeat()  # greet a new ground station at once
        for msg in msgs:
            self.handle(msg)
        return len(msgs)

    def handle(self, msg: Any) -> None:
        """Handle one decoded MAVLink message (never raises)."""
        try:
            self._dispatch(msg)
        except Exception:  # a bad message must never take the vehicle down
            self.ignored_messages += 1
            log.exception("sysid %d: error handling %s", self.sysid, msg.get_type())

    def _for_us(self, msg: Any) -> bool:
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, self.sysid) and tc in (0, 1)

    def _dispatch(self, msg: Any) -> None:
        if msg.get_srcSystem() == self.sysid and msg.get_srcComponent() == 1:
            return  # our own echo
        mtype = msg.get_type()
        handler = getattr(self, "_on_" + mtype.lower(), None)
        if handler is None:
            return
        if hasattr(msg, "target_system") and not self._for_us(msg):
            return
        handler(msg)

    # ------------------------------------------------------------------ commands

    def _on_command_long(self, msg: Any) -> None:
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        self._command_dispatch(msg, msg.command, params, None)

    def _on_command_int(self, msg: Any) -> None:
        params = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
        self._command_dispatch(msg, msg.command, params, msg.frame)

    def _command_dispatch(self, msg: Any, command: int, p: tuple[float, ...], frame: int | None) -> None:
        m = self.m
        self.commands_handled += 1
        handlers: dict[int, Callable[[Any, tuple[float, ...], int | None], int]] = {
            m.MAV_CMD_COMPONENT_ARM_DISARM: self._cmd_arm,
            m.MAV_CMD_NAV_TAKEOFF: self._cmd_takeoff,
            m.MAV_CMD_NAV_LAND: self._cmd_land,
            m.MAV_CMD_NAV_RETURN_TO_LAUNCH: self._cmd_rtl,
            m.MAV_CMD_DO_SET_MODE: self._cmd_set_mode,
            m.MAV_CMD_SET_MESSAGE_INTERVAL: self._cmd_set_interval,
            m.MAV_CMD_GET_MESSAGE_INTERVAL: self._cmd_get_interval,
            m.MAV_CMD_REQUEST_MESSAGE: self._cmd_request_message,
            m.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: self._reply_with(m.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, self.msg_autopilot_version),
            m.MAV_CMD_REQUEST_PROTOCOL_VERSION: self._reply_with(m.MAV_CMD_REQUEST_PROTOCOL_VERSION, self.msg_protocol_version),
            m.MAV_CMD_GET_HOME_POSITION: self._cmd_get_home_position,
            m.MAV_CMD_DO_REPOSITION: self._cmd_reposition,
            m.MAV_CMD_DO_CHANGE_SPEED: self._cmd_change_speed,
            m.MAV_CMD_DO_FENCE_ENABLE: self._cmd_fence_enable,
            MAV_CMD_DO_SET_GLOBAL_ORIGIN: self._cmd_set_origin,
        }
        handler = handlers.get(command)
        if handler is None:
            self._ack(msg, command, m.MAV_RESULT_UNSUPPORTED)
            return
        acks_before = self.acks_sent
        try:
            handler(msg, p, frame)
        except Exception:  # a handler bug must still answer the command
            # Handlers validate their parameters and answer; reaching this is a bug in the
            # vehicle: logged and counted, and the sender still gets its COMMAND_ACK.
            self.ignored_messages += 1
            log.exception("sysid %d: error handling command %d", self.sysid, command)
            if self.acks_sent == acks_before:
                self._ack(msg, command, m.MAV_RESULT_FAILED, "Command: internal error", 3)

    def _prearm_failure(self) -> str | None:
        not_ready = self._not_ready_reason()
        if not_ready:
            return not_ready
        if not self.mode.armable:
            if self.config.flavour == "ardupilot":
                return f"PreArm: {self.mode.name} mode not armable"
            return f"PreArm: mode {self.mode.name} not armable"
        if self.config.flavour == "px4" and self.mode.behaviour == "guided" and not self._offboard_stream_ok():
            return "PreArm: no offboard setpoints"
        if not self.healthy:
            return "PreArm: vehicle unhealthy"
        if self.battery < 0.2:
            return "PreArm: battery low"
        if not self.inside_fence(self.position, check_floor=False):
            return "PreArm: vehicle outside fence"
        return None

    def _cmd_arm(self, msg: Any, p: tuple[float, ...], _f: int | None) -> int:
        m = self.m
        arm = p[0]
        if arm == 1.0:
            if self.armed:
                return self._ack(msg, m.MAV_CMD_COMPONENT_ARM_DISARM, m.MAV_RESULT_ACCEPTED)
            reason = None if p[1] == FORCE_ARM_MAGIC else self._prearm_failure()
            if reason and self.config.flavour == "ardupilot" and reason.startswith("PreArm: "):
                # ArduPilot runs the same checks on an arming command with the prefix "Arm: "
                # (AP_Arming::check_failed while arming); "PreArm: " is its periodic report.
                reason = "Arm: " + reason[len("PreArm: ") :]
            if reason:
                return self._ack(msg, m.MAV_CMD_COMPONENT_ARM_DISARM, m.MAV_RESULT_FAILED, reason, 2)
            self.armed = True
            self.statustext(6, "Arming motors")
            return self._ack(msg, m.MAV_CMD_COMPONENT_ARM_DISARM, m.MAV_RESULT_ACCEPTED)
        if arm == 0.0:
            if not self.armed:
                return self._ack(msg, m.MAV_CMD_COMPONENT_ARM_DISARM, m.MAV_RESULT_ACCEPTED)
            if self.flying and p[1] != FORCE_MAGIC:
                return self._ack(msg, m.MAV_CMD_COMPONENT_ARM_DISARM, m.MAV_RESULT_FAILED, "Disarm: vehicle is flying", 3)
            self.armed = False
            if self.flying:  # forced disarm in flight: the motors stop, the mass drops
                self.position[2] = self.config.ground_z_m
                self._touchdown()
            self.statustext(6, "Disarming motors")
            return self._ack(msg, m.MAV_CMD_COMPONENT_ARM_DISARM, m.MAV_RESULT_ACCEPTED)
        return self._ack(msg, m.MAV_CMD_COMPONENT_ARM_DISARM, m.MAV_RESULT_DENIED, "Arm: param1 must be 0 or 1")

    def _cmd_takeoff(self, msg: Any, p: tuple[float, ...], frame: int | None) -> int:
        m = self.m
        cmd = m.MAV_CMD_NAV_TAKEOFF
        px4 = self.config.flavour == "px4"

        def refuse(text: str) -> int:
            # ArduPilot: do_user_takeoff() returns false -> FAILED, no STATUSTEXT (measured on SITL 4.5.5)
            if px4:
                return self._ack(msg, cmd, m.MAV_RESULT_TEMPORARILY_REJECTED, text)
            return self._ack(msg, cmd, m.MAV_RESULT_FAILED)

        if not self.armed:
            return refuse("Takeoff: vehicle not armed")
        if self.flying:
            return refuse("Takeoff: already flying")
        if not self.ready:
            return refuse("Takeoff: no position estimate")
        alt = float(p[6])
        if math.isinf(alt):
            return self._ack(msg, cmd, m.MAV_RESULT_DENIED, "Takeoff: altitude is not finite")
        if px4:
            z = self.home[2] + self.takeoff_alt_m if math.isnan(alt) else self._alt_to_z(alt, frame, amsl_default=True)
        else:
            if self.mode.behaviour != "guided":
                return refuse("Takeoff: mode must be GUIDED")
            if not math.isfinite(alt):
                return self._ack(msg, cmd, m.MAV_RESULT_DENIED, "Takeoff: altitude is not a number")
            z = self._alt_to_z(alt, frame, amsl_default=False)
        if not math.isfinite(z) or z <= self.position[2] + 0.05:
            return self._ack(msg, cmd, m.MAV_RESULT_DENIED, "Takeoff: altitude must be above ground")
        if self.fence.enabled and z > self.fence.z_max_m:
            return self._ack(msg, cmd, m.MAV_RESULT_DENIED, "Takeoff: altitude above fence")
        if self.config.flavour == "px4" and self.info.takeoff_mode is not None:
            self.mode = self.info.require_mode(self.info.takeoff_mode)
        self._start_takeoff(z)
        return self._ack(msg, cmd, m.MAV_RESULT_ACCEPTED)

    def _alt_to_z(self, alt: float, frame: int | None, *, amsl_default: bool) -> float:
        """Altitude of a command (m) -> ENU z (m): AMSL for GLOBAL frames (and PX4 takeoff),
        above home otherwise."""
        m = self.m
        amsl = frame in (m.MAV_FRAME_GLOBAL, m.MAV_FRAME_GLOBAL_INT) if frame is not None else amsl_default
        if amsl:
            return alt - self.config.origin.alt_m
        if frame in (m.MAV_FRAME_GLOBAL_TERRAIN_ALT, m.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT):
            return self.config.ground_z_m + alt
        return float(self.home[2]) + alt

    def _cmd_land(self, msg: Any, _p: tuple[float, ...], _f: int | None) -> int:
        m = self.m
        mode = self.info.require_mode(self.info.land_mode)
        if not self.flying:
            return self._ack(msg, m.MAV_CMD_NAV_LAND, m.MAV_RESULT_TEMPORARILY_REJECTED, "Land: not flying")
        self.set_mode(mode)
        return self._ack(msg, m.MAV_CMD_NAV_LAND, m.MAV_RESULT_ACCEPTED)

    def _cmd_rtl(self, msg: Any, _p: tuple[float, ...], _f: int | None) -> int:
        m = self.m
        mode = self.info.require_mode(self.info.rtl_mode)
        if not self.flying:
            return self._ack(msg, m.MAV_CMD_NAV_RETURN_TO_LAUNCH, m.MAV_RESULT_TEMPORARILY_REJECTED, "RTL: not flying")
        self.set_mode(mode)
        return self._ack(msg, m.MAV_CMD_NAV_RETURN_TO_LAUNCH, m.MAV_RESULT_ACCEPTED)

    def _mode_from(self, base_mode: float, custom: float, sub: float) -> Mode | None:
        if not (math.isfinite(custom) and math.isfinite(sub)):
            return None
        if int(base_mode) & self.m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED == 0:
            return None
        if self.config.flavour == "px4":
            main = int(custom)
            if main >= 1 << 16:  # a full custom_mode word (as SET_MODE carries it)
                return self.info.mode(main)
            return self.info.mode((main << 16) | (int(sub) << 24))
        return self.info.mode(int(custom))

    def _cmd_set_mode(self, msg: Any, p: tuple[float, ...], _f: int | None) -> int:
        m = self.m
        cmd = m.MAV_CMD_DO_SET_MODE
        if not math.isfinite(p[0]):
            return self._ack(msg, cmd, m.MAV_RESULT_DENIED, "Mode: invalid base mode")
        mode = self._mode_from(p[0], p[1], p[2])
        if mode is None:
            if self.config.flavour == "ardupilot" and math.isfinite(p[1]) and int(p[0]) & m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                # Copter::set_mode -> notify_no_such_mode; _set_mode_common answers FAILED
                return self._ack(msg, cmd, m.MAV_RESULT_FAILED, f"No such mode {int(p[1]) & 0xFF}")
            return self._ack(msg, cmd, m.MAV_RESULT_DENIED, f"Mode: unknown mode {p[1]:g}")
        reason = self.set_mode(mode)
        if reason:
            return self._ack(msg, cmd, m.MAV_RESULT_FAILED, reason, 3)
        return self._ack(msg, cmd, m.MAV_RESULT_ACCEPTED)

    def _on_set_mode(self, msg: Any) -> None:
        m = self.m
        mode = self._mode_from(msg.base_mode, msg.custom_mode, 0)
        if mode is None:
            if self.config.flavour == "ardupilot" and msg.base_mode & m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                result = m.MAV_RESULT_FAILED
                self.statustext(4, f"No such mode {msg.custom_mode & 0xFF}")
            else:
                result = m.MAV_RESULT_DENIED
                self.statustext(4, f"Mode: unknown mode {msg.custom_mode}")
        else:
            reason = self.set_mode(mode)
            result = m.MAV_RESULT_FAILED if reason else m.MAV_RESULT_ACCEPTED
            if reason:
                self.statustext(3, reason)
        # ArduPilot acknowledges SET_MODE with COMMAND_ACK whose command is the message id (11).
        self.link.send(m.MAVLink_command_ack_message(m.MAVLINK_MSG_ID_SET_MODE, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))

    def _stream_name(self, msg_id: float) -> str | None:
        if not math.isfinite(msg_id):
            return None
        cls = self.m.mavlink_map.get(int(msg_id))
        if cls is None:
            return None
        name = cls.msgname
        return name if name in self.defaults else None

    def _cmd_set_interval(self, msg: Any, p: tuple[float, ...], _f: int | None) -> int:
        m = self.m
        cmd = m.MAV_CMD_SET_MESSAGE_INTERVAL
        name = self._stream_name(p[0])
        if name is None:
            # PX4 (1.15) answers FAILED for a message it has no stream for (EKF_STATUS_REPORT).
            result = m.MAV_RESULT_FAILED if self.config.flavour == "px4" else m.MAV_RESULT_DENIED
            return self._ack(msg, cmd, result, f"Interval: cannot stream msg {p[0]:g}")
        us = p[1]
        if not math.isfinite(us) or (us < 0 and us != -1):
            return self._ack(msg, cmd, m.MAV_RESULT_DENIED, "Interval: bad interval")
        if us == -1:
            self.intervals[name] = None
        elif us == 0:
            self.intervals[name] = self.defaults[name]
        else:
            self.intervals[name] = max(us * 1e-6, self.h)
        self._due[name] = self.t
        return self._ack(msg, cmd, m.MAV_RESULT_ACCEPTED)

    def _cmd_get_interval(self, msg: Any, p: tuple[float, ...], _f: int | None) -> int:
        m = self.m
        name = self._stream_name(p[0])
        if name is None:
            return self._ack(msg, m.MAV_CMD_GET_MESSAGE_INTERVAL, m.MAV_RESULT_DENIED)
        iv = self.intervals[name]
        self._ack(msg, m.MAV_CMD_GET_MESSAGE_INTERVAL, m.MAV_RESULT_ACCEPTED)
        self.link.send(m.MAVLink_message_interval_message(int(p[0]), -1 if iv is None else int(round(iv * 1e6))))
        return m.MAV_RESULT_ACCEPTED

    def _cmd_request_message(self, msg: Any, p: tuple[float, ...], _f: int | None) -> int:
        m = self.m
        cmd = m.MAV_CMD_REQUEST_MESSAGE
        if not math.isfinite(p[0]):
            return self._ack(msg, cmd, m.MAV_RESULT_DENIED)
        mid = int(p[0])
        builders: dict[int, Callable[[], Any]] = {
            m.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self.msg_autopilot_version,
            PROTOCOL_VERSION_ID: self.msg_protocol_version,
            m.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN: self.msg_gps_global_origin,
            m.MAVLINK_MSG_ID_HEARTBEAT: self.msg_heartbeat,
        }
        name = self._stream_name(mid)
        builder = builders.get(mid) or (self._telemetry_builder(name) if name else None)
        if builder is None:
            return self._ack(msg, cmd, m.MAV_RESULT_DENIED, f"Request: message {mid} not available")
        cls = m.mavlink_map.get(mid)
        if cls is not None and not self._available(cls.msgname):
            # Not available yet (no home, no origin): ArduPilot accepts the request and its
            # sender sends nothing; PX4's stream cannot send and the request is DENIED.
            if self.config.flavour == "px4":
                return self._ack(msg, cmd, m.MAV_RESULT_DENIED)
            return self._ack(msg, cmd, m.MAV_RESULT_ACCEPTED)
        self._ack(msg, cmd, m.MAV_RESULT_ACCEPTED)
        self.link.send(builder())
        return m.MAV_RESULT_ACCEPTED

    def _cmd_get_home_position(self, msg: Any, _p: tuple[float, ...], _f: int | None) -> int:
        """MAV_CMD_GET_HOME_POSITION: HOME_POSITION and GPS_GLOBAL_ORIGIN (as ArduPilot);
        without a home yet ArduPilot answers FAILED, PX4 DENIED."""
        m = self.m
        cmd = m.MAV_CMD_GET_HOME_POSITION
        if not self.ready:
            return self._ack(msg, cmd, m.MAV_RESULT_DENIED if self.config.flavour == "px4" else m.MAV_RESULT_FAILED)
        self._ack(msg, cmd, m.MAV_RESULT_ACCEPTED)
        self.link.send(self.msg_home_position())
        self.link.send(self.msg_gps_global_origin())
        return int(m.MAV_RESULT_ACCEPTED)

    def _reply_with(self, command: int, builder: Callable[[], Any]) -> Callable[[Any, tuple[float, ...], int | None], int]:
        """Handler of a command answered by ACCEPTED followed by one message."""

        def handler(msg: Any, _p: tuple[float, ...], _f: int | None) -> int:
            self._ack(msg, command, self.m.MAV_RESULT_ACCEPTED)
            self.link.send(builder())
            return int(self.m.MAV_RESULT_ACCEPTED)

        return handler

    def _cmd_reposition(self, msg: Any, p: tuple[float, ...], frame: int | None) -> int:
        """MAV_CMD_DO_REPOSITION (COMMAND_INT only): param1 ground speed (m/s; ≤ 0 or NaN:
        unchanged), param2 flags (MAV_DO_REPOSITION_FLAGS, an integer), x/y latitude and
        longitude (1e-7 deg; both 0: stay over the current position), z altitude in ``frame``
        (NaN: keep the current altitude; ±inf is not an altitude). Every parameter is
        checked before anything changes (DENIED), then the state (TEMPORARILY_REJECTED)."""
        m = self.m
        cmd = m.MAV_CMD_DO_REPOSITION
        if frame is None:
            return self._ack(msg, cmd, m.MAV_RESULT_DENIED, "Reposition: send as COMMAND_INT")
        speed_mps, flags, alt = float(p[0]), float(p[1]), float(p[6])
        if not (math.isfinite(flags) and flags == int(flags) and 0 <= flags <= 0xFFFFFFFF):
            return self._ack(msg, cmd, m.MAV_RESULT_DENIED, "Reposition: flags must be an integer")
        if math.isinf(speed_mps):
            return self._ack(msg, cmd, m.MAV_RESULT_DENIED, "Reposition: speed is not finite")
        if math.isinf(alt):
            return self._ack(msg, cmd, m.MAV_RESULT_DENIED, "Reposition: altitude is not finite")
        lat_i, lon_i = int(p[4]), int(p[5])
        if not (abs(lat_i) < 900_000_000 and abs(lon_i) <= 1_800_000_000):
            return self._ack(msg, cmd, m.MAV_RESULT_DENIED, "Reposition: invalid latitude/longitude")
        if not self.flying:
            return self._ack(msg, cmd, m.MAV_RESULT_TEMPORARILY_REJECTED, "Reposition: not flying")
        change_mode = bool(int(flags) & m.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE) and self.config.flavour == "ardupilot"
        if self.mode.behaviour != "guided" and not change_mode:
            return self._ack(msg, cmd, m.MAV_RESULT_DENIED, "Reposition: not in guided mode")
        cur = self.position
        if lat_i == 0 and lon_i == 0:
            x, y = float(cur[0]), float(cur[1])
        else:
            x, y, _ = self.world.geodetic_to_enu(lat_i * 1e-7, lon_i * 1e-7, self.config.origin.alt_m)
        z = float(cur[2]) if math.isnan(alt) else self._alt_to_z(alt, frame, amsl_default=False)
        target = np.array([x, y, z], dtype=float)
        if not np.all(np.isfinite(target)):
            return self._ack(msg, cmd, m.MAV_RESULT_DENIED, "Reposition: invalid target")
        if self.fence.action == "reject" and not self.inside_fence(target):
            return self._ack(msg, cmd, m.MAV_RESULT_DENIED, "Fence: target outside fence, refused")
        if self.mode.behaviour != "guided":
            reason = self.set_mode(self.info.require_mode(self.info.guided_mode))
            if reason:
                return self._ack(msg, cmd, m.MAV_RESULT_FAILED, reason, 3)
        previous_speed = self.speed_override_mps
        if speed_mps > 0:
            self.speed_override_mps = speed_mps
        ok = self._apply_guided(target, None, source="reposition")
        if not ok:
            self.speed_override_mps = previous_speed
        return self._ack(msg, cmd, m.MAV_RESULT_ACCEPTED if ok else m.MAV_RESULT_DENIED)

    def _cmd_change_speed(self, msg: Any, p: tuple[float, ...], _f: int | None) -> int:
        m = self.m
        if not (math.isfinite(p[1]) and (p[1] > 0 or p[1] == -1)):
            return self._ack(msg, m.MAV_CMD_DO_CHANGE_SPEED, m.MAV_RESULT_DENIED, "Speed: invalid value")
        self.speed_override_mps = None if p[1] == -1 else float(p[1])
        return self._ack(msg, m.MAV_CMD_DO_CHANGE_SPEED, m.MAV_RESULT_ACCEPTED)

    def _cmd_fence_enable(self, msg: Any, p: tuple[float, ...], _f: int | None) -> int:
        m = self.m
        if p[0] not in (0.0, 1.0):
            return self._ack(msg, m.MAV_CMD_DO_FENCE_ENABLE, m.MAV_RESULT_DENIED, "Fence: param1 must be 0 or 1")
        self.fence = replace(self.fence, enabled=p[0] == 1.0)
        self.statustext(6, f"Fence {'enabled' if self.fence.enabled else 'disabled'}")
        return self._ack(msg, m.MAV_CMD_DO_FENCE_ENABLE, m.MAV_RESULT_ACCEPTED)

    def _cmd_set_origin(self, msg: Any, p: tuple[float, ...], frame: int | None) -> int:
        m = self.m
        cmd = MAV_CMD_DO_SET_GLOBAL_ORIGIN
        if frame is None:
            lat, lon = p[4], p[5]
        else:
            lat, lon = p[4] * 1e-7, p[5] * 1e-7
        reason = self.set_ekf_origin(lat, lon, p[6])
        if reason:
            return self._ack(msg, cmd, m.MAV_RESULT_DENIED, reason)
        return self._ack(msg, cmd, m.MAV_RESULT_ACCEPTED)

    def set_ekf_origin(self, lat_deg: float, lon_deg: float, alt_m: float) -> str | None:
        """Move the EKF origin (LOCAL_NED frame) while disarmed; report GPS_GLOBAL_ORIGIN.
        Return the reason for refusing, or None."""
        if self.armed:
            return "Origin: cannot change while armed"
        try:
            origin = Origin(float(lat_deg), float(lon_deg), float(alt_m))
        except ValueError as exc:
            return f"Origin: {exc}"[:50]
        if not abs(origin.alt_m) <= ORIGIN_ALT_MAX_M:
            return "Origin: altitude out of range"
        self.ekf = self.world if origin == self.config.origin else LocalFrame(origin)
        self.origin_set = True
        self.link.send(self.msg_gps_global_origin())
        return None

    def _on_set_gps_global_origin(self, msg: Any) -> None:
        reason = self.set_ekf_origin(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
        if reason:
            self.statustext(4, reason)

    # ------------------------------------------------------------------ setpoints

    def _offboard_stream_ok(self) -> bool:
        """PX4 OFFBOARD entry: the latest setpoint is at most 0.5 s old (sim time) and, if an
        earlier one exists, came within 0.5 s of it (a stream faster than 2 Hz). One fresh
        setpoint suffices, as on PX4, so MAVSDK's "set one setpoint, then start()" works."""
        ts = self.setpoint_times
        if not ts or self.t - ts[-1] > OFFBOARD_STREAM_GAP_S:
            return False
        return len(ts) < 2 or ts[-1] - ts[-2] <= OFFBOARD_STREAM_GAP_S

    def _note_setpoint(self) -> None:
        self.setpoint_times = (self.setpoint_times + [self.t])[-3:]

    def _decode_mask(self, mask: int) -> tuple[bool, bool, str | None]:
        m = self.m
        pos_ign = mask & 7
        vel_ign = mask & 56
        acc_ign = mask & 448
        use_pos = pos_ign == 0
        use_vel = vel_ign == 0
        if pos_ign not in (0, 7) or vel_ign not in (0, 56):
            return False, False, "Setpoint: partial axis masks unsupported"
        if not use_pos and not use_vel:
            if acc_ign != 448:
                return False, False, "Setpoint: acceleration-only unsupported"
            return False, False, "Setpoint: nothing to do"
        del m
        return use_pos, use_vel, None

    def _on_set_position_target_local_ned(self, msg: Any) -> None:
        m = self.m
        self._note_setpoint()
        use_pos, use_vel, err = self._decode_mask(msg.type_mask)
        if err:
            self.statustext(4, err, key="sp_mask")
            return
        vals = [msg.x, msg.y, msg.z] if use_pos else []
        vals += [msg.vx, msg.vy, msg.vz] if use_vel else []
        if not all(math.isfinite(v) for v in vals):
            self.statustext(4, "Setpoint: non-finite values ignored", key="sp_nan")
            return
        frame = msg.coordinate_frame
        cur = self.position
        yaw = self.yaw_rad
        pos = vel = None
        if frame == m.MAV_FRAME_LOCAL_NED:
            if use_pos:
                pos = self.local_ned_to_enu(msg.x, msg.y, msg.z)
            if use_vel:
                vel = np.array(self.world.ned_to_enu(msg.vx, msg.vy, msg.vz))
        elif frame == m.MAV_FRAME_LOCAL_OFFSET_NED:
            if use_pos:
                pos = cur + np.array(self.world.ned_to_enu(msg.x, msg.y, msg.z))
            if use_vel:
                vel = np.array(self.world.ned_to_enu(msg.vx, msg.vy, msg.vz))
        elif frame in (m.MAV_FRAME_BODY_NED, m.MAV_FRAME_BODY_OFFSET_NED):
            c, s = math.cos(yaw), math.sin(yaw)
            if use_pos:
                n, e = c * msg.x - s * msg.y, s * msg.x + c * msg.y
                pos = cur + np.array(self.world.ned_to_enu(n, e, msg.z))
            if use_vel:
                n, e = c * msg.vx - s * msg.vy, s * msg.vx + c * msg.vy
                vel = np.array(self.world.ned_to_enu(n, e, msg.vz))
        else:
            self.statustext(4, f"Setpoint: frame {frame} unsupported", key="sp_frame")
            return
        self._maybe_yaw(msg)
        self._apply_guided(pos, vel, source="setpoint")

    def _on_set_position_target_global_int(self, msg: Any) -> None:
        m = self.m
        self._note_setpoint()
        use_pos, use_vel, err = self._decode_mask(msg.type_mask)
        if err:
            self.statustext(4, err, key="sp_mask")
            return
        frame = msg.coordinate_frame
        allowed = (
            m.MAV_FRAME_GLOBAL_INT,
            m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
            m.MAV_FRAME_GLOBAL,
            m.MAV_FRAME_GLOBAL_RELATIVE_ALT,
            m.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
            m.MAV_FRAME_GLOBAL_TERRAIN_ALT,
        )
        if frame not in allowed:
            self.statustext(4, f"Setpoint: frame {frame} unsupported", key="sp_frame")
            return
        vals = [msg.alt] if use_pos else []
        vals += [msg.vx, msg.vy, msg.vz] if use_vel else []
        if not all(math.isfinite(v) for v in vals) or (use_pos and not (abs(msg.lat_int) <= 900_000_000 and abs(msg.lon_int) <= 1_800_000_000)):
            self.statustext(4, "Setpoint: invalid values ignored", key="sp_nan")
            return
        pos = vel = None
        if use_pos:
            z = self._alt_to_z(float(msg.alt), frame, amsl_default=False)
            x, y, _ = self.world.geodetic_to_enu(msg.lat_int * 1e-7, msg.lon_int * 1e-7, self.config.origin.alt_m)
            pos = np.array([x, y, z])
        if use_vel:
            vel = np.array(self.world.ned_to_enu(msg.vx, msg.vy, msg.vz))
        self._maybe_yaw(msg)
        self._apply_guided(pos, vel, source="setpoint")

    def _maybe_yaw(self, msg: Any) -> None:
        if msg.type_mask & 1024 == 0 and math.isfinite(msg.yaw):
            self.yaw_rad = math.remainder(float(msg.yaw), 2.0 * math.pi)

    def _apply_guided(self, pos: FloatArray | None, vel: FloatArray | None, *, source: str) -> bool:
        """Adopt a guided target (ENU m, ENU m/s); True when accepted."""
        if self.mode.behaviour != "guided":
            return False
        if not self.armed:
            self.statustext(4, "Guided: vehicle not armed", key="sp_disarmed")
            return False
        if not self.flying:
            if self.config.flavour == "px4" and pos is not None and pos[2] > self.config.ground_z_m + 0.1:
                self.flying = True
                self.landed_state = self.m.MAV_LANDED_STATE_IN_AIR
            else:
                self.statustext(4, "Guided: take off first", key="sp_ground")
                return False
        if self.phase:
            self.phase = ""
            self.landed_state = self.m.MAV_LANDED_STATE_IN_AIR
        if pos is not None and not self.inside_fence(pos):
            if self.fence.action == "reject":
                self.statustext(4, "Fence: target outside fence, refused", key="fence_target")
                return False
            pos = self.fence_clamp(pos)
            self.statustext(4, "Fence: target outside fence, clamped", key="fence_target")
        fence = self._motion_fence()
        speed = self.speed_override_mps if source == "reposition" else None
        if pos is not None and vel is not None:
            # ArduPilot's GUIDED moves a position+velocity target along its velocity; PX4 does not.
            cmd = Command("posvel", position=pos, velocity=vel, fence=fence, moving=self.config.flavour == "ardupilot")
            kind = "posvel"
        elif pos is not None:
            cmd = Command("position", position=pos, speed_mps=speed or self.speed_override_mps, fence=fence)
            kind = "position"
        else:
            cmd = Command("velocity", velocity=vel, fence=fence)
            kind = "velocity"
        self.guided_kind = kind
        self.last_setpoint_t = self.t
        self._command(cmd)
        return True

    def _on_mission_item_int(self, msg: Any) -> None:
        self._mission_item(msg, msg.x * 1e-7, msg.y * 1e-7)

    def _on_mission_item(self, msg: Any) -> None:
        self._mission_item(msg, msg.x, msg.y)

    def _mission_item(self, msg: Any, lat: float, lon: float) -> None:
        m = self.m
        result = m.MAV_MISSION_UNSUPPORTED
        if msg.current == 2 and msg.command == m.MAV_CMD_NAV_WAYPOINT:  # ArduPilot guided "fly to"
            if math.isfinite(lat) and math.isfinite(lon) and math.isfinite(msg.z) and abs(lat) < 90 and abs(lon) <= 180:
                x, y, _ = self.world.geodetic_to_enu(lat, lon, self.config.origin.alt_m)
                z = self._alt_to_z(float(msg.z), msg.frame, amsl_default=False)
                ok = self.flying and self._apply_guided(np.array([x, y, z]), None, source="reposition")
                result = m.MAV_MISSION_ACCEPTED if ok else m.MAV_MISSION_ERROR
            else:
                result = m.MAV_MISSION_INVALID
        self.link.send(m.MAVLink_mission_ack_message(msg.get_srcSystem(), msg.get_srcComponent(), result, msg.mission_type))

    # ------------------------------------------------------------------ mission protocol

    def _on_mission_request_list(self, msg: Any) -> None:
        self.link.send(self.m.MAVLink_mission_count_message(msg.get_srcSystem(), msg.get_srcComponent(), 0, msg.mission_type))

    def _on_mission_request_int(self, msg: Any) -> None:
        m = self.m
        self.link.send(m.MAVLink_mission_ack_message(msg.get_srcSystem(), msg.get_srcComponent(), m.MAV_MISSION_INVALID_SEQUENCE, msg.mission_type))

    _on_mission_request = _on_mission_request_int

    def _on_mission_count(self, msg: Any) -> None:
        m = self.m
        result = m.MAV_MISSION_ACCEPTED if msg.count == 0 else m.MAV_MISSION_UNSUPPORTED
        self.link.send(m.MAVLink_mission_ack_message(msg.get_srcSystem(), msg.get_srcComponent(), result, msg.mission_type))

    def _on_mission_clear_all(self, msg: Any) -> None:
        m = self.m
        self.link.send(m.MAVLink_mission_ack_message(msg.get_srcSystem(), msg.get_srcComponent(), m.MAV_MISSION_ACCEPTED, msg.mission_type))

    # ------------------------------------------------------------------ streams, timesync

    def _on_request_data_stream(self, msg: Any) -> None:
        sid = msg.req_stream_id
        names: tuple[str, ...] = tuple(n for group in DATA_STREAMS.values() for n in group) if sid == 0 else DATA_STREAMS.get(sid, ())
        for name in names:
            if name not in self.intervals:
                continue
            if msg.start_stop == 0 or msg.req_message_rate == 0:
                self.intervals[name] = None
            else:
                self.intervals[name] = max(1.0 / msg.req_message_rate, self.h)
                self._due[name] = self.t

    def _on_timesync(self, msg: Any) -> None:
        if msg.tc1 == 0:
            now_ns = int(round(self.t * 1e9))
            self.link.send(self.m.MAVLink_timesync_message(now_ns, msg.ts1))

    # ------------------------------------------------------------------ MAVLink FTP

    def _on_file_transfer_protocol(self, msg: Any) -> None:
        """No file system: answer every FTP request at once so ground stations (MAVProxy's
        parameter download) fall back to the parameter protocol instead of timing out.
        Session resets are ACKed; opens/listings get NAK FileNotFound (10); the rest NAK
        UnknownCommand (7)."""
        req = bytes(msg.payload)
        if len(req) < 12:
            return
        seq, session, opcode = int.from_bytes(req[0:2], "little"), req[2], req[3]
        if opcode in (1, 2):  # TerminateSession, ResetSessions
            reply_op, size, data = 128, 0, b""
        else:
            reply_op, size = 129, 1
            data = bytes([10 if opcode in (3, 4, 6, 11, 14) else 7])
        body = ((seq + 1) & 0xFFFF).to_bytes(2, "little") + bytes([session, reply_op, size, opcode, 0, 0])
        body += bytes(4) + data
        payload = list(body + bytes(251 - len(body)))
        self.link.send(self.m.MAVLink_file_transfer_protocol_message(0, msg.get_srcSystem(), msg.get_srcComponent(), payload))

    # ------------------------------------------------------------------ parameters

    def _build_params(self) -> dict[str, _Param]:
        lim = "limits"

        def setter(attr: str, field: str, scale: float, positive: bool = True) -> Callable[[float], str | None]:
            def _set(v: float) -> str | None:
                val = v * scale
                if not math.isfinite(val) or (positive and val <= 0):
                    return "must be a finite positive number"
                try:
                    setattr(self, attr, replace(getattr(self, attr), **{field: val}))
                except ValueError as exc:
                    return str(exc)
                if attr == lim:
                    self.pm.limits = self.limits
                return None

            return _set

        def scalar(attr: str, lo: float, hi: float) -> Callable[[float], str | None]:
            def _set(v: float) -> str | None:
                if not (math.isfinite(v) and lo <= v <= hi):
                    return f"must be in [{lo:g}, {hi:g}]"
                setattr(self, attr, float(v))
                return None

            return _set

        def fence_enable(v: float) -> str | None:
            if v not in (0.0, 1.0):
                return "must be 0 or 1"
            self.fence = replace(self.fence, enabled=v == 1.0)
            return None

        def fence_alt(field: Literal["z_min_m", "z_max_m"], relative: bool) -> Callable[[float], str | None]:
            def _set(v: float) -> str | None:
                if not math.isfinite(v):
                    return "must be finite"
                z = v + (float(self.home[2]) if relative else 0.0)
                try:
                    self.fence = replace(self.fence, z_min_m=z) if field == "z_min_m" else replace(self.fence, z_max_m=z)
                except ValueError as exc:
                    return str(exc)
                return None

            return _set

        def fence_radius(v: float) -> str | None:
            if not (math.isfinite(v) and v >= 0):
                return "must be >= 0 (0 = off)"
            self.fence = replace(self.fence, radius_m=None if v == 0 else float(v))
            return None

        def radius_get() -> float:
            return 0.0 if self.fence.radius_m is None else self.fence.radius_m

        def box(field: str) -> Callable[[], float]:
            def _get() -> float:
                val = getattr(self.fence, field)
                return float("nan") if val is None else float(val)

            return _get

        def sysid_set(v: float) -> str | None:
            if not (v == int(v) and 1 <= v <= 255):
                return "must be an integer in 1..255"
            self.sysid_param = float(v)  # takes effect at reboot, as on ArduPilot
            return None

        def read_only(_v: float) -> str | None:
            return "read-only"

        def integer(attr: str, lo: int, hi: int) -> Callable[[float], str | None]:
            def _set(v: float) -> str | None:
                if not (math.isfinite(v) and v == int(v) and lo <= v <= hi):
                    return f"must be an integer in {lo}..{hi}"
                setattr(self, attr, float(v))
                return None

            return _set

        def home_z() -> float:
            return float(self.home[2])

        def z_max_get() -> float:
            return self.fence.z_max_m - home_z()

        def z_min_get() -> float:
            return self.fence.z_min_m - home_z()

        P = _Param
        common = [P("FENCE_ENABLE", True, lambda: float(self.fence.enabled), fence_enable)]
        if self.fence.has_box:  # the mission's horizontal box (read-only, ENU m)
            common += [
                P("FIMNAV_FENCE_XMIN", False, box("x_min_m"), read_only),
                P("FIMNAV_FENCE_XMAX", False, box("x_max_m"), read_only),
                P("FIMNAV_FENCE_YMIN", False, box("y_min_m"), read_only),
                P("FIMNAV_FENCE_YMAX", False, box("y_max_m"), read_only),
            ]
        if self.config.flavour == "px4":
            specific = [
                P("MAV_SYS_ID", True, lambda: self.sysid_param, sysid_set),
                P("MPC_XY_VEL_MAX", False, lambda: self.limits.speed_max_h_mps, setter(lim, "speed_max_h_mps", 1.0)),
                P("MPC_Z_VEL_MAX_UP", False, lambda: self.limits.speed_max_up_mps, setter(lim, "speed_max_up_mps", 1.0)),
                P("MPC_Z_VEL_MAX_DN", False, lambda: self.limits.speed_max_down_mps, setter(lim, "speed_max_down_mps", 1.0)),
                P("MPC_ACC_HOR_MAX", False, lambda: self.limits.accel_max_mps2, setter(lim, "accel_max_mps2", 1.0)),
                P("MPC_LAND_SPEED", False, lambda: self.limits.land_speed_mps, setter(lim, "land_speed_mps", 1.0)),
                P("MPC_TKO_SPEED", False, lambda: self.limits.takeoff_speed_mps, setter(lim, "takeoff_speed_mps", 1.0)),
                P("COM_OF_LOSS_T", False, lambda: self.offboard_loss_s, scalar("offboard_loss_s", 0.1, 60.0)),
                P("COM_OBL_RC_ACT", True, lambda: self.offboard_loss_action, integer("offboard_loss_action", 0, 7)),
                P("MIS_TAKEOFF_ALT", False, lambda: self.takeoff_alt_m, scalar("takeoff_alt_m", 0.5, 1000.0)),
                P("RTL_RETURN_ALT", False, lambda: self.rtl_alt_m, scalar("rtl_alt_m", 0.0, 1000.0)),
                P("GF_MAX_VER_DIST", False, z_max_get, fence_alt("z_max_m", True)),
                P("GF_MAX_HOR_DIST", False, radius_get, fence_radius),
                P("FIMNAV_FENCE_ZMIN", False, z_min_get, fence_alt("z_min_m", True)),
            ]
        else:
            specific = [
                P("SYSID_THISMAV", True, lambda: self.sysid_param, sysid_set),
                P("FRAME_CLASS", True, lambda: 1.0, read_only),
                P("WPNAV_SPEED", False, lambda: self.limits.speed_max_h_mps * 100, setter(lim, "speed_max_h_mps", 0.01)),
                P("WPNAV_SPEED_UP", False, lambda: self.limits.speed_max_up_mps * 100, setter(lim, "speed_max_up_mps", 0.01)),
                P("WPNAV_SPEED_DN", False, lambda: self.limits.speed_max_down_mps * 100, setter(lim, "speed_max_down_mps", 0.01)),
                P("WPNAV_ACCEL", False, lambda: self.limits.accel_max_mps2 * 100, setter(lim, "accel_max_mps2", 0.01)),
                P("LAND_SPEED", False, lambda: self.limits.land_speed_mps * 100, setter(lim, "land_speed_mps", 0.01)),
                P("PILOT_SPEED_UP", False, lambda: self.limits.takeoff_speed_mps * 100, setter(lim, "takeoff_speed_mps", 0.01)),
                P("GUID_TIMEOUT", False, lambda: self.guided_timeout_s, scalar("guided_timeout_s", 0.1, 5.0)),
                P("FS_GCS_ENABLE", True, lambda: self.fs_gcs_enable, integer("fs_gcs_enable", 0, 6)),
                P("FS_GCS_TIMEOUT", False, lambda: self.fs_gcs_timeout_s, scalar("fs_gcs_timeout_s", 2.0, 120.0)),
                P("SYSID_MYGCS", True, lambda: self.sysid_mygcs, integer("sysid_mygcs", 1, 255)),
                P("RTL_ALT", False, lambda: self.rtl_alt_m * 100, lambda v: scalar("rtl_alt_m", 0.0, 1000.0)(v / 100)),
                P("FENCE_ALT_MAX", False, z_max_get, fence_alt("z_max_m", True)),
                P("FENCE_ALT_MIN", False, z_min_get, fence_alt("z_min_m", True)),
                P("FENCE_RADIUS", False, radius_get, fence_radius),
            ]
        return {p.name: p for p in specific + common}

    def _boot_param(self, name: str, value: float) -> None:
        """Set parameter ``name`` at boot (``VehicleConfig.params``).

        Raises:
            ValueError: unknown name (with the closest known names) or a refused value.
        """
        p = self.params.get(name)
        if p is None:
            close = difflib.get_close_matches(name, list(self.params), n=3)
            hint = f"; did you mean {', '.join(close)}?" if close else f"; known: {', '.join(sorted(self.params))}"
            raise ValueError(f"parameter {name!r} is not a parameter of the simulated {self.config.flavour} vehicle{hint}")
        err = p.set(float(value))
        if err:
            raise ValueError(f"parameter {name} = {value:g}: {err}")

    def _encode_param(self, p: _Param) -> tuple[float, int]:
        m = self.m
        value = p.get()
        if not p.integer:
            return value, m.MAV_PARAM_TYPE_REAL32
        if self.info.param_bytewise:
            return struct.unpack("<f", struct.pack("<i", int(value)))[0], m.MAV_PARAM_TYPE_INT32
        return float(int(value)), m.MAV_PARAM_TYPE_INT32

    def _decode_param(self, p: _Param, raw: float) -> float:
        if p.integer and self.info.param_bytewise:
            return float(struct.unpack("<i", struct.pack("<f", raw))[0])
        return float(raw)

    def _send_param(self, p: _Param) -> None:
        names = list(self.params)
        value, ptype = self._encode_param(p)
        self.link.send(self.m.MAVLink_param_value_message(p.name.encode(), value, ptype, len(names), names.index(p.name)))

    @staticmethod
    def _param_id(raw: Any) -> str:
        if isinstance(raw, bytes):
            raw = raw.decode("utf-8", errors="replace")
        return str(raw).split("\x00")[0].strip()

    def _on_param_request_list(self, msg: Any) -> None:
        for p in self.params.values():
            self._send_param(p)

    def _on_param_request_read(self, msg: Any) -> None:
        names = list(self.params)
        if msg.param_index >= 0:
            if msg.param_index < len(names):
                self._send_param(self.params[names[msg.param_index]])
            return
        p = self.params.get(self._param_id(msg.param_id))
        if p is not None:
            self._send_param(p)

    def _on_param_set(self, msg: Any) -> None:
        name = self._param_id(msg.param_id)
        p = self.params.get(name)
        if p is None:
            self.statustext(4, f"Param {name[:16]} not found")
            return
        value = self._decode_param(p, msg.param_value)
        err = p.set(value)
        if err:
            self.statustext(4, f"Param {name}: {err}"[:50])
        self._send_param(p)

    # ------------------------------------------------------------------ telemetry

    def heartbeat(self) -> None:
        """Send one HEARTBEAT (nothing while unhealthy)."""
        if self.healthy:
            self.link.send(self.msg_heartbeat())

    def emit_due(self, *, report_position: bool = False) -> None:
        """Send every telemetry message whose interval has elapsed (sim time).

        A lockstep tick report (``report_position``) starts with a HEARTBEAT when the mode or
        the armed state changed since the last one: the 1 Hz wall-clock heartbeat spans many
        lockstep steps, and a planner must see a pilot's take-over (a ground station switching
        the mode between two ticks) with the position of the next tick, before it commands."""
        t = self.t
        if report_position and self.healthy and self._heartbeat_state not in (None, (self.mode.custom_mode, self.armed)):
            self.heartbeat()
        forced = ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED") if report_position else ()
        for name, iv in self.intervals.items():
            if iv is None:
                continue
            due = self._due[name]
            if t + 1e-9 >= due or name in forced:
                if self._available(name):
                    self.link.send(self._telemetry_builder(name)())
                nxt = due + iv
                self._due[name] = nxt if nxt > t else t + iv

    def _telemetry_builder(self, name: str) -> Callable[[], Any]:
        return getattr(self, "msg_" + name.lower())

    def _reported_position(self) -> FloatArray:
        p = self.position
        sigma = self.config.position_noise_m
        if sigma > 0.0:
            return p + self.noise_rng.normal(0.0, sigma, 3)
        return p

    def _base_mode(self) -> int:
        m = self.m
        base = m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | m.MAV_MODE_FLAG_STABILIZE_ENABLED
        if self.config.flavour == "ardupilot":
            # GCS_MAVLINK_Copter::base_mode: manual input always; GUIDED_ENABLED in the modes
            # that navigate (AUTO, RTL, LOITER, GUIDED, POSHOLD, BRAKE, ...), not in LAND.
            base |= m.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
            if self.mode.name in ARDUPILOT_GUIDED_FLAG_MODES:
                base |= m.MAV_MODE_FLAG_GUIDED_ENABLED
        elif self.mode.behaviour in ("guided", "takeoff", "land", "rtl", "mission"):
            base |= m.MAV_MODE_FLAG_GUIDED_ENABLED
        if self.armed:
            base |= m.MAV_MODE_FLAG_SAFETY_ARMED
        return base

    def msg_heartbeat(self) -> Any:
        """HEARTBEAT: QUADROTOR, ArduPilot or PX4, custom mode, armed flag, system status."""
        m = self.m
        if not self.healthy:
            status = m.MAV_STATE_CRITICAL
        elif self.config.flavour == "ardupilot":
            # GCS_MAVLINK_Copter::vehicle_system_status: CRITICAL in a failsafe, STANDBY while
            # landed (armed or not), ACTIVE in the air.
            status = m.MAV_STATE_CRITICAL if self.gcs_failsafe else (m.MAV_STATE_ACTIVE if self.flying else m.MAV_STATE_STANDBY)
        else:
            status = m.MAV_STATE_ACTIVE if self.armed else m.MAV_STATE_STANDBY
        self._heartbeat_state = (self.mode.custom_mode, self.armed)
        return m.MAVLink_heartbeat_message(m.MAV_TYPE_QUADROTOR, self.info.autopilot, self._base_mode(), self.mode.custom_mode, status, 3)

    def msg_sys_status(self) -> Any:
        """SYS_STATUS: sensors present/enabled/healthy, battery."""
        m = self.m
        sensors = (
            m.MAV_SYS_STATUS_SENSOR_3D_GYRO
            | m.MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | m.MAV_SYS_STATUS_SENSOR_3D_MAG
            | m.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
            | m.MAV_SYS_STATUS_SENSOR_GPS
            | m.MAV_SYS_STATUS_AHRS
            | m.MAV_SYS_STATUS_SENSOR_BATTERY
        )
        present = sensors | m.MAV_SYS_STATUS_PREARM_CHECK
        if self.fence.enabled:
            present |= m.MAV_SYS_STATUS_GEOFENCE
        health = sensors | (m.MAV_SYS_STATUS_GEOFENCE if self.fence.enabled else 0)
        if not self.ready:  # no GPS fix; the EKF (AHRS) is unhealthy until its attitude aligns
            health &= ~m.MAV_SYS_STATUS_SENSOR_GPS
            if self.stage == "init":
                health &= ~m.MAV_SYS_STATUS_AHRS
        if self._prearm_failure() is None or self.armed:
            health |= m.MAV_SYS_STATUS_PREARM_CHECK
        if not self.healthy:
            health = 0
        volt_mv = int(self._voltage() * 1000)
        return m.MAVLink_sys_status_message(present, present, health, 100, volt_mv, self._current_ca(), int(self.battery * 100), 0, 0, 0, 0, 0, 0)

    def _voltage(self) -> float:
        return 16.8 * (0.85 + 0.15 * self.battery)

    def _current_ca(self) -> int:
        return 1500 if self.flying else 50

    def msg_global_position_int(self) -> Any:
        """GLOBAL_POSITION_INT: lat/lon 1e7 deg, alt mm AMSL, relative_alt mm above home,
        velocity cm/s NED, heading cdeg. Before the vehicle is ready (ArduPilot only; PX4
        sends none): all zeros, as ArduPilot sends its never-set location."""
        if not self.ready:
            hdg0 = int(round(math.degrees(self.yaw_rad) % 360.0 * 100)) % 36000
            return self.m.MAVLink_global_position_int_message(self.time_boot_ms(), 0, 0, 0, 0, 0, 0, 0, hdg0)
        p = self._reported_position()
        lat, lon, alt = self.world.enu_to_geodetic(float(p[0]), float(p[1]), float(p[2]))
        vn, ve, vd = self.vel_enu_to_ned(self.pm.velocity)
        rel = float(p[2] - self.home[2])
        hdg = int(round(math.degrees(self.yaw_rad) % 360.0 * 100)) % 36000
        return self.m.MAVLink_global_position_int_message(
            self.time_boot_ms(),
            int(round(lat * 1e7)),
            int(round(lon * 1e7)),
            int(round(alt * 1000)),
            int(round(rel * 1000)),
            _i16(vn * 100),
            _i16(ve * 100),
            _i16(vd * 100),
            hdg,
        )

    def msg_local_position_ned(self) -> Any:
        """LOCAL_POSITION_NED about the EKF origin (m, m/s)."""
        p = self._reported_position()
        n, e, d = self.enu_to_local_ned(p)
        vn, ve, vd = self.vel_enu_to_ned(self.pm.velocity)
        return self.m.MAVLink_local_position_ned_message(self.time_boot_ms(), n, e, d, vn, ve, vd)

    def msg_attitude(self) -> Any:
        """ATTITUDE (rad) from the horizontal acceleration and the held yaw."""
        roll, pitch = self.pm.attitude(self.yaw_rad)
        return self.m.MAVLink_attitude_message(self.time_boot_ms(), roll, pitch, self.yaw_rad, 0.0, 0.0, 0.0)

    def msg_gps_raw_int(self) -> Any:
        """GPS_RAW_INT: 3D fix, 16 satellites; before the vehicle is ready no fix and no
        satellites (fix_type 0 while the EKF initialises, then 1), position unknown (0)."""
        if not self.ready:
            fix = self.m.GPS_FIX_TYPE_NO_GPS if self.stage == "init" else self.m.GPS_FIX_TYPE_NO_FIX
            return self.m.MAVLink_gps_raw_int_message(int(round(self.t * 1e6)), fix, 0, 0, 0, 65535, 65535, 0, 65535, 0)
        p = self._reported_position()
        lat, lon, alt = self.world.enu_to_geodetic(float(p[0]), float(p[1]), float(p[2]))
        v = self.pm.velocity
        gs = math.hypot(float(v[0]), float(v[1]))
        cog = int(round(math.degrees(math.atan2(float(v[0]), float(v[1]))) % 360.0 * 100)) % 36000
        return self.m.MAVLink_gps_raw_int_message(
            int(round(self.t * 1e6)),
            self.m.GPS_FIX_TYPE_3D_FIX,
            int(round(lat * 1e7)),
            int(round(lon * 1e7)),
            int(round(alt * 1000)),
            70,
            100,
            min(int(gs * 100), 65534),
            cog,
            16,
        )

    def msg_ekf_status_report(self) -> Any:
        """EKF_STATUS_REPORT (ArduPilot): flags (EKF_STATUS_FLAGS) and normalised variances
        (test ratios, 1 = at the innovation gate): 0 while the EKF initialises, attitude with
        constant-position mode once aligned, everything but terrain height when ready."""
        if self.stage == "ready":
            flags, var = EKF_FLAGS_READY, 0.05
        elif self.stage == "aligned":
            flags, var = EKF_FLAGS_ALIGNED, 0.5
        else:
            flags, var = 0, 0.0
        return self.m.MAVLink_ekf_status_report_message(flags, var, var, var, var, 0.0)

    def msg_home_position(self) -> Any:
        """HOME_POSITION: geodetic and local NED."""
        lat, lon, alt = self.world.enu_to_geodetic(*map(float, self.home))
        n, e, d = self.enu_to_local_ned(self.home)
        return self.m.MAVLink_home_position_message(
            int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)), n, e, d, [1.0, 0.0, 0.0, 0.0], 0, 0, 0
        )

    def msg_extended_sys_state(self) -> Any:
        """EXTENDED_SYS_STATE: landed state."""
        return self.m.MAVLink_extended_sys_state_message(self.m.MAV_VTOL_STATE_UNDEFINED, self.landed_state)

    def msg_battery_status(self) -> Any:
        """BATTERY_STATUS: a 4S LiPo draining while flying."""
        m = self.m
        cell_mv = int(self._voltage() * 1000 / 4)
        return m.MAVLink_battery_status_message(
            0,
            m.MAV_BATTERY_FUNCTION_ALL,
            m.MAV_BATTERY_TYPE_LIPO,
            32767,
            [cell_mv] * 4 + [65535] * 6,
            self._current_ca(),
            int((1.0 - self.battery) * 5000),
            -1,
            int(self.battery * 100),
        )

    def msg_vfr_hud(self) -> Any:
        """VFR_HUD: ground speed, heading, altitude AMSL, climb rate."""
        v = self.pm.velocity
        gs = math.hypot(float(v[0]), float(v[1]))
        alt = self.config.origin.alt_m + float(self.position[2])
        hdg = int(math.degrees(self.yaw_rad) % 360.0)
        return self.m.MAVLink_vfr_hud_message(gs, gs, hdg, 50 if self.flying else 0, alt, float(v[2]))

    def msg_system_time(self) -> Any:
        """SYSTEM_TIME: wall UNIX time (µs) and sim time since boot (ms)."""
        return self.m.MAVLink_system_time_message(int(self.wall() * 1e6), self.time_boot_ms())

    def msg_gps_global_origin(self) -> Any:
        """GPS_GLOBAL_ORIGIN: the EKF origin."""
        o = self.ekf.origin
        return self.m.MAVLink_gps_global_origin_message(
            int(round(o.lat_deg * 1e7)), int(round(o.lon_deg * 1e7)), int(round(o.alt_m * 1000)), int(self.t * 1e6)
        )

    def msg_autopilot_version(self) -> Any:
        """AUTOPILOT_VERSION with the capabilities MAVSDK and QGroundControl look for."""
        m = self.m
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
        return m.MAVLink_autopilot_version_message(
            caps,
            self.info.flight_sw_version,
            0,
            0,
            0,
            list(b"fimnavsm"),
            [0] * 8,
            [0] * 8,
            0,
            0,
            0x46494D0000000000 | self.sysid,
        )

    def msg_protocol_version(self) -> Any:
        """PROTOCOL_VERSION: MAVLink 2 (200), minimum 100."""
        return protocol_version_message(200, 100, 200)

    # ------------------------------------------------------------------ payload

    def measure(self, step: int) -> Measurement:
        """The simulated RSS payload's measurement for step ``step``, taken at the *true*
        position and the current sim time.

        Raises:
            ValueError: no payload configured, or the step was already measured.
        """
        if self.payload is None:
            raise ValueError(f"sysid {self.sysid}: no payload configured")
        return self.payload.measure(self.position, step, self.t)

    # ------------------------------------------------------------------ inspection

    def state(self) -> VehicleState:
        """A snapshot of the vehicle state (true values)."""
        return VehicleState(
            t_s=self.t,
            armed=self.armed,
            mode=self.mode.custom_mode,
            mode_name=self.mode.name,
            landed_state=self.landed_state,
            position_enu_m=vec3(self.position),
            velocity_enu_mps=vec3(self.pm.velocity),
            params=tuple((name, p.get()) for name, p in self.params.items()),
            intervals_s=tuple(self.intervals.items()),
            origin=self.ekf.origin,
            fence_enabled=self.fence.enabled,
            stage=self.stage,
            gcs_failsafe=self.gcs_failsafe,
        )


def _i16(v: float) -> int:
    return max(-32768, min(32767, int(round(v))))

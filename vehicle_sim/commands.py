"""Commands of a simulated vehicle: COMMAND_LONG / COMMAND_INT (arming, take-off, landing,
RTL, mode, reposition, speed, fence, EKF origin, message requests), SET_MODE and
SET_GPS_GLOBAL_ORIGIN, each answered with COMMAND_ACK (and a STATUSTEXT reason)."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from comms.autopilot import FlavourInfo
from vehicle_sim.config import Origin, VehicleConfig
from vehicle_sim.flight_state import FlightState
from vehicle_sim.frames import VehicleFrames
from vehicle_sim.geofence import FenceGuard
from vehicle_sim.modes import ModeMachine
from vehicle_sim.outbox import Outbox
from vehicle_sim.readiness import ArmingChecks, Readiness
from vehicle_sim.setpoints import GuidedSetpoints
from vehicle_sim.streams import TelemetryStreams
from vehicle_sim.telemetry import TelemetryEncoder

log = logging.getLogger("vehicle_sim.vehicle")

FORCE_MAGIC = 21196  # param2 of ARM_DISARM that forces disarm (ArduPilot)
FORCE_ARM_MAGIC = 2989  # param2 that forces arming (ArduPilot)
#: MAV_CMD_DO_SET_GLOBAL_ORIGIN (common.xml, not yet in pymavlink's ardupilotmega dialect).
MAV_CMD_DO_SET_GLOBAL_ORIGIN = 611
ORIGIN_ALT_MAX_M = (2**31 - 1) / 1000.0  # GPS_GLOBAL_ORIGIN.altitude is int32 mm

#: A command handler: (message, the seven parameters, COMMAND_INT frame or None) -> result.
Handler = Callable[[Any, tuple[float, ...], "int | None"], int]


class CommandHandler:
    """Answers the vehicle's commands.

    Args:
        config: the vehicle configuration. info: the autopilot profile. state: the flight
            state. outbox: the sending side. readiness, arming: start-up stage and pre-arm
            checks. fence, frames: the fence and the frames. modes: the mode machine.
        setpoints: the guided setpoints. streams, encoder: telemetry requests.

    Attributes:
        commands_handled: commands received. ignored_messages: handler failures (bugs).
    """

    def __init__(
        self,
        config: VehicleConfig,
        info: FlavourInfo,
        state: FlightState,
        outbox: Outbox,
        readiness: Readiness,
        arming: ArmingChecks,
        fence: FenceGuard,
        frames: VehicleFrames,
        modes: ModeMachine,
        setpoints: GuidedSetpoints,
        streams: TelemetryStreams,
        encoder: TelemetryEncoder,
    ) -> None:
        self.config = config
        self.info = info
        self.state = state
        self.outbox = outbox
        self.readiness = readiness
        self.arming = arming
        self.fence = fence
        self.frames = frames
        self.modes = modes
        self.setpoints = setpoints
        self.encoder = encoder
        self.mavlink = m = outbox.mavlink
        self.commands_handled = 0
        self.ignored_messages = 0
        self._handlers: dict[int, Handler] = {
            m.MAV_CMD_COMPONENT_ARM_DISARM: self._cmd_arm,
            m.MAV_CMD_NAV_TAKEOFF: self._cmd_takeoff,
            m.MAV_CMD_NAV_LAND: self._cmd_land,
            m.MAV_CMD_NAV_RETURN_TO_LAUNCH: self._cmd_rtl,
            m.MAV_CMD_DO_SET_MODE: self._cmd_set_mode,
            m.MAV_CMD_SET_MESSAGE_INTERVAL: streams.cmd_set_interval,
            m.MAV_CMD_GET_MESSAGE_INTERVAL: streams.cmd_get_interval,
            m.MAV_CMD_REQUEST_MESSAGE: streams.cmd_request_message,
            m.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: self._reply_with(m.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, encoder.msg_autopilot_version),
            m.MAV_CMD_REQUEST_PROTOCOL_VERSION: self._reply_with(m.MAV_CMD_REQUEST_PROTOCOL_VERSION, encoder.msg_protocol_version),
            m.MAV_CMD_GET_HOME_POSITION: self._cmd_get_home_position,
            m.MAV_CMD_DO_REPOSITION: self._cmd_reposition,
            m.MAV_CMD_DO_CHANGE_SPEED: self._cmd_change_speed,
            m.MAV_CMD_DO_FENCE_ENABLE: self._cmd_fence_enable,
            MAV_CMD_DO_SET_GLOBAL_ORIGIN: self._cmd_set_origin,
        }

    def on_command_long(self, msg: Any) -> None:
        """COMMAND_LONG: param1..param7, no frame."""
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        self._dispatch(msg, msg.command, params, None)

    def on_command_int(self, msg: Any) -> None:
        """COMMAND_INT: param1..param4, x, y (as floats), z, and its frame."""
        params = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
        self._dispatch(msg, msg.command, params, msg.frame)

    def _dispatch(self, msg: Any, command: int, p: tuple[float, ...], frame: int | None) -> None:
        m = self.mavlink
        self.commands_handled += 1
        handler = self._handlers.get(command)
        if handler is None:
            self.outbox.ack(msg, command, m.MAV_RESULT_UNSUPPORTED)
            return
        acks_before = self.outbox.acks_sent
        try:
            handler(msg, p, frame)
        except Exception:  # a handler bug must still answer the command
            # Handlers validate their parameters and answer; reaching this is a bug in the
            # vehicle: logged and counted, and the sender still gets its COMMAND_ACK.
            self.ignored_messages += 1
            log.exception("sysid %d: error handling command %d", self.config.sysid, command)
            if self.outbox.acks_sent == acks_before:
                self.outbox.ack(msg, command, m.MAV_RESULT_FAILED, "Command: internal error", 3)

    def _reply_with(self, command: int, builder: Callable[[], Any]) -> Handler:
        """Handler of a command answered by ACCEPTED followed by one message."""

        def handler(msg: Any, _p: tuple[float, ...], _f: int | None) -> int:
            self.outbox.ack(msg, command, self.mavlink.MAV_RESULT_ACCEPTED)
            self.outbox.send(builder())
            return int(self.mavlink.MAV_RESULT_ACCEPTED)

        return handler

    def _cmd_arm(self, msg: Any, p: tuple[float, ...], _f: int | None) -> int:
        m = self.mavlink
        s = self.state
        cmd = m.MAV_CMD_COMPONENT_ARM_DISARM
        arm = p[0]
        if arm == 1.0:
            if s.armed:
                return self.outbox.ack(msg, cmd, m.MAV_RESULT_ACCEPTED)
            reason = None if p[1] == FORCE_ARM_MAGIC else self.arming.prearm_failure()
            prefix = self.info.arm_command_prefix
            if reason and prefix is not None and reason.startswith("PreArm: "):
                # ArduPilot runs the same checks on an arming command with the prefix "Arm: "
                # (AP_Arming::check_failed while arming); "PreArm: " is its periodic report.
                reason = prefix + reason[len("PreArm: ") :]
            if reason:
                return self.outbox.ack(msg, cmd, m.MAV_RESULT_FAILED, reason, 2)
            s.armed = True
            self.outbox.statustext(6, "Arming motors")
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_ACCEPTED)
        if arm == 0.0:
            if not s.armed:
                return self.outbox.ack(msg, cmd, m.MAV_RESULT_ACCEPTED)
            if s.flying and p[1] != FORCE_MAGIC:
                return self.outbox.ack(msg, cmd, m.MAV_RESULT_FAILED, "Disarm: vehicle is flying", 3)
            s.armed = False
            if s.flying:  # forced disarm in flight: the motors stop, the mass drops
                s.position[2] = self.config.ground_z_m
                self.modes.touchdown()
            self.outbox.statustext(6, "Disarming motors")
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_ACCEPTED)
        return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED, "Arm: param1 must be 0 or 1")

    def _cmd_takeoff(self, msg: Any, p: tuple[float, ...], frame: int | None) -> int:
        m = self.mavlink
        s = self.state
        cmd = m.MAV_CMD_NAV_TAKEOFF
        info = self.info

        def refuse(text: str) -> int:
            # ArduPilot: do_user_takeoff() returns false -> FAILED, no STATUSTEXT (measured on SITL 4.5.5)
            if info.takeoff_refused_text:
                return self.outbox.ack(msg, cmd, info.takeoff_refused_result, text)
            return self.outbox.ack(msg, cmd, info.takeoff_refused_result)

        if not s.armed:
            return refuse("Takeoff: vehicle not armed")
        if s.flying:
            return refuse("Takeoff: already flying")
        if not self.readiness.ready:
            return refuse("Takeoff: no position estimate")
        alt = float(p[6])
        if math.isinf(alt):
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED, "Takeoff: altitude is not finite")
        if info.takeoff_mode is not None:  # PX4: AUTO.TAKEOFF from any mode, AMSL altitude
            z = s.home[2] + self.modes.takeoff_alt_m if math.isnan(alt) else self.frames.alt_to_z(alt, frame, amsl_default=True)
        else:
            if s.mode.behaviour != "guided":
                return refuse("Takeoff: mode must be GUIDED")
            if not math.isfinite(alt):
                return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED, "Takeoff: altitude is not a number")
            z = self.frames.alt_to_z(alt, frame, amsl_default=False)
        if not math.isfinite(z) or z <= s.position[2] + 0.05:
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED, "Takeoff: altitude must be above ground")
        if self.fence.fence.enabled and z > self.fence.fence.z_max_m:
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED, "Takeoff: altitude above fence")
        if info.takeoff_mode is not None:
            s.mode = info.require_mode(info.takeoff_mode)
        self.modes.start_takeoff(z)
        return self.outbox.ack(msg, cmd, m.MAV_RESULT_ACCEPTED)

    def _cmd_land(self, msg: Any, _p: tuple[float, ...], _f: int | None) -> int:
        m = self.mavlink
        mode = self.info.require_mode(self.info.land_mode)
        if not self.state.flying:
            return self.outbox.ack(msg, m.MAV_CMD_NAV_LAND, m.MAV_RESULT_TEMPORARILY_REJECTED, "Land: not flying")
        self.modes.set_mode(mode)
        return self.outbox.ack(msg, m.MAV_CMD_NAV_LAND, m.MAV_RESULT_ACCEPTED)

    def _cmd_rtl(self, msg: Any, _p: tuple[float, ...], _f: int | None) -> int:
        m = self.mavlink
        mode = self.info.require_mode(self.info.rtl_mode)
        if not self.state.flying:
            return self.outbox.ack(msg, m.MAV_CMD_NAV_RETURN_TO_LAUNCH, m.MAV_RESULT_TEMPORARILY_REJECTED, "RTL: not flying")
        self.modes.set_mode(mode)
        return self.outbox.ack(msg, m.MAV_CMD_NAV_RETURN_TO_LAUNCH, m.MAV_RESULT_ACCEPTED)

    def _cmd_set_mode(self, msg: Any, p: tuple[float, ...], _f: int | None) -> int:
        m = self.mavlink
        cmd = m.MAV_CMD_DO_SET_MODE
        if not math.isfinite(p[0]):
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED, "Mode: invalid base mode")
        mode = self.modes.mode_from(p[0], p[1], p[2])
        if mode is None:
            if self.info.unknown_mode_no_such_mode and math.isfinite(p[1]) and int(p[0]) & m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                # Copter::set_mode -> notify_no_such_mode; _set_mode_common answers FAILED
                return self.outbox.ack(msg, cmd, m.MAV_RESULT_FAILED, f"No such mode {int(p[1]) & 0xFF}")
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED, f"Mode: unknown mode {p[1]:g}")
        reason = self.modes.set_mode(mode)
        if reason:
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_FAILED, reason, 3)
        return self.outbox.ack(msg, cmd, m.MAV_RESULT_ACCEPTED)

    def on_set_mode(self, msg: Any) -> None:
        """SET_MODE (the message): as DO_SET_MODE; ArduPilot acknowledges it with COMMAND_ACK
        whose command is the message id (11)."""
        m = self.mavlink
        mode = self.modes.mode_from(msg.base_mode, msg.custom_mode, 0)
        if mode is None:
            if self.info.unknown_mode_no_such_mode and msg.base_mode & m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                result = m.MAV_RESULT_FAILED
                self.outbox.statustext(4, f"No such mode {msg.custom_mode & 0xFF}")
            else:
                result = m.MAV_RESULT_DENIED
                self.outbox.statustext(4, f"Mode: unknown mode {msg.custom_mode}")
        else:
            reason = self.modes.set_mode(mode)
            result = m.MAV_RESULT_FAILED if reason else m.MAV_RESULT_ACCEPTED
            if reason:
                self.outbox.statustext(3, reason)
        self.outbox.send(m.MAVLink_command_ack_message(m.MAVLINK_MSG_ID_SET_MODE, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))

    def _cmd_get_home_position(self, msg: Any, _p: tuple[float, ...], _f: int | None) -> int:
        """MAV_CMD_GET_HOME_POSITION: HOME_POSITION and GPS_GLOBAL_ORIGIN (as ArduPilot);
        without a home yet ArduPilot answers FAILED, PX4 DENIED."""
        m = self.mavlink
        cmd = m.MAV_CMD_GET_HOME_POSITION
        if not self.readiness.ready:
            return self.outbox.ack(msg, cmd, self.info.home_unknown_result)
        self.outbox.ack(msg, cmd, m.MAV_RESULT_ACCEPTED)
        self.outbox.send(self.encoder.msg_home_position())
        self.outbox.send(self.encoder.msg_gps_global_origin())
        return int(m.MAV_RESULT_ACCEPTED)

    def _cmd_reposition(self, msg: Any, p: tuple[float, ...], frame: int | None) -> int:
        """MAV_CMD_DO_REPOSITION (COMMAND_INT only): param1 ground speed (m/s; ≤ 0 or NaN:
        unchanged), param2 flags (MAV_DO_REPOSITION_FLAGS, an integer), x/y latitude and
        longitude (1e-7 deg; both 0: stay over the current position), z altitude in ``frame``
        (NaN: keep the current altitude; ±inf is not an altitude). Every parameter is
        checked before anything changes (DENIED), then the state (TEMPORARILY_REJECTED)."""
        m = self.mavlink
        s = self.state
        cmd = m.MAV_CMD_DO_REPOSITION
        if frame is None:
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED, "Reposition: send as COMMAND_INT")
        speed_mps, flags, alt = float(p[0]), float(p[1]), float(p[6])
        if not (math.isfinite(flags) and flags == int(flags) and 0 <= flags <= 0xFFFFFFFF):
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED, "Reposition: flags must be an integer")
        if math.isinf(speed_mps):
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED, "Reposition: speed is not finite")
        if math.isinf(alt):
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED, "Reposition: altitude is not finite")
        lat_i, lon_i = int(p[4]), int(p[5])
        if not (abs(lat_i) < 900_000_000 and abs(lon_i) <= 1_800_000_000):
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED, "Reposition: invalid latitude/longitude")
        if not s.flying:
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_TEMPORARILY_REJECTED, "Reposition: not flying")
        change_mode = bool(int(flags) & m.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE) and self.info.reposition_changes_mode
        if s.mode.behaviour != "guided" and not change_mode:
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED, "Reposition: not in guided mode")
        cur = s.position
        if lat_i == 0 and lon_i == 0:
            x, y = float(cur[0]), float(cur[1])
        else:
            x, y = self.frames.horizontal_enu(lat_i * 1e-7, lon_i * 1e-7)
        z = float(cur[2]) if math.isnan(alt) else self.frames.alt_to_z(alt, frame, amsl_default=False)
        target = np.array([x, y, z], dtype=float)
        if not np.all(np.isfinite(target)):
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED, "Reposition: invalid target")
        if self.fence.fence.action == "reject" and not self.fence.inside(target):
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED, "Fence: target outside fence, refused")
        if s.mode.behaviour != "guided":
            reason = self.modes.set_mode(self.info.require_mode(self.info.guided_mode))
            if reason:
                return self.outbox.ack(msg, cmd, m.MAV_RESULT_FAILED, reason, 3)
        sp = self.setpoints
        previous_speed = sp.speed_override_mps
        if speed_mps > 0:
            sp.speed_override_mps = speed_mps
        ok = sp.apply_guided(target, None, source="reposition")
        if not ok:
            sp.speed_override_mps = previous_speed
        return self.outbox.ack(msg, cmd, m.MAV_RESULT_ACCEPTED if ok else m.MAV_RESULT_DENIED)

    def _cmd_change_speed(self, msg: Any, p: tuple[float, ...], _f: int | None) -> int:
        m = self.mavlink
        if not (math.isfinite(p[1]) and (p[1] > 0 or p[1] == -1)):
            return self.outbox.ack(msg, m.MAV_CMD_DO_CHANGE_SPEED, m.MAV_RESULT_DENIED, "Speed: invalid value")
        self.setpoints.speed_override_mps = None if p[1] == -1 else float(p[1])
        return self.outbox.ack(msg, m.MAV_CMD_DO_CHANGE_SPEED, m.MAV_RESULT_ACCEPTED)

    def _cmd_fence_enable(self, msg: Any, p: tuple[float, ...], _f: int | None) -> int:
        m = self.mavlink
        if p[0] not in (0.0, 1.0):
            return self.outbox.ack(msg, m.MAV_CMD_DO_FENCE_ENABLE, m.MAV_RESULT_DENIED, "Fence: param1 must be 0 or 1")
        self.fence.fence = replace(self.fence.fence, enabled=p[0] == 1.0)
        self.outbox.statustext(6, f"Fence {'enabled' if self.fence.fence.enabled else 'disabled'}")
        return self.outbox.ack(msg, m.MAV_CMD_DO_FENCE_ENABLE, m.MAV_RESULT_ACCEPTED)

    def _cmd_set_origin(self, msg: Any, p: tuple[float, ...], frame: int | None) -> int:
        m = self.mavlink
        cmd = MAV_CMD_DO_SET_GLOBAL_ORIGIN
        if frame is None:
            lat, lon = p[4], p[5]
        else:
            lat, lon = p[4] * 1e-7, p[5] * 1e-7
        reason = self.set_ekf_origin(lat, lon, p[6])
        if reason:
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED, reason)
        return self.outbox.ack(msg, cmd, m.MAV_RESULT_ACCEPTED)

    def set_ekf_origin(self, lat_deg: float, lon_deg: float, alt_m: float) -> str | None:
        """Move the EKF origin (LOCAL_NED frame) while disarmed; report GPS_GLOBAL_ORIGIN.
        Return the reason for refusing, or None."""
        if self.state.armed:
            return "Origin: cannot change while armed"
        try:
            origin = Origin(float(lat_deg), float(lon_deg), float(alt_m))
        except ValueError as exc:
            return f"Origin: {exc}"[:50]
        if not abs(origin.alt_m) <= ORIGIN_ALT_MAX_M:
            return "Origin: altitude out of range"
        self.frames.set_ekf_origin(origin)
        self.readiness.origin_set = True
        self.outbox.send(self.encoder.msg_gps_global_origin())
        return None

    def on_set_gps_global_origin(self, msg: Any) -> None:
        """SET_GPS_GLOBAL_ORIGIN (lat/lon 1e-7 deg, altitude mm): as DO_SET_GLOBAL_ORIGIN."""
        reason = self.set_ekf_origin(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
        if reason:
            self.outbox.statustext(4, reason)

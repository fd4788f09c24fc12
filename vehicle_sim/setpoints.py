"""Guided setpoints of a simulated vehicle: SET_POSITION_TARGET_LOCAL_NED / _GLOBAL_INT, the
guided target they become, and the guided timeouts (ArduPilot GUID_TIMEOUT, PX4 offboard loss)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from comms.autopilot import FlavourInfo
from vehicle_sim.config import VehicleConfig
from vehicle_sim.dynamics import Command, FloatArray
from vehicle_sim.flight_state import FlightState
from vehicle_sim.frames import VehicleFrames
from vehicle_sim.geofence import FenceGuard
from vehicle_sim.outbox import Outbox

#: PX4: OFFBOARD needs setpoints faster than 2 Hz (sim s between two setpoints).
OFFBOARD_STREAM_GAP_S = 0.5


class GuidedSetpoints:
    """Turns setpoint messages into the guided target of the point mass.

    Args:
        config: the vehicle configuration (flavour, ground height, default timeouts).
        info: the autopilot profile. state: the flight state. outbox: STATUSTEXT.
        fence: the fence. frames: the vehicle's frames.

    Attributes:
        guided_kind: kind of the last guided target (``"position"``, ``"velocity"``,
            ``"posvel"``; ``""`` none).
        last_setpoint_t_s: sim time of the last adopted guided target (s).
        setpoint_times_s: sim times of the last three setpoint messages (s).
        speed_override_mps: MAV_CMD_DO_CHANGE_SPEED / DO_REPOSITION speed (m/s), None: limits.
        guided_timeout_s: ArduPilot GUID_TIMEOUT (sim s). offboard_loss_s: PX4 COM_OF_LOSS_T.
    """

    def __init__(
        self, config: VehicleConfig, info: FlavourInfo, state: FlightState, outbox: Outbox, fence: FenceGuard, frames: VehicleFrames
    ) -> None:
        self.config = config
        self.info = info
        self.state = state
        self.outbox = outbox
        self.fence = fence
        self.frames = frames
        self.mavlink = outbox.mavlink
        self.guided_kind = ""
        self.last_setpoint_t_s = -math.inf
        self.setpoint_times_s: list[float] = []
        self.speed_override_mps: float | None = None
        self.guided_timeout_s = config.guided_timeout_s
        self.offboard_loss_s = config.offboard_loss_s

    def offboard_stream_ok(self) -> bool:
        """PX4 OFFBOARD entry: the latest setpoint is at most 0.5 s old (sim time) and, if an
        earlier one exists, came within 0.5 s of it (a stream faster than 2 Hz). One fresh
        setpoint suffices, as on PX4, so MAVSDK's "set one setpoint, then start()" works."""
        ts = self.setpoint_times_s
        if not ts or self.state.t_s - ts[-1] > OFFBOARD_STREAM_GAP_S:
            return False
        return len(ts) < 2 or ts[-1] - ts[-2] <= OFFBOARD_STREAM_GAP_S

    def _note_setpoint(self) -> None:
        self.setpoint_times_s = (self.setpoint_times_s + [self.state.t_s])[-3:]

    @staticmethod
    def _decode_mask(mask: int) -> tuple[bool, bool, str | None]:
        """(use position, use velocity, refusal) of a POSITION_TARGET_TYPEMASK."""
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
        return use_pos, use_vel, None

    def _begin_setpoint(self, msg: Any) -> tuple[bool, bool] | None:
        """Note a setpoint's arrival and decode its type mask: (use position, use velocity), or
        None after a STATUSTEXT naming a mask it cannot fly."""
        self._note_setpoint()
        use_pos, use_vel, err = self._decode_mask(msg.type_mask)
        if err:
            self.outbox.statustext(4, err, key="sp_mask")
            return None
        return use_pos, use_vel

    def on_set_position_target_local_ned(self, msg: Any) -> None:
        """SET_POSITION_TARGET_LOCAL_NED in LOCAL_NED, LOCAL_OFFSET_NED or a BODY frame."""
        m = self.mavlink
        masks = self._begin_setpoint(msg)
        if masks is None:
            return
        use_pos, use_vel = masks
        vals = [msg.x, msg.y, msg.z] if use_pos else []
        vals += [msg.vx, msg.vy, msg.vz] if use_vel else []
        if not all(math.isfinite(v) for v in vals):
            self.outbox.statustext(4, "Setpoint: non-finite values ignored", key="sp_nan")
            return
        frame = msg.coordinate_frame
        if frame in (m.MAV_FRAME_BODY_NED, m.MAV_FRAME_BODY_OFFSET_NED):
            c, s = math.cos(self.state.yaw_rad), math.sin(self.state.yaw_rad)
            x, y = c * msg.x - s * msg.y, s * msg.x + c * msg.y
            vx, vy = c * msg.vx - s * msg.vy, s * msg.vx + c * msg.vy
        else:
            x, y, vx, vy = msg.x, msg.y, msg.vx, msg.vy
        pos = vel = None
        if frame == m.MAV_FRAME_LOCAL_NED:
            if use_pos:
                pos = self.frames.local_ned_to_enu(x, y, msg.z)
        elif frame in (m.MAV_FRAME_LOCAL_OFFSET_NED, m.MAV_FRAME_BODY_NED, m.MAV_FRAME_BODY_OFFSET_NED):
            if use_pos:
                pos = self.state.position + self.frames.vel_ned_to_enu(x, y, msg.z)
        else:
            self.outbox.statustext(4, f"Setpoint: frame {frame} unsupported", key="sp_frame")
            return
        if use_vel:
            vel = self.frames.vel_ned_to_enu(vx, vy, msg.vz)
        self._maybe_yaw(msg)
        self.apply_guided(pos, vel, source="setpoint")

    def on_set_position_target_global_int(self, msg: Any) -> None:
        """SET_POSITION_TARGET_GLOBAL_INT in a GLOBAL (AMSL, relative or terrain) frame."""
        m = self.mavlink
        masks = self._begin_setpoint(msg)
        if masks is None:
            return
        use_pos, use_vel = masks
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
            self.outbox.statustext(4, f"Setpoint: frame {frame} unsupported", key="sp_frame")
            return
        vals = [msg.alt] if use_pos else []
        vals += [msg.vx, msg.vy, msg.vz] if use_vel else []
        if not all(math.isfinite(v) for v in vals) or (use_pos and not (abs(msg.lat_int) <= 900_000_000 and abs(msg.lon_int) <= 1_800_000_000)):
            self.outbox.statustext(4, "Setpoint: invalid values ignored", key="sp_nan")
            return
        pos = vel = None
        if use_pos:
            z = self.frames.alt_to_z(float(msg.alt), frame, amsl_default=False)
            x, y = self.frames.horizontal_enu(msg.lat_int * 1e-7, msg.lon_int * 1e-7)
            pos = np.array([x, y, z])
        if use_vel:
            vel = self.frames.vel_ned_to_enu(msg.vx, msg.vy, msg.vz)
        self._maybe_yaw(msg)
        self.apply_guided(pos, vel, source="setpoint")

    def _maybe_yaw(self, msg: Any) -> None:
        if msg.type_mask & 1024 == 0 and math.isfinite(msg.yaw):
            self.state.yaw_rad = math.remainder(float(msg.yaw), 2.0 * math.pi)

    def apply_guided(self, pos: FloatArray | None, vel: FloatArray | None, *, source: str) -> bool:
        """Adopt a guided target (ENU m, ENU m/s); True when accepted. ``source`` is
        ``"reposition"`` for DO_REPOSITION and guided MISSION_ITEMs (they fly at the speed
        override), ``"setpoint"`` otherwise."""
        s = self.state
        m = self.mavlink
        if s.mode.behaviour != "guided":
            return False
        if not s.armed:
            self.outbox.statustext(4, "Guided: vehicle not armed", key="sp_disarmed")
            return False
        if not s.flying:
            if self.info.takeoff_by_setpoint and pos is not None and pos[2] > self.config.ground_z_m + 0.1:
                s.flying = True
                s.landed_state = m.MAV_LANDED_STATE_IN_AIR
            else:
                self.outbox.statustext(4, "Guided: take off first", key="sp_ground")
                return False
        if s.phase:
            s.phase = ""
            s.landed_state = m.MAV_LANDED_STATE_IN_AIR
        if pos is not None and not self.fence.inside(pos):
            if self.fence.fence.action == "reject":
                self.outbox.statustext(4, "Fence: target outside fence, refused", key="fence_target")
                return False
            pos = self.fence.clamp(pos)
            self.outbox.statustext(4, "Fence: target outside fence, clamped", key="fence_target")
        fence = self.fence.motion_fence(s.position)
        speed = self.speed_override_mps if source == "reposition" else None
        if pos is not None and vel is not None:
            # ArduPilot's GUIDED moves a position+velocity target along its velocity; PX4 does not.
            cmd = Command("posvel", position=pos, velocity=vel, fence=fence, moving=self.info.posvel_target_moves)
            kind = "posvel"
        elif pos is not None:
            cmd = Command("position", position=pos, speed_mps=speed or self.speed_override_mps, fence=fence)
            kind = "position"
        else:
            cmd = Command("velocity", velocity=vel, fence=fence)
            kind = "velocity"
        self.guided_kind = kind
        self.last_setpoint_t_s = s.t_s
        s.command(cmd)
        return True

    def check_timeout(self) -> bool:
        """At each physics step in the guided mode, flying, outside a phase: ArduPilot drops a
        velocity (or moving position+velocity) target older than GUID_TIMEOUT and holds; PX4
        loses OFFBOARD after COM_OF_LOSS_T without a setpoint. Returns True on that PX4 loss
        (the caller runs the offboard failsafe)."""
        s = self.state
        age = s.t_s - self.last_setpoint_t_s
        if not self.info.guided_needs_setpoint_stream:
            if self.guided_kind in ("velocity", "posvel") and age > self.guided_timeout_s:
                if self.guided_kind == "velocity":
                    s.hold_here()
                else:
                    # ArduPilot zeroes the velocity: the moving target stops where it got to.
                    cmd = s.pm.command
                    target = cmd.position
                    if cmd.moving and target is not None and cmd.velocity is not None:
                        target = target + np.asarray(cmd.velocity, dtype=float) * age
                    s.command(Command("position", position=target, fence=self.fence.motion_fence(s.position)))
                self.guided_kind = "position"
                self.outbox.statustext(4, "Guided: velocity timeout, holding")
            return False
        if s.t_s - (self.setpoint_times_s[-1] if self.setpoint_times_s else -math.inf) > self.offboard_loss_s:
            self.guided_kind = ""
            return True
        return False

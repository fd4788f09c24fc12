"""The flight-mode state machine of a simulated vehicle: mode changes, take-off, landing and
return-to-launch sequences, touchdown (modes and their numbers: :mod:`comms.autopilot`)."""

from __future__ import annotations

import math

import numpy as np

from comms.autopilot import Behaviour, FlavourInfo, Mode
from vehicle_sim.config import VehicleConfig
from vehicle_sim.dynamics import Command
from vehicle_sim.flight_state import FlightState
from vehicle_sim.outbox import Outbox
from vehicle_sim.readiness import Readiness
from vehicle_sim.setpoints import GuidedSetpoints

#: Take-off / RTL phase completion distance (m).
ARRIVAL_TOL_M = 0.1
RTL_ALT_DEFAULT_M = 15.0
PX4_TAKEOFF_ALT_DEFAULT_M = 2.5


class ModeMachine:
    """Mode changes and the phases of take-off, landing and RTL.

    Args:
        config: the vehicle configuration. info: the autopilot profile.
        state: the flight state. outbox: STATUSTEXT. readiness: the start-up stage (modes
            that need a position). setpoints: the guided setpoints (the PX4 OFFBOARD stream
            rule; a mode change forgets the guided target).

    Attributes:
        rtl_alt_m: RTL return height above home (m; ArduPilot RTL_ALT, PX4 RTL_RETURN_ALT).
        takeoff_alt_m: PX4 MIS_TAKEOFF_ALT (m above home).
        mode_after_disarm: PX4: the mode restored when the vehicle disarms (the last armable
            mode chosen).
    """

    def __init__(
        self, config: VehicleConfig, info: FlavourInfo, state: FlightState, outbox: Outbox, readiness: Readiness, setpoints: GuidedSetpoints
    ) -> None:
        self.config = config
        self.readiness = readiness
        self.info = info
        self.state = state
        self.outbox = outbox
        self.setpoints = setpoints
        self.mavlink = outbox.mavlink
        self.rtl_alt_m = RTL_ALT_DEFAULT_M
        self.takeoff_alt_m = PX4_TAKEOFF_ALT_DEFAULT_M
        self.mode_after_disarm: Mode | None = None

    def set_mode(self, mode: Mode) -> str | None:
        """Switch to ``mode``; return None or the reason for refusing."""
        s = self.state
        if mode.behaviour == "mission":
            return "Mode change failed: no mission"
        # ArduPilot copter skips its mode checks while disarmed (Copter::set_mode: "allow
        # switching to any mode if disarmed; we rely on the arming check"); PX4 does not.
        checks = self.info.mode_checks_disarmed or s.armed
        if checks and mode.needs_position and not self.readiness.ready and mode.custom_mode != s.mode.custom_mode:
            return self.info.needs_position_text.format(mode=mode.name)
        if mode.behaviour == "guided" and self.info.guided_needs_setpoint_stream and not self.setpoints.offboard_stream_ok():
            return "Offboard: no setpoint stream >2Hz"
        if mode.behaviour in ("land", "rtl") and not s.flying and not s.armed:
            s.mode = mode
            return None
        if mode.behaviour == "takeoff" and not s.armed:
            return "Takeoff: arm first"
        previous = s.mode
        s.mode = mode
        if mode.armable:
            self.mode_after_disarm = mode
        if mode.custom_mode == previous.custom_mode:
            return None
        s.phase = ""
        self.setpoints.guided_kind = ""
        if not s.flying:
            s.pm.set_command(Command("idle"), s.t_s)
            if mode.behaviour == "takeoff":
                self.start_takeoff(s.home[2] + self.takeoff_alt_m)
            return None
        if mode.behaviour in ("hold", "guided"):
            s.hold_here()
        elif mode.behaviour == "land":
            self.start_land()
        elif mode.behaviour == "rtl":
            self.start_rtl()
        elif mode.behaviour == "takeoff":
            self.start_takeoff(max(float(s.position[2]), s.home[2] + self.takeoff_alt_m))
        if self.info.mode_change_text is not None:
            self.outbox.statustext(6, self.info.mode_change_text.format(mode=mode.name))
        return None

    def start_takeoff(self, z_target_m: float) -> None:
        """Climb straight up to ENU height ``z_target_m`` (m) at the take-off speed."""
        s = self.state
        s.flying = True
        s.phase = "takeoff"
        s.takeoff_target_z_m = z_target_m
        s.landed_state = self.mavlink.MAV_LANDED_STATE_TAKEOFF
        target = np.array([s.position[0], s.position[1], z_target_m])
        s.command(Command("position", position=target, speed_mps=s.limits.takeoff_speed_mps))

    def start_land(self) -> None:
        """Descend at the landing speed until touchdown."""
        s = self.state
        s.phase = "land"
        s.landed_state = self.mavlink.MAV_LANDED_STATE_LANDING
        s.command(Command("velocity", velocity=np.array([0.0, 0.0, -s.limits.land_speed_mps])))

    def start_rtl(self) -> None:
        """Return to launch: climb to the RTL height, fly home, land."""
        s = self.state
        z_rtl = max(float(s.position[2]), s.home[2] + self.rtl_alt_m)
        s.phase = "rtl_climb"
        s.command(Command("position", position=np.array([s.position[0], s.position[1], z_rtl])))

    def touchdown(self) -> None:
        """On the ground: idle, and disarm (PX4 then returns to the last armable mode)."""
        s = self.state
        s.flying = False
        s.phase = ""
        s.landed_state = self.mavlink.MAV_LANDED_STATE_ON_GROUND
        s.pm.set_command(Command("idle"), s.t_s)
        if s.armed:
            s.armed = False
            self.outbox.statustext(6, self.info.landed_disarm_text)
            if self.info.restore_mode_after_disarm and self.mode_after_disarm is not None:
                # PX4 (commander's UserModeIntention::onDisarm) returns to the last armable
                # mode chosen, e.g. OFFBOARD after AUTO.LAND.
                s.mode = self.mode_after_disarm

    def motors_off(self) -> None:
        """Disarm now, in the air too (flight termination): the mass drops to the ground."""
        s = self.state
        s.armed = False
        if s.flying:
            s.position[2] = self.config.ground_z_m
            self.touchdown()

    def update_phase(self) -> Behaviour:
        """Phase transitions at each physics step (take-off reached, touchdown, RTL climb and
        return done); returns the mode's behaviour as it was before them."""
        s = self.state
        beh = s.mode.behaviour
        p = s.position
        home = s.home
        if s.phase == "takeoff" and abs(float(p[2]) - s.takeoff_target_z_m) <= ARRIVAL_TOL_M:
            s.phase = ""
            s.landed_state = self.mavlink.MAV_LANDED_STATE_IN_AIR
            if self.info.takeoff_complete_text is not None:  # ArduPilot's GUIDED take-off ends silently
                self.outbox.statustext(6, self.info.takeoff_complete_text)
            if beh == "takeoff":  # PX4: AUTO.TAKEOFF ends in AUTO.LOITER at the take-off point
                s.mode = self.info.require_mode(self.info.hold_mode)
                target = s.pm.command.position
                s.command(Command("hold", position=None if target is None else target.copy()))
        elif s.phase == "land" and s.flying and float(p[2]) <= self.config.ground_z_m + 1e-6:
            self.touchdown()
        elif s.phase == "rtl_climb":
            target = s.pm.command.position
            if target is not None and abs(float(p[2] - target[2])) <= ARRIVAL_TOL_M:
                s.phase = "rtl_return"
                s.command(Command("position", position=np.array([home[0], home[1], float(p[2])])))
        elif s.phase == "rtl_return" and math.hypot(float(p[0] - home[0]), float(p[1] - home[1])) <= ARRIVAL_TOL_M:
            self.start_land()
        return beh

    def mode_from(self, base_mode: float, custom: float, sub: float) -> Mode | None:
        """The mode a DO_SET_MODE (base mode, custom mode, sub mode) or SET_MODE names, or
        None (no custom mode flag, not a number, or not a mode of the flavour)."""
        if not (math.isfinite(custom) and math.isfinite(sub)):
            return None
        if int(base_mode) & self.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED == 0:
            return None
        if self.info.mode_command_main_sub:
            main = int(custom)
            if main >= 1 << 16:  # a full custom_mode word (as SET_MODE carries it)
                return self.info.mode(main)
            return self.info.mode((main << 16) | (int(sub) << 24))
        return self.info.mode(int(custom))

"""The flight state a simulated vehicle's collaborators share (true values, mission ENU frame)."""

from __future__ import annotations

from dataclasses import dataclass

from comms.autopilot import Mode
from vehicle_sim.config import VehicleLimits
from vehicle_sim.dynamics import Command, FloatArray, PointMass


@dataclass
class FlightState:
    """Mutable state read and changed by the mode machine, the command handler, the setpoint
    handler, the failsafes and the telemetry encoders of one vehicle.

    Attributes:
        pm: the point mass (true position and velocity, ENU m and m/s; its command).
        home: home position (3,), ENU m (the boot position on the ground).
        mode: the current flight mode. armed, flying: motor and air state.
        landed_state: MAV_LANDED_STATE_* as EXTENDED_SYS_STATE reports it.
        t_s: sim time (s). yaw_rad: held yaw (rad, ENU heading as MAVLink yaw: 0 north).
        battery: remaining battery fraction (0..1). healthy: False once the vehicle failed.
        phase: take-off / landing / RTL sub-phase (``""``, ``"takeoff"``, ``"land"``,
            ``"rtl_climb"``, ``"rtl_return"``).
        takeoff_target_z_m: ENU height (m) that ends the take-off phase.
    """

    pm: PointMass
    home: FloatArray
    mode: Mode
    armed: bool
    flying: bool
    landed_state: int
    t_s: float = 0.0
    yaw_rad: float = 0.0
    battery: float = 1.0
    healthy: bool = True
    phase: str = ""
    takeoff_target_z_m: float = 0.0

    @property
    def position(self) -> FloatArray:
        """True position (3,), ENU m."""
        return self.pm.position

    @property
    def limits(self) -> VehicleLimits:
        """The kinematic limits the point mass flies with."""
        return self.pm.limits

    def command(self, cmd: Command) -> None:
        """Give the point mass ``cmd`` from the current sim time."""
        self.pm.set_command(cmd, self.t_s)

    def hold_here(self) -> None:
        """Hold the current position."""
        self.pm.set_command(Command("hold", position=self.position.copy()), self.t_s)

    def time_boot_ms(self) -> int:
        """Sim time since boot in ms (uint32 wrap)."""
        return int(round(self.t_s * 1000.0)) & 0xFFFFFFFF

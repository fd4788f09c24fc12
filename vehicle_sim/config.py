"""Frozen configuration of a simulated vehicle (no I/O, no MAVLink).

Frames and units: positions in the mission ENU frame (metres, x east, y north, z up) about
the mission origin; speeds in m/s, accelerations in m/s², times in seconds of *sim* time
unless a name says ``wall``. The vehicle's MAVLink ``LOCAL_NED`` frame is the same frame
about the same origin, with N = y, E = x, D = -z (see :mod:`vehicle_sim.frames`). The origin
type is :class:`comms.geodesy.Origin`, imported here for the vehicle's configuration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from comms.autopilot import FlavourName, flavour_names
from comms.geodesy import Origin

#: A flavour's name (:data:`comms.autopilot.FLAVOURS`).
Flavour = FlavourName
Profile = Literal["ideal", "pointmass"]
FenceAction = Literal["clamp", "reject"]

PROFILES: tuple[str, ...] = ("ideal", "pointmass")


def _finite(name: str, value: float) -> None:
    if not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, found {value!r}")


def _positive(name: str, value: float) -> None:
    if not (math.isfinite(value) and value > 0.0):
        raise ValueError(f"{name} must be a finite positive number, found {value!r}")


@dataclass(frozen=True)
class Geofence:
    """Inclusion fence in the mission ENU frame.

    The altitude box ``[z_min_m, z_max_m]`` (ENU up, metres) applies to setpoints and guided
    motion; take-off, landing and the ground itself are exempt from ``z_min_m`` (as with
    ArduPilot's FENCE_ALT_MIN, which only arms once reached). The horizontal boundary is the
    box ``[x_min_m, x_max_m] × [y_min_m, y_max_m]`` and/or a circle of ``radius_m`` about the
    home position; ``None`` disables that part.

    Attributes:
        action: ``"clamp"`` moves an outside position target onto the boundary;
            ``"reject"`` ignores the setpoint. Either way a STATUSTEXT says so.
    """

    z_min_m: float = -math.inf
    z_max_m: float = math.inf
    x_min_m: float | None = None
    x_max_m: float | None = None
    y_min_m: float | None = None
    y_max_m: float | None = None
    radius_m: float | None = None
    enabled: bool = True
    action: FenceAction = "clamp"

    def __post_init__(self) -> None:
        if math.isnan(self.z_min_m) or math.isnan(self.z_max_m) or not self.z_min_m <= self.z_max_m:
            raise ValueError(f"Geofence: expected z_min_m <= z_max_m, found {self.z_min_m} and {self.z_max_m}")
        pairs = (("x", self.x_min_m, self.x_max_m), ("y", self.y_min_m, self.y_max_m))
        for axis, lo, hi in pairs:
            if (lo is None) != (hi is None):
                raise ValueError(f"Geofence: give both {axis}_min_m and {axis}_max_m or neither")
            if lo is not None and hi is not None:
                _finite(f"Geofence.{axis}_min_m", lo)
                _finite(f"Geofence.{axis}_max_m", hi)
                if not lo < hi:
                    raise ValueError(f"Geofence: expected {axis}_min_m < {axis}_max_m, found {lo} and {hi}")
        if self.radius_m is not None:
            _positive("Geofence.radius_m", self.radius_m)
        if self.action not in ("clamp", "reject"):
            raise ValueError(f"Geofence.action: expected 'clamp' or 'reject', found {self.action!r}")

    @property
    def has_box(self) -> bool:
        """True when the horizontal box is set."""
        return self.x_min_m is not None and self.y_min_m is not None

    @property
    def box(self) -> tuple[float, float, float, float] | None:
        """``(x_min_m, x_max_m, y_min_m, y_max_m)`` when the horizontal box is set (:attr:`has_box`), else None."""
        if self.x_min_m is None or self.x_max_m is None or self.y_min_m is None or self.y_max_m is None:
            return None
        return self.x_min_m, self.x_max_m, self.y_min_m, self.y_max_m


@dataclass(frozen=True)
class VehicleLimits:
    """Kinematic limits of the point mass (ArduPilot WPNAV_* / PX4 MPC_* in SI units).

    Attributes:
        speed_max_h_mps: maximum horizontal speed (m/s).
        speed_max_up_mps, speed_max_down_mps: maximum climb and descent rates (m/s, > 0).
        accel_max_mps2: maximum acceleration magnitude (m/s²).
        land_speed_mps: descent rate while landing (m/s).
        takeoff_speed_mps: climb rate during take-off (m/s).
    """

    speed_max_h_mps: float = 10.0
    speed_max_up_mps: float = 2.5
    speed_max_down_mps: float = 1.5
    accel_max_mps2: float = 5.0
    land_speed_mps: float = 1.0
    takeoff_speed_mps: float = 2.5

    def __post_init__(self) -> None:
        for name in (
            "speed_max_h_mps",
            "speed_max_up_mps",
            "speed_max_down_mps",
            "accel_max_mps2",
            "land_speed_mps",
            "takeoff_speed_mps",
        ):
            _positive(f"VehicleLimits.{name}", getattr(self, name))


#: Default telemetry rates (Hz, sim time). 0 disables a stream.
DEFAULT_RATES_HZ: tuple[tuple[str, float], ...] = (
    ("SYS_STATUS", 1.0),
    ("GLOBAL_POSITION_INT", 4.0),
    ("LOCAL_POSITION_NED", 4.0),
    ("ATTITUDE", 4.0),
    ("GPS_RAW_INT", 1.0),
    ("HOME_POSITION", 0.2),
    ("EXTENDED_SYS_STATE", 1.0),
    ("BATTERY_STATUS", 0.5),
    ("VFR_HUD", 2.0),
    ("SYSTEM_TIME", 0.5),
)


@dataclass(frozen=True)
class VehicleConfig:
    """Everything one simulated vehicle needs; built by ``fimnav vehicle`` from a mission or
    from command-line options.

    Attributes:
        sysid: MAVLink system id (1..255); the component id is always 1 (autopilot).
        flavour: a flavour of :data:`comms.autopilot.FLAVOURS`: ``"ardupilot"`` (copter,
            default) or ``"px4"``.
        start_enu_m: boot position (x, y, z) in the mission ENU frame (m).
        airborne: boot armed and hovering at ``start_enu_m`` in GUIDED (ArduPilot) or
            AUTO.LOITER (PX4); otherwise boot disarmed on the ground below ``start_enu_m``.
        ground_z_m: ENU altitude of the ground (m).
        origin: geodetic origin of the mission frame.
        limits: kinematic limits. geofence: the inclusion fence.
        guided_timeout_s: ArduPilot GUID_TIMEOUT: a velocity (or position+velocity) command
            not refreshed within this time is dropped and the vehicle holds (sim s).
        offboard_loss_s: PX4 COM_OF_LOSS_T: OFFBOARD failsafe after this silence (sim s).
        physics_hz: fixed integration rate (Hz, sim time).
        rates_hz: default telemetry rates, (message name, Hz) pairs.
        profile: ``"ideal"`` integrates the commanded velocity exactly (no acceleration
            limit, no lag); ``"pointmass"`` tracks with speed/acceleration limits.
        lag_s: first-order lag time constant on the commanded velocity (pointmass only; 0 off).
        wind_enu_mps: constant wind (m/s, ENU); acts through ``drag_per_s`` (pointmass only).
        drag_per_s: linear drag coefficient (1/s) coupling air-relative velocity to acceleration.
        position_noise_m: standard deviation of the *reported* position noise (m); the true
            position (payload, physics) is never noisy.
        seed: seed of the sensor-noise generator (with ``sysid``).
        signing_key_path: file with a 32-byte MAVLink 2 signing key (raw or 64 hex digits);
            with a key, unsigned incoming frames are refused.
        tlog_path: write every frame in and out to this .tlog (None: no log).
        battery_drain_per_s: fraction of battery used per flying second (0..1).
        ready_after_s: sim seconds from boot until the vehicle can fly, as a real copter
            that aligns its EKF and waits for a GPS fix (0: ready at boot). Before that:
            no GPS fix, EKF without position, no home and no EKF origin, arming refused
            with the PreArm reason (see docs/vehicle_sim.md, "Readiness start-up").
        ekf_status_hz: default rate of EKF_STATUS_REPORT (Hz, sim time; ArduPilot flavour
            only, as its EXTRA3 stream; 0: only on request).
        params: parameter values set at boot, (name, value) pairs in the flavour's own names
            and units (as a SITL parameter file); checked by the vehicle when it is built.
    """

    sysid: int = 1
    flavour: Flavour = "ardupilot"
    start_enu_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    airborne: bool = False
    ground_z_m: float = 0.0
    origin: Origin = field(default_factory=Origin)
    limits: VehicleLimits = field(default_factory=VehicleLimits)
    geofence: Geofence = field(default_factory=Geofence)
    guided_timeout_s: float = 3.0
    offboard_loss_s: float = 1.0
    physics_hz: float = 50.0
    rates_hz: tuple[tuple[str, float], ...] = DEFAULT_RATES_HZ
    profile: Profile = "pointmass"
    lag_s: float = 0.0
    wind_enu_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    drag_per_s: float = 0.5
    position_noise_m: float = 0.0
    seed: int = 0
    signing_key_path: str | None = None
    tlog_path: str | None = None
    battery_drain_per_s: float = 1.0 / 1800.0
    ready_after_s: float = 0.0
    ekf_status_hz: float = 2.0
    params: tuple[tuple[str, float], ...] = ()

    def __post_init__(self) -> None:
        if not (isinstance(self.sysid, int) and 1 <= self.sysid <= 255):
            raise ValueError(f"VehicleConfig.sysid must be an integer in 1..255, found {self.sysid!r}")
        if self.flavour not in flavour_names():
            raise ValueError(f"VehicleConfig.flavour: expected one of {flavour_names()}, found {self.flavour!r}")
        if self.profile not in PROFILES:
            raise ValueError(f"VehicleConfig.profile: expected one of {PROFILES}, found {self.profile!r}")
        if len(self.start_enu_m) != 3:
            raise ValueError(f"VehicleConfig.start_enu_m: expected 3 values, found {len(self.start_enu_m)}")
        for i, v in enumerate(self.start_enu_m):
            _finite(f"VehicleConfig.start_enu_m[{i}]", v)
        for i, v in enumerate(self.wind_enu_mps):
            _finite(f"VehicleConfig.wind_enu_mps[{i}]", v)
        _finite("VehicleConfig.ground_z_m", self.ground_z_m)
        if self.start_enu_m[2] < self.ground_z_m:
            raise ValueError(f"VehicleConfig.start_enu_m: z = {self.start_enu_m[2]} m is below the ground ({self.ground_z_m} m)")
        _positive("VehicleConfig.guided_timeout_s", self.guided_timeout_s)
        _positive("VehicleConfig.offboard_loss_s", self.offboard_loss_s)
        _positive("VehicleConfig.physics_hz", self.physics_hz)
        _positive("VehicleConfig.drag_per_s", self.drag_per_s)
        if not (math.isfinite(self.lag_s) and self.lag_s >= 0.0):
            raise ValueError(f"VehicleConfig.lag_s must be >= 0 s, found {self.lag_s!r}")
        if not (math.isfinite(self.position_noise_m) and self.position_noise_m >= 0.0):
            raise ValueError(f"VehicleConfig.position_noise_m must be >= 0 m, found {self.position_noise_m!r}")
        if not (0.0 <= self.battery_drain_per_s < 1.0):
            raise ValueError(f"VehicleConfig.battery_drain_per_s must be in [0, 1), found {self.battery_drain_per_s!r}")
        if not (math.isfinite(self.ready_after_s) and self.ready_after_s >= 0.0):
            raise ValueError(f"VehicleConfig.ready_after_s must be a finite number >= 0 s, found {self.ready_after_s!r}")
        if self.airborne and self.ready_after_s > 0.0:
            raise ValueError(f"VehicleConfig: a vehicle booting airborne is ready at boot; ready_after_s must be 0, found {self.ready_after_s!r}")
        if not (math.isfinite(self.ekf_status_hz) and self.ekf_status_hz >= 0.0):
            raise ValueError(f"VehicleConfig.ekf_status_hz must be >= 0 Hz, found {self.ekf_status_hz!r}")
        for name, hz in self.rates_hz:
            if not (math.isfinite(hz) and hz >= 0.0):
                raise ValueError(f"VehicleConfig.rates_hz[{name!r}] must be >= 0 Hz, found {hz!r}")

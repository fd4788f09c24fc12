"""The fimnav mission format: one typed, frozen :class:`Mission` built from a YAML file.

Every section is a frozen pydantic v2 model that forbids unknown keys. YAML carries degrees,
metres, seconds and metres per second (units are in the key names); the conversion methods
return SI and radians for the math core (:mod:`planner.params`). Nothing downstream of
:func:`missions.format.loader.load_mission` reads raw dicts.

Frames: positions are in the mission frame, ENU (x east, y north, z up), metres, relative to
:attr:`Mission.origin`. Drones are numbered 1..N in user-facing text (the paper's numbering);
arrays are indexed 0..N-1 in the same order.

Cross-field checks (a mission that would start in violation of its own constraints is refused)
raise :class:`pydantic_core.PydanticCustomError` of type ``"mission_invalid"`` whose context
holds ``path`` (key path relative to the model that raised it), ``expected`` and ``found``;
:mod:`missions.format.loader` turns those into one message naming the file and the key path.

See ``docs/mission-format.md`` for every key, its unit, default and paper symbol.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    Strict,
    ValidationInfo,
    WithJsonSchema,
    model_validator,
)
from pydantic_core import PydanticCustomError

from comms.autopilot import FlavourName, FlavourSetting, flavour_names
from comms.faults import FaultModel
from comms.geodesy import DEFAULT_ORIGIN_ALT_M, DEFAULT_ORIGIN_LAT_DEG, DEFAULT_ORIGIN_LON_DEG, Origin
from planner.config import PlannerConfig
from planner.estimator import EstimatorConfig
from planner.params import Channel, Criterion, Limits
from planner.policies import POLICIES
from planner.radio.power_settings import UnknownPowerSettings
from planner.sensing import ROLE_NAMES, SENSING, SensingTable, role_masks

if TYPE_CHECKING:  # pragma: no cover - types only
    from vehicle_sim.config import VehicleConfig

#: Version of the mission format written by :func:`missions.format.loader.mission_to_yaml`.
SCHEMA_VERSION: int = 1

#: Largest swarm the format accepts (MAVLink system ids are 1..255; 250 leaves room for GCSs).
MAX_DRONES: int = 250

#: Default origin of the mission frame (DEFAULT_ORIGIN_*, from comms.geodesy): ArduPilot SITL's
#: default home, the Canberra Model Aircraft Club field (CMAC), so simulated vehicles and a
#: default mission agree.

#: The sensing role names, from the role table of :mod:`planner.sensing` (one place to add a role).
ROLES: tuple[str, ...] = ROLE_NAMES
if TYPE_CHECKING:
    Role = str
else:
    Role = Literal[ROLE_NAMES]  # validated against the table; the JSON Schema's enum is ROLES

#: The navigation policies (:data:`planner.policies.POLICIES`).
if TYPE_CHECKING:
    PolicyField = str
else:
    PolicyField = Literal[POLICIES]

# --- scalar and vector types -------------------------------------------------------------
# Numbers are strict: YAML ``"10"`` (a string) or ``true`` is not a number. An int is a valid
# float. NaN and infinities are refused by ``allow_inf_nan=False`` on every model.
Float = Annotated[float, Strict()]
Int = Annotated[int, Strict()]
Bool = Annotated[bool, Strict()]
Str = Annotated[str, Strict()]  # YAML !!binary (bytes) is not text


def fail(path: str, expected: str, found: object) -> PydanticCustomError:
    """A cross-field validation error at ``path`` (relative to the model that raises it).

    ``found`` is shown with ``repr`` unless it is already a string describing the value.
    """
    found_text = found if isinstance(found, str) else repr(found)
    return PydanticCustomError(
        "mission_invalid",
        "expected {expected}, found {found}",
        {"path": path, "expected": expected, "found": found_text},
    )


def _vector3_shape(value: Any) -> Any:
    """Refuse anything but a list of exactly three items, with a message that says so."""
    if isinstance(value, (list, tuple)) and len(value) != 3:
        raise PydanticCustomError(
            "vector3",
            "expected a list of 3 numbers [x, y, z] in metres, found {found}",
            {"found": f"{len(value)} items {list(value)!r}"[:120]},
        )
    return value


#: A 3-vector [x, y, z] of finite numbers (ENU mission frame).
Vec3 = Annotated[tuple[Float, Float, Float], BeforeValidator(_vector3_shape)]


def _resolve_path(value: Path, info: ValidationInfo) -> Path:
    """Resolve a relative file path against the mission file's directory (validation
    context ``base_dir``), so that a mission means the same thing from any working directory."""
    base = (info.context or {}).get("base_dir") if info is not None else None
    if not value.is_absolute() and base is not None:
        return (Path(base) / value).resolve()
    return value


#: A file path; relative paths are relative to the mission file.
FilePath = Annotated[Path, AfterValidator(_resolve_path)]

_CONNECTION_RE = re.compile(
    r"^(?:(?:udpin|udpout|udp|udpbcast|tcp|tcpin):[^:\s]+:\d{1,5}"
    r"|(?:/dev/|COM\d)[^\s,]*(?:,\d+)?)$"
)


def _check_connection(value: str) -> str:
    """A pymavlink/MAVProxy connection string: ``udpin:HOST:PORT``, ``udpout:``, ``tcp:``,
    ``tcpin:``, or a serial device with an optional baud rate (``/dev/ttyUSB0,57600``)."""
    if not _CONNECTION_RE.match(value):
        raise PydanticCustomError(
            "mavlink_connection",
            "expected a pymavlink connection string such as 'udpin:127.0.0.1:14550', 'tcp:HOST:PORT' or '/dev/ttyUSB0,57600', found {found}",
            {"found": repr(value)},
        )
    return value


MavlinkConnection = Annotated[str, Strict(), AfterValidator(_check_connection)]


class _Section(BaseModel):
    """Base of every mission section: frozen, unknown keys are errors, finite numbers only."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False, validate_default=True)


# --- sections ----------------------------------------------------------------------------


class OriginSpec(_Section):
    """Origin of the ENU mission frame (WGS-84).

    Default: ArduPilot SITL's home, CMAC, Canberra (-35.363261°, 149.165230°, 584 m AMSL).
    """

    # The mission file's section; the origin itself is comms.geodesy.Origin (to_origin).
    model_config = ConfigDict(title="Origin")

    lat_deg: Float = Field(DEFAULT_ORIGIN_LAT_DEG, ge=-90.0, le=90.0, description="Latitude (deg, WGS-84).")
    lon_deg: Float = Field(DEFAULT_ORIGIN_LON_DEG, ge=-180.0, le=180.0, description="Longitude (deg, WGS-84).")
    alt_m: Float = Field(DEFAULT_ORIGIN_ALT_M, description="Altitude of the frame origin, metres AMSL.")

    def to_origin(self) -> Origin:
        """The plain origin (:class:`comms.geodesy.Origin`) the frames and the vehicle use."""
        return Origin(self.lat_deg, self.lon_deg, self.alt_m)

    @property
    def lat_rad(self) -> float:
        """Latitude in radians."""
        return math.radians(self.lat_deg)

    @property
    def lon_rad(self) -> float:
        """Longitude in radians."""
        return math.radians(self.lon_deg)


class Ellipse(_Section):
    """The paper's start formation: drones evenly spaced in angle on an ellipse in the XZ plane.

    Drone i (1-based) sits at angle α_i = phase + 2π (i - 1) / N, measured in the XZ plane
    from +x (east) towards +z (up), i.e. counter-clockwise as seen from the south looking
    north; its position is ``center + [r_x cos α_i, 0, r_z sin α_i]``. With the default
    phase 0, drone 1 is the east end of the ellipse, ``center + [r_x, 0, 0]``.
    """

    center_m: Vec3 = Field((0.0, 150.0, 8.0), description="Centre [x, y, z] of the ellipse (m, ENU).")
    radius_x_m: Float = Field(20.0, ge=0.0, description="Semi-axis r_x along x (m).")
    radius_z_m: Float = Field(5.0, ge=0.0, description="Semi-axis r_z along z (m).")
    phase_deg: Float = Field(0.0, ge=-360.0, le=360.0, description="Angle α_1 of drone 1 (deg).")

    def positions_m(self, count: int) -> NDArray[np.float64]:
        """Start positions of ``count`` drones, shape (count, 3), metres ENU, drone 1 first."""
        alpha = math.radians(self.phase_deg) + 2.0 * np.pi * np.arange(count) / count
        center = np.asarray(self.center_m, dtype=float)
        offsets = np.stack([self.radius_x_m * np.cos(alpha), np.zeros(count), self.radius_z_m * np.sin(alpha)], axis=-1)
        return center + offsets


class Rows(_Section):
    """A start formation that scales with the swarm: rows of ``per_row`` drones ``spacing_m``
    apart, the first row centred on ``center_m``, each next row ``spacing_m`` further in the
    direction ``back_deg`` (behind the first, away from the source), all at the height of the
    centre. Any number of drones is at least ``spacing_m`` from each other (the paper's
    ellipse crowds its ends below d_U* beyond about 40 drones).

    Drone i (1-based) is in row r = ⌊(i − 1) / per_row⌋ and place c = (i − 1) mod per_row of the
    n_r drones of its row; its position is ``center + s (c − (n_r − 1)/2) a + s r b``, with s
    the spacing, b the unit vector at azimuth ``back_deg`` (from east towards north) and a = b
    turned 90° clockwise (for the default b = north, a = east).
    """

    center_m: Vec3 = Field((0.0, 150.0, 8.0), description="Centre [x, y, z] of the first row (m, ENU).")
    spacing_m: Float = Field(5.0, gt=0.0, description="Distance between neighbours in a row and between rows (m).")
    per_row: Int = Field(10, ge=1, le=MAX_DRONES, description="Drones in a row (the last row may hold fewer).")
    back_deg: Float = Field(
        90.0, ge=-360.0, le=360.0, description="Azimuth of the direction the rows stack in, from east towards north (deg; 90: north)."
    )

    def positions_m(self, count: int) -> NDArray[np.float64]:
        """Start positions of ``count`` drones, shape (count, 3), metres ENU, drone 1 first."""
        i = np.arange(count)
        row, place = i // self.per_row, i % self.per_row
        in_row = np.minimum(self.per_row, count - row * self.per_row)
        b = math.radians(self.back_deg)
        back = np.array([math.cos(b), math.sin(b), 0.0])
        across = np.array([math.sin(b), -math.cos(b), 0.0])
        lateral = self.spacing_m * (place - (in_row - 1) / 2.0)
        return np.asarray(self.center_m, dtype=float) + lateral[:, None] * across + (self.spacing_m * row)[:, None] * back


class Start(_Section):
    """Initial positions: exactly one of ``positions_m`` (explicit), ``ellipse`` (the paper's)
    or ``rows`` (a formation for any number of drones)."""

    model_config = ConfigDict(json_schema_extra={"oneOf": [{"required": ["positions_m"]}, {"required": ["ellipse"]}, {"required": ["rows"]}]})

    #: The keys of which a start has exactly one. An override (``--set``) of one of them
    #: replaces the mission file's (:func:`missions.format.loader.load_mission`).
    FORMATIONS: ClassVar[tuple[str, ...]] = ("positions_m", "ellipse", "rows")

    positions_m: tuple[Vec3, ...] | None = Field(None, description="Explicit start positions, one [x, y, z] per drone (m, ENU), drone 1 first.")
    ellipse: Ellipse | None = Field(None, description="Start on the paper's XZ-plane ellipse.")
    rows: Rows | None = Field(None, description="Start in rows behind a centre, for any number of drones (size sweeps).")

    @model_validator(mode="after")
    def _exactly_one(self) -> Start:
        given = [name for name in self.FORMATIONS if getattr(self, name) is not None]
        if len(given) != 1:
            found = " and ".join(repr(g) for g in given) if given else "none of them"
            raise fail("", "exactly one of 'positions_m', 'ellipse' or 'rows'", found)
        return self

    def positions_for(self, count: int) -> NDArray[np.float64]:
        """Start positions of ``count`` drones, shape (count, 3), metres ENU (a new array)."""
        if self.positions_m is not None:
            return np.array(self.positions_m, dtype=float).reshape(count, 3)
        formation = self.ellipse or self.rows
        if formation is None:  # pragma: no cover - excluded by _exactly_one
            raise RuntimeError("Start has no formation")
        return formation.positions_m(count)


def _expand_roles(data: Any) -> Any:
    """Accept one role string for every drone, or ``{cycle: [roles]}`` repeated in order;
    expand either to a list of ``count`` roles."""
    if isinstance(data, dict) and isinstance(data.get("roles"), dict):
        data = {**data, "roles": _cycle_roles(data["roles"], data.get("count"))}
    if isinstance(data, dict) and isinstance(data.get("roles"), str):
        role = data["roles"]
        if role not in ROLES:
            names = ", ".join(repr(name) for name in ROLES)
            raise fail("roles", f"one of {names} (or a list of them, one per drone)", repr(role))
        count = data.get("count")
        if not (isinstance(count, int) and not isinstance(count, bool) and 1 <= count <= MAX_DRONES):
            count = 1
        data = {**data, "roles": [role] * count}
    return data


def _cycle_roles(spec: dict[Any, Any], count: Any) -> list[str]:
    """``{cycle: [r1, r2, ...]}``: drone i gets r_((i − 1) mod len) (``count`` roles)."""
    cycle = spec.get("cycle")
    if set(spec) != {"cycle"} or not isinstance(cycle, list) or not cycle:
        raise fail("roles", "a role, a list of roles, or {cycle: [a non-empty list of roles]}", f"a mapping {spec!r}"[:120])
    for j, role in enumerate(cycle):
        if role not in ROLES:
            names = ", ".join(repr(name) for name in ROLES)
            raise fail(f"roles.cycle[{j}]", f"one of {names}", repr(role))
    if not (isinstance(count, int) and not isinstance(count, bool) and 1 <= count <= MAX_DRONES):
        count = len(cycle)
    return [cycle[i % len(cycle)] for i in range(count)]


RolesField = Annotated[
    tuple[Role, ...],
    WithJsonSchema(
        {
            "anyOf": [
                {"enum": list(ROLES), "description": "One role for every drone."},
                {"type": "array", "items": {"enum": list(ROLES)}, "description": "One role per drone."},
                {
                    "type": "object",
                    "properties": {"cycle": {"type": "array", "items": {"enum": list(ROLES)}, "minItems": 1}},
                    "required": ["cycle"],
                    "additionalProperties": False,
                    "description": "Roles repeated in this order, drone 1 first, for any drones.count.",
                },
            ]
        }
    ),
]


class Drones(_Section):
    """The swarm: size N, per-drone sensing role and start positions.

    Roles (paper section II-B): ``ranging`` ∈ N_R (κ_j = 1), ``bearing`` ∈ N_B (β_j = 1),
    ``joint`` ∈ N_J (κ_j = β_j = 1).
    """

    # The role names and their (κ, β) come from the role table, planner.sensing.ROLES (this
    # docstring is the JSON Schema's description of the section).

    count: Int = Field(..., ge=1, le=MAX_DRONES, description="Number of drones N.")
    roles: RolesField = Field(..., description="Sensing role of every drone (one string for all, or a list).")
    start: Start = Field(..., description="Initial positions p_i^(0).")

    @model_validator(mode="before")
    @classmethod
    def _expand(cls, data: Any) -> Any:
        return _expand_roles(data)

    @model_validator(mode="after")
    def _counts_agree(self) -> Drones:
        if len(self.roles) != self.count:
            raise fail("roles", f"{self.count} roles (drones.count)", f"{len(self.roles)} roles")
        if self.start.positions_m is not None and len(self.start.positions_m) != self.count:
            raise fail(
                "start.positions_m",
                f"{self.count} positions (drones.count)",
                f"{len(self.start.positions_m)} positions",
            )
        return self

    def start_positions_m(self) -> NDArray[np.float64]:
        """Start positions p_i^(0), shape (count, 3), metres ENU, drone 1 first (a new array)."""
        return self.start.positions_for(self.count)

    def ranging_mask(self) -> NDArray[np.bool_]:
        """κ_j of eq. (10): True where drone j's role measures range (:data:`planner.sensing.ROLES`), shape (count,)."""
        return role_masks(self.roles)[0]

    def bearing_mask(self) -> NDArray[np.bool_]:
        """β_j of eq. (10): True where drone j's role measures bearing (:data:`planner.sensing.ROLES`), shape (count,)."""
        return role_masks(self.roles)[1]


class SearchBox(_Section):
    """Where the source can be (prior knowledge of the operator): the estimator keeps its
    estimate inside this box. Absent: the fence horizontally, any height."""

    min_m: Vec3 = Field(..., description="Lower corner [x, y, z] (m, ENU).")
    max_m: Vec3 = Field(..., description="Upper corner [x, y, z] (m, ENU).")

    @model_validator(mode="after")
    def _ordered(self) -> SearchBox:
        for axis, (lo, hi) in enumerate(zip(self.min_m, self.max_m)):
            if not lo < hi:
                raise fail(f"max_m[{axis}]", f"max_m[{axis}] > min_m[{axis}] = {lo:g} ({'xyz'[axis]} axis)", hi)
        return self


class Source(_Section):
    """The radio source p_0: initial position and constant velocity (zero = static source)."""

    position_m: Vec3 = Field(..., description="Source position p_0 at t = 0 (m, ENU).")
    velocity_mps: Vec3 = Field((0.0, 0.0, 0.0), description="Constant source velocity (m/s, ENU).")
    search_box: SearchBox | None = Field(
        None, description="Region the source is known to lie in (the estimator's bounds); absent: fence, any height."
    )
    power: Literal["known", "unknown"] = Field(
        "known",
        description="The source's transmit power as the drones know it: known (the paper's model: ranges from received power "
        "with the nominal reference power) or unknown (a nuisance parameter: the estimator estimates the power offset jointly "
        "with the position and the planning cost is eq. 6 on the position's information with the offset unknown).",
    )
    power_offset_db: Float = Field(
        0.0,
        ge=-60.0,
        le=60.0,
        description="Simulation only: the true source's reference power above the nominal one the drones assume (dB; "
        "positive: a stronger source, whose ranges read short). With power known the planner assumes the nominal power "
        "(biased); with power unknown it estimates the offset.",
    )

    @model_validator(mode="after")
    def _inside_search_box(self) -> Source:
        box = self.search_box
        if box is not None:
            for axis, v in enumerate(self.position_m):
                if not box.min_m[axis] <= v <= box.max_m[axis]:
                    raise fail(
                        f"search_box.min_m[{axis}]",
                        f"a search box that contains the source position ({'xyz'[axis]} = {v:g} m)",
                        f"[{box.min_m[axis]:g}, {box.max_m[axis]:g}]",
                    )
        return self

    def position_at(self, t_s: float) -> NDArray[np.float64]:
        """Source position p_0(t) = p_0 + v t at time ``t_s`` seconds, shape (3,), metres ENU."""
        return np.asarray(self.position_m, dtype=float) + float(t_s) * np.asarray(self.velocity_mps, dtype=float)

    @property
    def is_static(self) -> bool:
        """True when the source does not move."""
        return not any(self.velocity_mps)


class Box(_Section):
    """An obstacle: axis-aligned parallelepiped [min_m, max_m] (the paper's set O)."""

    name: Str = Field(..., min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$", description="Obstacle name.")
    min_m: Vec3 = Field(..., description="Lower corner [x, y, z] (m, ENU).")
    max_m: Vec3 = Field(..., description="Upper corner [x, y, z] (m, ENU).")

    @model_validator(mode="after")
    def _ordered(self) -> Box:
        for axis, (lo, hi) in enumerate(zip(self.min_m, self.max_m)):
            if not lo < hi:
                raise fail(f"max_m[{axis}]", f"max_m[{axis}] > min_m[{axis}] = {lo:g} ({'xyz'[axis]} axis)", hi)
        return self


class ChannelSpec(_Section):
    """RSS channel of the observation model (eqs. 3-5, 11)."""

    path_loss_exponent: Float = Field(2.0, gt=0.0, le=10.0, description="Path-loss exponent γ (dimensionless).")
    sigma_ratio_los: Float = Field(1.7, gt=0.0, description="σ_sh/γ in LOS (paper 1.7).")
    sigma_ratio_nlos: Float = Field(3.2, gt=0.0, description="σ_sh/γ in NLOS (paper 3.2).")
    sigma_bearing_deg: Float = Field(10.0, gt=0.0, le=180.0, description="Bearing std σ_b,0 (deg, paper 10).")
    reference_power_db: Float | None = Field(
        None,
        ge=-300.0,
        le=300.0,
        description="Received power 1 m from the source, in the receiver's dB (fitted by fimnav calibrate); "
        "absent: unknown. fimnav localize --power known uses it.",
    )

    @property
    def sigma_bearing_rad(self) -> float:
        """σ_b,0 in radians."""
        return math.radians(self.sigma_bearing_deg)

    def to_planner(self) -> Channel:
        """The math core's :class:`planner.params.Channel` (radians)."""
        return Channel(
            gamma=self.path_loss_exponent,
            sigma_ratio_los=self.sigma_ratio_los,
            sigma_ratio_nlos=self.sigma_ratio_nlos,
            sigma_bearing_rad=self.sigma_bearing_rad,
        )


class Constraints(_Section):
    """Safety distances and kinematic limits of problem (7).

    The paper gives speeds in m/step with Δt = 1 s; here they are m/s and
    :meth:`to_planner` multiplies by ``dt_s``. Turn limits are per step.
    """

    d_uav_m: Float = Field(1.0, gt=0.0, description="Anti-collision distance d_U* (m).")
    d_source_m: Float = Field(50.0, ge=0.0, description="Keep-out distance from the source d_S* (m).")
    d_obstacle_m: Float = Field(5.0, ge=0.0, description="Distance from any obstacle d_O* (m).")
    speed_min_mps: Float = Field(0.5, ge=0.0, description="Minimum speed v_min (m/s).")
    speed_max_mps: Float = Field(1.0, gt=0.0, le=100.0, description="Maximum speed v_max (m/s).")
    heading_change_max_deg: Float = Field(50.0, gt=0.0, le=180.0, description="φ_max, per step (deg).")
    tilt_change_max_deg: Float = Field(50.0, gt=0.0, le=180.0, description="θ_max, per step (deg).")
    z_min_m: Float = Field(2.0, description="Lowest altitude z_min (m, ENU up).")
    z_max_m: Float = Field(25.0, description="Highest altitude z_max (m, ENU up).")
    activation: Literal["safe", "paper"] = Field("safe", description="'safe': constraints act before violation; 'paper': eqs. 15-17 literally.")

    @model_validator(mode="after")
    def _ordered(self) -> Constraints:
        if self.speed_min_mps > self.speed_max_mps:
            raise fail("speed_min_mps", f"speed_min_mps <= speed_max_mps = {self.speed_max_mps:g}", self.speed_min_mps)
        if self.z_min_m > self.z_max_m:
            raise fail("z_min_m", f"z_min_m <= z_max_m = {self.z_max_m:g}", self.z_min_m)
        return self

    @property
    def heading_change_max_rad(self) -> float:
        """φ_max in radians (per step)."""
        return math.radians(self.heading_change_max_deg)

    @property
    def tilt_change_max_rad(self) -> float:
        """θ_max in radians (per step)."""
        return math.radians(self.tilt_change_max_deg)

    def to_planner(self, dt_s: float) -> Limits:
        """The math core's :class:`planner.params.Limits`: per-step metres (v·Δt) and radians."""
        return Limits(
            d_uav_m=self.d_uav_m,
            d_source_m=self.d_source_m,
            d_obstacle_m=self.d_obstacle_m,
            step_min_m=self.speed_min_mps * dt_s,
            step_max_m=self.speed_max_mps * dt_s,
            heading_change_max_rad=self.heading_change_max_rad,
            tilt_change_max_rad=self.tilt_change_max_rad,
            z_min_m=self.z_min_m,
            z_max_m=self.z_max_m,
            activation=self.activation,
        )


class Faults(_Section):
    """Injected loss and extra delay of the peers' records at each receiver (issue 7).

    Deterministic for a seed: receiver i draws its decisions from its own stream (see
    :mod:`comms.faults`); the planner node and the in-process simulator inject the same faults.
    Off by default.
    """

    loss: Float = Field(0.0, ge=0.0, lt=1.0, description="Probability that a peer's record is lost at a receiver, in [0, 1).")
    extra_delay_steps: Int = Field(0, ge=0, le=1000, description="Maximum extra delay D (steps): each record arrives a uniform 0..D steps late.")
    partition_start_step: Int | None = Field(
        None,
        ge=0,
        description="First step of a network partition (fimnav montecarlo only): drones "
        "1..ceil(N/2) and the rest exchange no record, whatever their distance.",
    )
    partition_steps: Int = Field(0, ge=0, le=100000, description="Length of the partition (steps); 0: none.")

    @property
    def enabled(self) -> bool:
        """Whether any fault is injected."""
        return self.loss > 0.0 or self.extra_delay_steps > 0 or self.partition is not None

    @property
    def partition(self) -> tuple[int, int] | None:
        """The partition's steps [start, end), or None when there is none."""
        if self.partition_start_step is None or self.partition_steps == 0:
            return None
        return self.partition_start_step, self.partition_start_step + self.partition_steps

    def to_model(self) -> FaultModel | None:
        """The :class:`comms.faults.FaultModel` of the loss and delay, or None when off."""
        return FaultModel(self.loss, self.extra_delay_steps) if self.loss > 0.0 or self.extra_delay_steps > 0 else None


class Comms(_Section):
    """Multi-hop sharing of records (section II-B): range r_max = ``d_hop_m``, hop cap h_max."""

    d_hop_m: Float = Field(100.0, gt=0.0, description="Radio range of one hop r_max (m).")
    h_max: Int = Field(1, ge=1, le=1000, description="Maximum number of hops h_max.")
    latency: Literal["emulated", "real"] = Field(
        "emulated", description="'emulated': one step of delay per hop (the paper); 'real': network latency."
    )
    faults: Faults = Field(Faults(), description="Injected loss and extra delay of the peers' records (off by default).")


class Controller(_Section):
    """Projected-gradient control law (eq. 14)."""

    xi: Float | None = Field(
        None,
        gt=0.0,
        description="Spatial step ξ (m per unit gradient). None: normalized step, the gradient direction scaled to v_max·Δt.",
    )
    random_perturbation_deg: Float = Field(20.0, ge=0.0, le=180.0, description="Random heading perturbation used when the FIM is singular (deg).")

    @property
    def random_perturbation_rad(self) -> float:
        """Singular-FIM perturbation in radians."""
        return math.radians(self.random_perturbation_deg)


#: Cells of the range memory for a static source when the mission file gives none: enough for a
#: paper mission's ranges at the estimator's cell radius (docs/estimator.md).
RANGE_MEMORY_CELLS = 256


class EstimatorSpec(_Section):
    """The source estimator's options (:class:`planner.estimator.EstimatorConfig`); the search
    box is ``source.search_box``, the forgetting factor follows from the source's motion."""

    range_memory_cells: Int | None = Field(
        None,
        ge=0,
        le=4096,
        description=(
            "Cells of the range memory that re-checks a ranging estimate on the exact likelihood of every range so far "
            "(docs/estimator.md); 0: off; default (null): 256 for a static source, 0 for a moving one."
        ),
    )


class Fence(_Section):
    """Horizontal geofence of the mission frame (m, ENU). Must contain the starts and the source."""

    x_min_m: Float = Field(-1000.0, description="West edge (m).")
    x_max_m: Float = Field(1000.0, description="East edge (m).")
    y_min_m: Float = Field(-1000.0, description="South edge (m).")
    y_max_m: Float = Field(1000.0, description="North edge (m).")

    @model_validator(mode="after")
    def _ordered(self) -> Fence:
        if not self.x_min_m < self.x_max_m:
            raise fail("x_max_m", f"x_max_m > x_min_m = {self.x_min_m:g}", self.x_max_m)
        if not self.y_min_m < self.y_max_m:
            raise fail("y_max_m", f"y_max_m > y_min_m = {self.y_min_m:g}", self.y_max_m)
        return self

    def contains(self, xy: NDArray[np.float64]) -> NDArray[np.bool_]:
        """True where points (..., ≥2) lie inside the fence (edges included)."""
        xy = np.asarray(xy, dtype=float)
        return (xy[..., 0] >= self.x_min_m) & (xy[..., 0] <= self.x_max_m) & (xy[..., 1] >= self.y_min_m) & (xy[..., 1] <= self.y_max_m)


class ZenohTls(_Section):
    """Zenoh TLS files (paths relative to the mission file)."""

    root_ca_certificate: FilePath = Field(..., description="CA certificate that signs the peers' certificates.")
    certificate: FilePath | None = Field(None, description="This node's certificate.")
    private_key: FilePath | None = Field(None, description="This node's private key.")


class ZenohAuth(_Section):
    """Zenoh user/password authentication; the password is read from a file, never the mission."""

    user: Str = Field(..., min_length=1, description="User name.")
    password_file: FilePath = Field(..., description="File holding the password (relative to the mission file).")


class ZenohSpec(_Section):
    """Zenoh session configuration. Default: peer mode on loopback only, no multicast scouting."""

    mode: Literal["peer", "client", "router"] = "peer"
    listen: tuple[Str, ...] = Field(("tcp/127.0.0.1:0",), description="Endpoints to listen on.")
    connect: tuple[Str, ...] = Field((), description="Endpoints to connect to.")
    multicast_scouting: Bool = False
    tls: ZenohTls | None = None
    auth: ZenohAuth | None = None


class VehicleOverride(_Section):
    """Per-drone vehicle settings; absent keys take the ``vehicles`` defaults."""

    connection: MavlinkConnection | None = Field(None, description="pymavlink connection string; absent: fimnav starts a simulated vehicle.")
    flavour: FlavourSetting | None = Field(
        None,
        description="Autopilot flavour. 'ardupilot' or 'px4' forces it for the planner (and sets the "
        "simulated vehicle's); 'auto' or absent: the planner detects it from HEARTBEAT.autopilot.",
    )
    signing_key_file: FilePath | None = Field(None, description="MAVLink 2 signing key file.")
    setpoint_frame: Literal["auto", "global", "local_ned"] | None = Field(
        None, description="Setpoint frame of this drone; absent: vehicles.setpoint_frame."
    )
    payload: Literal["simulated", "external"] | None = Field(
        None,
        description="Who publishes the measurements of a drone with a connection under fimnav launch --realtime: "
        "'simulated' (default): fimnav starts a simulated payload (fimnav payload) that follows the autopilot "
        "over payload_connection; 'external': a real payload does (fimnav starts none).",
    )
    payload_connection: MavlinkConnection | None = Field(
        None,
        description="A second MAVLink connection to the autopilot, for the simulated payload (e.g. SITL's SERIAL1, tcp:127.0.0.1:5762).",
    )


class ResolvedVehicle(BaseModel):
    """The vehicle settings of one drone after applying its override to the defaults.

    ``flavour`` is the simulated vehicle's flavour; ``autopilot`` is what the planner assumes:
    the flavour forced by the override, or ``auto`` (detected from HEARTBEAT.autopilot)."""

    model_config = ConfigDict(frozen=True)

    connection: str | None
    flavour: FlavourName
    profile: Literal["ideal", "pointmass"]
    signing_key_file: Path | None
    autopilot: FlavourSetting = "auto"
    setpoint_frame: Literal["auto", "global", "local_ned"] = "auto"
    payload: Literal["simulated", "external"] = "simulated"
    payload_connection: str | None = None


class Vehicles(_Section):
    """Autopilots: defaults and an optional per-drone override list (empty, or one per drone)."""

    flavour: FlavourName = Field("ardupilot", description="Autopilot dialect.")
    profile: Literal["ideal", "pointmass"] = Field("ideal", description="Simulated dynamics: 'ideal' reaches each setpoint in one step (the paper).")
    overrides: tuple[VehicleOverride, ...] = Field((), description="One entry per drone, drone 1 first.")
    setpoint_frame: Literal["auto", "global", "local_ned"] = Field(
        "auto",
        description="Planner setpoints: 'global' (SET_POSITION_TARGET_GLOBAL_INT, each vehicle keeps its own "
        "EKF origin), 'local_ned' (SET_POSITION_TARGET_LOCAL_NED; the vehicle's EKF origin must be the "
        "mission origin), 'auto' (local_ned in lockstep simulation, global in real time).",
    )

    def for_drone(self, index: int) -> ResolvedVehicle:
        """Settings of the drone at 0-based ``index`` (drone ``index + 1``)."""
        o = self.overrides[index] if self.overrides else VehicleOverride()
        forced = o.flavour if o.flavour in flavour_names() else None
        return ResolvedVehicle(
            connection=o.connection,
            flavour=forced or self.flavour,
            profile=self.profile,
            signing_key_file=o.signing_key_file,
            autopilot=forced or "auto",
            setpoint_frame=o.setpoint_frame or self.setpoint_frame,
            payload=o.payload or "simulated",
            payload_connection=o.payload_connection,
        )


# --- geometry helpers (independent of planner.geometry, for start-up checks only) --------


def _box_signed_distance(points: NDArray[np.float64], mins: NDArray[np.float64], maxs: NDArray[np.float64]) -> NDArray[np.float64]:
    """Signed distance (m) from points (P,3) to boxes (B,3): (P,B), negative inside."""
    p = points[:, None, :]
    outside = np.maximum(np.maximum(mins - p, p - maxs), 0.0)
    out_dist = np.linalg.norm(outside, axis=-1)
    in_dist = np.min(np.minimum(p - mins, maxs - p), axis=-1)
    return np.where(out_dist > 0.0, out_dist, -np.maximum(in_dist, 0.0))


def _segment_hits_box(a: NDArray[np.float64], b: NDArray[np.float64], lo: NDArray[np.float64], hi: NDArray[np.float64]) -> bool:
    """True if the segment a→b meets the closed box [lo, hi] (slab method)."""
    d = b - a
    t0, t1 = 0.0, 1.0
    for k in range(3):
        if d[k] == 0.0:
            if not lo[k] <= a[k] <= hi[k]:
                return False
            continue
        ta, tb = (lo[k] - a[k]) / d[k], (hi[k] - a[k]) / d[k]
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
        if t0 > t1:
            return False
    return True


def mission_json_schema() -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of the mission format, for editors and validators."""
    schema = _defs_named_by_title(Mission.model_json_schema(mode="validation"))
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": "https://fimnav.invalid/schema/mission-v1.json",
        **schema,
        "title": "fimnav mission",
    }


def _defs_named_by_title(schema: dict[str, Any]) -> dict[str, Any]:
    """``schema`` with each definition keyed by its title where a section's class name differs
    from the name the format gives it (:class:`OriginSpec` is the format's ``Origin``)."""
    defs = schema.get("$defs", {})
    names = {key: d["title"] for key, d in defs.items() if d.get("title", key) != key and d["title"] not in defs}
    if not names:
        return schema
    text = json.dumps(schema)
    for key, title in names.items():
        text = text.replace(f'"#/$defs/{key}"', f'"#/$defs/{title}"')
    out = json.loads(text)
    out["$defs"] = {names.get(key, key): d for key, d in out["$defs"].items()}
    return dict(out)


def _fmt(v: NDArray[np.float64]) -> str:
    return "[" + ", ".join(f"{x:.6g}" for x in v) + "]"


# --- the mission ---------------------------------------------------------------------------


class Mission(_Section):
    """One mission: the swarm, the source, the environment and every parameter of a run.

    Defaults are the paper's case study (section V) wherever it gives a value.
    """

    schema_version: Literal[1] = Field(1, description="Version of the mission format.")
    id: Str = Field(
        ...,
        min_length=1,
        max_length=64,
        pattern=r"^[A-Za-z0-9_-]+$",
        description="Mission id, used in Zenoh key expressions fimnav/<id>/...",
    )
    description: Str = Field("", description="Free text shown by fimnav check.")
    seed: Int = Field(0, ge=0, le=2**64 - 1, description="Root seed of every random draw.")
    dt_s: Float = Field(1.0, gt=0.0, le=3600.0, description="Step length Δt (s).")
    steps: Int = Field(550, ge=1, le=10_000_000, description="Number of steps K.")
    trials: Int = Field(100, ge=1, le=1_000_000, description="Monte Carlo trials M.")
    criterion: Literal["A", "D"] = Field("A", description="Design criterion of eq. (6).")
    policy: PolicyField = Field(
        "fim",
        description="How the drones navigate: 'fim' (the paper's planner) or a baseline ('static', 'orbit', 'random', "
        "'centralized'; fimnav montecarlo and sweep only).",
    )
    origin: OriginSpec = OriginSpec()
    drones: Drones
    source: Source
    obstacles: tuple[Box, ...] = Field((), description="Axis-aligned boxes (the set O).")
    channel: ChannelSpec = ChannelSpec()
    constraints: Constraints = Constraints()
    comms: Comms = Comms()
    controller: Controller = Controller()
    estimator: EstimatorSpec = EstimatorSpec()
    fence: Fence = Fence()
    zenoh: ZenohSpec = ZenohSpec()
    vehicles: Vehicles = Vehicles()
    end_action: Literal["hold", "land", "rtl"] = Field("hold", description="What vehicles do after the last step.")
    on_stop: Literal["hold", "land", "rtl"] = Field(
        "hold",
        description="What each vehicle is told when its planner stops early (Ctrl-C, SIGTERM, SIGHUP, a fatal error, the launch "
        "stopping it): hold (LOITER / AUTO.LOITER), land or rtl; a drone a pilot flies is left alone.",
    )
    altitude_reference: Literal["amsl", "relative"] = Field(
        "relative", description="How z maps to autopilot altitude: above the origin ('relative') or AMSL."
    )
    takeoff_alt_m: Float | None = Field(None, gt=0.0, description="Take-off altitude before the mission (m).")

    @property
    def duration_s(self) -> float:
        """Mission length K·Δt in seconds."""
        return self.steps * self.dt_s

    def limits(self) -> Limits:
        """``constraints.to_planner(dt_s)``."""
        return self.constraints.to_planner(self.dt_s)

    def source_is_slow(self) -> bool:
        """The source moves less than the turn buffer b (:attr:`planner.params.Limits.turn_buffer_m`)
        per step: static, or slow enough that b covers its motion between two steps. Planning
        with the true source (``--oracle-estimate``), its constraint then acts within one step
        of the drone's own motion (:func:`planner.control.source_activation_margin_m`)."""
        step_m = float(np.linalg.norm(np.asarray(self.source.velocity_mps, dtype=float))) * self.dt_s
        return step_m < self.limits().turn_buffer_m

    def estimator_config(self) -> EstimatorConfig:
        """The source estimator's settings for this mission: the search box (or the fence and
        any height) as bounds; a forgetting factor of 0.97 per step for a moving source; the
        range memory of ``estimator.range_memory_cells`` cells (by default 256 for a static source
        and off for a moving one, whose old ranges are not evidence of where it is now)."""
        box = self.source.search_box
        if box is not None:
            lo, hi = box.min_m, box.max_m
        else:
            f = self.fence
            lo, hi = (f.x_min_m, f.y_min_m, -math.inf), (f.x_max_m, f.y_max_m, math.inf)
        return EstimatorConfig(
            forgetting=1.0 if self.source.is_static else 0.97,
            bounds_min_m=lo,
            bounds_max_m=hi,
            range_memory_cells=self.range_memory_cells(),
        )

    def range_memory_cells(self) -> int:
        """Cells of the estimator's range memory: ``estimator.range_memory_cells`` if given, else
        :data:`RANGE_MEMORY_CELLS` for a static source and 0 (off) for a moving one."""
        cells = self.estimator.range_memory_cells
        if cells is not None:
            return cells
        return RANGE_MEMORY_CELLS if self.source.is_static else 0

    def planner_config(self, criterion: Criterion | None = None, sensing: SensingTable = SENSING) -> PlannerConfig:
        """Everything a drone's planning step takes from this mission (:class:`PlannerConfig`),
        with ``criterion`` in place of the mission's (a run's override), if given; the drones'
        component masks come from their roles in the role table of ``sensing``."""
        bmin, bmax = self.obstacle_bounds()
        return PlannerConfig(
            channel=self.channel.to_planner(),
            limits=self.limits(),
            criterion=self.criterion if criterion is None else criterion,
            component_masks=sensing.masks(self.drones.roles),
            boxes_min_m=bmin,
            boxes_max_m=bmax,
            d_hop_m=self.comms.d_hop_m,
            start_positions_m=self.drones.start_positions_m(),
            estimator=self.estimator_config(),
            xi=self.controller.xi,
            perturbation_rad=self.controller.random_perturbation_rad,
            sensing=sensing,
            unknown_power=UnknownPowerSettings() if self.source.power == "unknown" else None,
        )

    def vehicle_config(self, drone: int, **overrides: Any) -> VehicleConfig:
        """The simulated vehicle of drone ``drone`` (0-based; MAVLink system id ``drone + 1``)
        as this mission sets it up (:class:`vehicle_sim.config.VehicleConfig`): its start
        position (m, ENU), the mission's origin, a geofence at the mission's altitude limits
        (``constraints.z_min_m``/``z_max_m``) and fence box (m), its flavour, dynamics profile
        and signing key (``vehicles``), and the mission's seed. ``overrides``: other
        :class:`VehicleConfig` fields, or any of these given otherwise (e.g. on the command
        line), which win.

        Raises:
            ValueError: the vehicle config refuses a value.
        """
        from planner.geometry import vec3
        from vehicle_sim.config import Geofence, VehicleConfig

        resolved = self.vehicles.for_drone(drone)
        fields: dict[str, Any] = {
            "sysid": drone + 1,
            "flavour": resolved.flavour,
            "profile": resolved.profile,
            "start_enu_m": vec3(self.drones.start_positions_m()[drone]),
            "signing_key_path": str(resolved.signing_key_file) if resolved.signing_key_file is not None else None,
            "seed": int(self.seed),
        }
        if "origin" not in overrides:
            fields["origin"] = self.origin.to_origin()
        if "geofence" not in overrides:
            c, f = self.constraints, self.fence
            fields["geofence"] = Geofence(
                z_min_m=c.z_min_m, z_max_m=c.z_max_m, x_min_m=f.x_min_m, x_max_m=f.x_max_m, y_min_m=f.y_min_m, y_max_m=f.y_max_m
            )
        fields.update(overrides)
        return VehicleConfig(**fields)

    def obstacle_bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Obstacle corners (mins, maxs), each shape (B, 3), metres ENU; B may be 0."""
        mins = np.array([b.min_m for b in self.obstacles], dtype=float).reshape(-1, 3)
        maxs = np.array([b.max_m for b in self.obstacles], dtype=float).reshape(-1, 3)
        return mins, maxs

    @model_validator(mode="after")
    def _consistent(self) -> Mission:
        """Refuse a mission that starts in violation of its own constraints (see docs)."""
        c = self.constraints
        n = self.drones.count
        starts = self.drones.start_positions_m()
        explicit = self.drones.start.positions_m is not None

        def where(i: int) -> str:
            return f"drones.start.positions_m[{i}]" if explicit else "drones.start"

        def who(i: int) -> str:
            return f"drone {i + 1} at {_fmt(starts[i])}"

        cells = self.estimator.range_memory_cells
        if cells and not self.source.is_static:
            raise fail(
                "estimator.range_memory_cells",
                "0 or null for a moving source (the memory keeps old ranges as evidence of where a static source is)",
                cells,
            )
        if self.vehicles.overrides and len(self.vehicles.overrides) != n:
            raise fail("vehicles.overrides", f"0 or {n} entries (drones.count)", f"{len(self.vehicles.overrides)} entries")

        names = [b.name for b in self.obstacles]
        for j, name in enumerate(names):
            if name in names[:j]:
                raise fail(f"obstacles[{j}].name", "a name not used by another obstacle", repr(name))

        for i in range(n):
            z = starts[i, 2]
            if not c.z_min_m <= z <= c.z_max_m:
                raise fail(where(i), f"z within [z_min_m, z_max_m] = [{c.z_min_m:g}, {c.z_max_m:g}]", who(i))
        inside_fence = self.fence.contains(starts)
        for outside in np.flatnonzero(~inside_fence):
            raise fail(where(int(outside)), "a start position inside the fence", who(int(outside)))

        if n > 1:
            diff = starts[:, None, :] - starts[None, :, :]
            dist = np.linalg.norm(diff, axis=-1) + np.diag(np.full(n, np.inf))
            a, b = np.unravel_index(int(np.argmin(dist)), dist.shape)
            if dist[a, b] < c.d_uav_m:
                i, j = int(min(a, b)), int(max(a, b))
                hint = " (a swarm too large for the ellipse starts in rows: drones.start.rows, --set drones.start.rows={})"
                raise fail(
                    where(j),
                    f"start positions at least d_uav_m = {c.d_uav_m:g} m apart",
                    f"drones {i + 1} and {j + 1} {dist[i, j]:.3g} m apart" + (hint if self.drones.start.ellipse is not None else ""),
                )

        source0 = self.source.position_at(0.0)
        source_end = self.source.position_at(self.duration_s)
        d_src = np.linalg.norm(starts - source0, axis=-1)
        for near in np.flatnonzero(d_src < c.d_source_m):
            raise fail(
                where(int(near)),
                f"a start at least d_source_m = {c.d_source_m:g} m from the source",
                f"{who(int(near))}, {d_src[near]:.3g} m from it",
            )
        for label, point in (("at t = 0", source0), (f"at t = {self.duration_s:g} s", source_end)):
            if not bool(self.fence.contains(point)):
                raise fail("source", "a source inside the fence for the whole mission", f"{_fmt(point)} {label}")

        if self.obstacles:
            mins, maxs = self.obstacle_bounds()
            sd = _box_signed_distance(starts, mins, maxs)
            for i, b in zip(*np.nonzero(sd <= 0.0)):
                raise fail(where(int(i)), "a start outside every obstacle", f"{who(int(i))} inside obstacle {names[b]!r}")
            for i, b in zip(*np.nonzero(sd < c.d_obstacle_m)):
                raise fail(
                    where(int(i)),
                    f"a start at least d_obstacle_m = {c.d_obstacle_m:g} m from every obstacle",
                    f"{who(int(i))}, {sd[i, b]:.3g} m from obstacle {names[b]!r}",
                )
            for name, lo, hi in zip(names, mins, maxs):
                if _segment_hits_box(source0, source_end, lo, hi):
                    path = "source.position_m" if self.source.is_static else "source"
                    raise fail(path, "a source outside every obstacle", f"the source meets obstacle {name!r}")
        return self

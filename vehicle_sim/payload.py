"""Simulated RSS payload: the drone's ranging / bearing estimate at its true position.

Pure core (numpy + the planner's observation model, no I/O). At step ``k`` the payload of
drone ``j`` draws, with the paper's observation model (eqs. 3-5; NLOS from the obstacle
boxes, bearing outliers in NLOS) as implemented by :func:`planner.observation.observe`:

.. math::
    \\hat d_j = d_j + n_{r,j},\\qquad \\hat\\alpha_j = p_j(\\alpha_j + n_{b,j}) + \\bar p_j\\,\\omega_j

where ``d_j``, ``α_j`` are taken between the vehicle's *true* position and the source at
time ``t`` (``p0(t) = p0 + v_s t``, ENU m). Noise comes from
:func:`planner.randomness.measurement_rng` ``(seed, trial, drone)``, consumed five uniforms
per step in step order, so the payload reproduces the in-process simulator's draws. A step
that is skipped still consumes its draws; a step cannot be measured twice.

The :class:`Measurement` record (:meth:`Measurement.to_json`) is the interface a real RSS
payload on a companion computer would publish; see docs/vehicle_sim.md.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner.params import Channel

if TYPE_CHECKING:
    from planner.sensing import SensingTable

FloatArray = NDArray[np.float64]

#: Version of the measurement record.
MEASUREMENT_SCHEMA = 1


@dataclass(frozen=True)
class PayloadWorld:
    """What the payload needs to know of the mission world (ENU frame, metres, seconds).

    Attributes:
        source_position_m: source position p0 at t = 0, (3,).
        source_velocity_mps: source velocity, (3,) (m/s).
        boxes_min_m, boxes_max_m: obstacle boxes, (B, 3) each.
        channel: the RSS channel.
        seed: mission seed. trial: trial index (0 for a distributed run).
        power_offset_db: the source's reference power above the nominal one the drones assume
            (dB, mission ``source.power_offset_db``): its ranges read short (positive) or long
            (:func:`planner.radio.power_offset.offset_ranges`).
    """

    source_position_m: tuple[float, float, float]
    source_velocity_mps: tuple[float, float, float]
    boxes_min_m: tuple[tuple[float, float, float], ...]
    boxes_max_m: tuple[tuple[float, float, float], ...]
    channel: Channel
    seed: int
    trial: int = 0
    power_offset_db: float = 0.0

    def __post_init__(self) -> None:
        if len(self.boxes_min_m) != len(self.boxes_max_m):
            raise ValueError(f"PayloadWorld: {len(self.boxes_min_m)} box minima but {len(self.boxes_max_m)} maxima")
        for name in ("source_position_m", "source_velocity_mps"):
            v = getattr(self, name)
            if len(v) != 3 or not all(math.isfinite(x) for x in v):
                raise ValueError(f"PayloadWorld.{name}: expected 3 finite numbers, found {v!r}")

    def source_at(self, time_s: float) -> FloatArray:
        """Source position at sim time ``time_s`` (s): p0 + v_s t, ENU m."""
        return np.asarray(self.source_position_m, dtype=float) + time_s * np.asarray(self.source_velocity_mps, dtype=float)


@dataclass(frozen=True)
class Measurement:
    """One drone's measurement at one step (the published record).

    Attributes:
        drone: 0-based drone index. sysid: its MAVLink system id. step: step index k.
        t_s: sim time of the measurement (s).
        position_enu_m: true position where it was taken, (x, y, z) ENU m.
        range_m: ranging estimate d̂ (m) or None (no ranging sensor).
        azimuth_rad, elevation_rad: bearing estimate of the source seen from the drone (rad,
            ENU: azimuth from east towards north, elevation above the horizontal) or None
            (no bearing sensor).
        los: whether the link was line of sight.
        extra_values: the values of the drone's components beyond range and bearing, by value
            name (:data:`planner.sensing.SENSING`; NaN: not measured); empty for a drone of
            range and bearing only, whose JSON then has no ``extra_values`` key.
    """

    drone: int
    sysid: int
    step: int
    t_s: float
    position_enu_m: tuple[float, float, float]
    range_m: float | None
    azimuth_rad: float | None
    elevation_rad: float | None
    los: bool
    extra_values: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (``schema`` = :data:`MEASUREMENT_SCHEMA`; NaN values as None)."""
        out: dict[str, Any] = {
            "schema": MEASUREMENT_SCHEMA,
            "drone": self.drone,
            "sysid": self.sysid,
            "step": self.step,
            "t_s": self.t_s,
            "position_enu_m": list(self.position_enu_m),
            "range_m": self.range_m,
            "azimuth_rad": self.azimuth_rad,
            "elevation_rad": self.elevation_rad,
            "los": self.los,
        }
        if self.extra_values:
            out["extra_values"] = {name: _nan_to_none(v) for name, v in self.extra_values.items()}
        return out

    def to_json(self) -> bytes:
        """UTF-8 JSON of :meth:`to_dict`."""
        return json.dumps(self.to_dict(), allow_nan=False).encode()

    @staticmethod
    def from_json(payload: bytes | str) -> Measurement:
        """Decode a record; raises ValueError naming the bad field."""
        try:
            d = json.loads(payload)
        except (ValueError, UnicodeDecodeError) as exc:
            raise ValueError(f"measurement: not JSON ({exc})") from None
        if not isinstance(d, dict):
            raise ValueError("measurement: expected a JSON object")
        if d.get("schema") != MEASUREMENT_SCHEMA:
            raise ValueError(f"measurement.schema: expected {MEASUREMENT_SCHEMA}, found {d.get('schema')!r}")
        try:
            pos = tuple(float(x) for x in d["position_enu_m"])
            if len(pos) != 3:
                raise ValueError("position_enu_m needs 3 values")

            def opt(key: str) -> float | None:
                v = d[key]
                return None if v is None else float(v)

            extra = d.get("extra_values", {})
            if not isinstance(extra, dict):
                raise ValueError(f"extra_values: expected an object of value name -> number or null, found {extra!r}")

            return Measurement(
                drone=int(d["drone"]),
                sysid=int(d["sysid"]),
                step=int(d["step"]),
                t_s=float(d["t_s"]),
                position_enu_m=pos,
                range_m=opt("range_m"),
                azimuth_rad=opt("azimuth_rad"),
                elevation_rad=opt("elevation_rad"),
                los=bool(d["los"]),
                extra_values=MappingProxyType({str(k): math.nan if v is None else float(v) for k, v in extra.items()}),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"measurement: bad or missing field ({exc})") from None


def _nan_to_none(x: float) -> float | None:
    return None if math.isnan(x) else float(x)


class Payload:
    """The simulated RSS payload of one drone.

    Args:
        world: the mission world.
        drone: 0-based drone index (selects the noise stream). sysid: MAVLink system id.
        ranging, bearing: the drone's sensing roles (κ_j, β_j).
        extra_components: the names of the drone's components beyond range and bearing
            (:data:`planner.sensing.SENSING`, e.g. from :func:`role_extra_components`).
        sensing: the sensing table those names refer to (default :data:`planner.sensing.SENSING`).
        observe: the observation model (default :func:`planner.observation.observe`;
            injectable for tests).
    """

    def __init__(
        self,
        world: PayloadWorld,
        drone: int,
        *,
        sysid: int | None = None,
        ranging: bool = True,
        bearing: bool = False,
        extra_components: Collection[str] = (),
        observe: Callable[..., Any] | None = None,
        sensing: SensingTable | None = None,
    ) -> None:
        if drone < 0:
            raise ValueError(f"Payload.drone must be >= 0, found {drone}")
        if not (ranging or bearing or extra_components):
            raise ValueError("Payload: a drone needs ranging, bearing or both")
        from planner.randomness import measurement_rng
        from planner.sensing import SENSING

        sensing = SENSING if sensing is None else sensing
        known = [c.name for c in sensing.extra_components]
        unknown = sorted(set(extra_components) - set(known))
        if unknown:
            raise ValueError(f"Payload.extra_components: expected names among {known}, found {unknown}")
        #: Masks of the components beyond range and bearing, (1,) bool each (empty: none).
        self.extra_masks = {name: np.array([name in extra_components]) for name in known if name in extra_components}
        self._extra_value_names = tuple(n for c in sensing.extra_components if c.name in extra_components for n in c.value_names)
        self._components = sensing.components
        self._draws = sensing.measurement_draws()

        if observe is None:
            from planner.observation import observe as observe_fn

            observe = observe_fn
        self.world = world
        self.drone = drone
        self.sysid = drone + 1 if sysid is None else sysid
        self.ranging = np.array([ranging])
        self.bearing = np.array([bearing])
        self._observe = observe
        self._rng = measurement_rng(world.seed, world.trial, drone)
        self._next_step = 0
        bmin = np.asarray(world.boxes_min_m, dtype=float).reshape(-1, 3)
        bmax = np.asarray(world.boxes_max_m, dtype=float).reshape(-1, 3)
        self._boxes = (bmin, bmax)

    def measure(self, true_position_enu: ArrayLike, step: int, time_s: float) -> Measurement:
        """Measure at ``true_position_enu`` ((3,) ENU m) for step ``step`` at sim time ``time_s``.

        Raises:
            ValueError: a step already measured, or a non-finite position/time.
        """
        p = np.asarray(true_position_enu, dtype=float).reshape(3)
        if not (np.all(np.isfinite(p)) and math.isfinite(time_s)):
            raise ValueError(f"Payload.measure: non-finite position {p} or time {time_s}")
        if step < self._next_step:
            raise ValueError(f"Payload.measure: step {step} already measured (next is {self._next_step})")
        if step > self._next_step:
            self._rng.random((step - self._next_step, self._draws))  # keep the stream aligned
        self._next_step = step + 1
        # The extra masks only for a drone that has such components (an injected observe
        # may take the eight arguments of range and bearing only).
        extra: tuple[Any, ...] = (self.extra_masks, self._components) if self.extra_masks else ()
        obs = self._observe(
            self.world.source_at(time_s),
            p[None, :],
            self.ranging,
            self.bearing,
            self._boxes[0],
            self._boxes[1],
            self.world.channel,
            self._rng,
            *extra,
        )
        range_m = float(np.asarray(obs.range_m).reshape(-1)[0])
        if self.world.power_offset_db != 0.0:
            from planner.radio.power_offset import offset_of_power_db, offset_ranges  # plain numpy

            gamma = self.world.channel.gamma
            distance = float(np.linalg.norm(self.world.source_at(time_s) - p))
            range_m = float(offset_ranges(np.array(range_m), np.array(distance), offset_of_power_db(self.world.power_offset_db, gamma), gamma))
        return Measurement(
            drone=self.drone,
            sysid=self.sysid,
            step=int(step),
            t_s=float(time_s),
            position_enu_m=(float(p[0]), float(p[1]), float(p[2])),
            range_m=_nan_to_none(range_m),
            azimuth_rad=_nan_to_none(float(np.asarray(obs.azimuth_rad).reshape(-1)[0])),
            elevation_rad=_nan_to_none(float(np.asarray(obs.elevation_rad).reshape(-1)[0])),
            los=bool(np.asarray(obs.los).reshape(-1)[0]),
            extra_values=MappingProxyType({name: float(np.asarray(obs.values[name]).reshape(-1)[0]) for name in self._extra_value_names}),
        )


def roles_to_flags(role: str) -> tuple[bool, bool]:
    """(ranging, bearing) of a mission role, from the role table :data:`planner.sensing.ROLES`.

    Raises:
        ValueError: an unknown role (the message lists the known ones).
    """
    from planner.sensing import sensing_role  # imported here: see Payload.__init__

    found = sensing_role(role)
    return found.ranging, found.bearing


def role_extra_components(role: str) -> tuple[str, ...]:
    """The components beyond range and bearing of a mission role (:data:`planner.sensing.ROLES`),
    the ``extra_components`` of :class:`Payload`.

    Raises:
        ValueError: an unknown role (the message lists the known ones).
    """
    from planner.sensing import BEARING, RANGE, sensing_role  # imported here: see Payload.__init__

    return tuple(c for c in sensing_role(role).components if c not in (RANGE.name, BEARING.name))

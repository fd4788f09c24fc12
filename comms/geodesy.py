"""The mission frame and WGS-84, at the MAVLink edge, through pyproj (never by hand).

Frames and conventions (docs/architecture.md, "Frames, units, time"):

* Mission frame: ENU, metres, x east, y north, z up, about the mission ``origin`` (latitude,
  longitude in degrees WGS-84, altitude in metres AMSL).
* Horizontal: (x, y) is the topocentric (local tangent plane) position of the point at the
  origin's height, pyproj ``+proj=topocentric`` about the origin; exact on the ellipsoid.
* Vertical: z is height above the origin, so ``altitude AMSL = origin.alt_m + z``
  (``altitude_reference: amsl``, MAVLink ``MAV_FRAME_GLOBAL_INT``) and, with
  ``altitude_reference: relative``, the autopilot's altitude above its home is ``z − z_home``
  (``MAV_FRAME_GLOBAL_RELATIVE_ALT_INT``), z_home the mission-frame height of the vehicle's
  home (0 for a drone that took off from ground at the origin's height).

The origin's AMSL altitude is given to pyproj as an ellipsoidal height: a geoid undulation
constant over the mission area cancels between both directions (it changes by well under a
metre over kilometres), and the vertical is carried separately anyway. The curvature of the
earth within a mission (< 8 cm at 1 km) is in the horizontal mapping; heights are along the
local vertical of each point, as autopilots report them.

Two conventions share the one topocentric transform, and callers depend on which one:

* the **mission convention** above (:meth:`MissionFrame.to_global`, :meth:`MissionFrame.to_enu`):
  the planner's MAVLink client, the payload command, the exports and the tests that place
  vehicles: heights are altitudes above the origin's altitude;
* the **topocentric convention** (:meth:`MissionFrame.topocentric_to_geodetic`,
  :meth:`MissionFrame.geodetic_to_topocentric`): the simulated vehicle
  (:mod:`vehicle_sim.frames`), whose physics run in the flat ENU tangent frame itself; its
  reported ellipsoidal height includes the curvature of the earth under the tangent plane
  (x² + y²)/2R (8 cm at 1 km). Where the vehicle reads a latitude/longitude "at the origin's
  height" (global setpoints, DO_REPOSITION) the two conventions give the same (x, y).

LOCAL_NED is the same frame with the axes swapped, N = y, E = x, D = −z
(:meth:`MissionFrame.enu_to_ned`, pyproj ``axisswap``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np

#: Convergence of the horizontal inverse (m); two iterations reach it within 10 km.
_HORIZONTAL_TOL_M = 1e-6


#: ArduPilot SITL's default home (CMAC, Canberra), the default mission origin.
DEFAULT_ORIGIN_LAT_DEG: float = -35.363261
DEFAULT_ORIGIN_LON_DEG: float = 149.165230
DEFAULT_ORIGIN_ALT_M: float = 584.0


@dataclass(frozen=True)
class Origin:
    """Geodetic origin of a mission ENU frame (or of a vehicle's EKF frame).

    The one plain origin type: the mission schema's ``origin`` section converts to it
    (``missions.format.schema.OriginSpec.to_origin()``), the simulated vehicle's configuration holds it.

    Attributes:
        lat_deg, lon_deg: WGS84 latitude and longitude (degrees).
        alt_m: altitude of the origin (m). Treated as height above the WGS84 ellipsoid
            *and* as AMSL (no geoid model): GLOBAL_POSITION_INT.alt and relative_alt differ
            exactly by this value.

    Raises:
        ValueError: a latitude outside (-90, 90), a longitude outside [-180, 180], or a
            non-finite value.
    """

    lat_deg: float = DEFAULT_ORIGIN_LAT_DEG
    lon_deg: float = DEFAULT_ORIGIN_LON_DEG
    alt_m: float = DEFAULT_ORIGIN_ALT_M

    def __post_init__(self) -> None:
        if not (math.isfinite(self.lat_deg) and -90.0 < self.lat_deg < 90.0):
            raise ValueError(f"Origin.lat_deg must be in (-90, 90) degrees, found {self.lat_deg!r}")
        if not (math.isfinite(self.lon_deg) and -180.0 <= self.lon_deg <= 180.0):
            raise ValueError(f"Origin.lon_deg must be in [-180, 180] degrees, found {self.lon_deg!r}")
        if not math.isfinite(self.alt_m):
            raise ValueError(f"Origin.alt_m must be a finite number, found {self.alt_m!r}")


@dataclass(frozen=True)
class GeoPoint:
    """A WGS-84 position: latitude and longitude (degrees), altitude (m AMSL)."""

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float

    @property
    def lat_e7(self) -> int:
        """Latitude as MAVLink's int32 degrees × 1e7."""
        return int(round(self.lat_deg * 1e7))

    @property
    def lon_e7(self) -> int:
        """Longitude as MAVLink's int32 degrees × 1e7."""
        return int(round(self.lon_deg * 1e7))


class OriginSection(Protocol):
    """The schema's ``origin`` section (``missions.format.schema.OriginSpec``; duck-typed: comms does not
    import missions): it converts to an :class:`Origin`."""

    def to_origin(self) -> Origin: ...


class HasOrigin(Protocol):
    """A mission (``missions.format.schema.Mission``): anything with an :class:`OriginSection`."""

    @property
    def origin(self) -> OriginSection: ...


class MissionFrame:
    """Conversions between the mission ENU frame and WGS-84 for one mission origin.

    Args:
        lat_deg, lon_deg: origin latitude and longitude (degrees, WGS-84).
        alt_amsl_m: origin altitude (m AMSL).
    """

    def __init__(self, lat_deg: float, lon_deg: float, alt_amsl_m: float) -> None:
        for name, v in (("lat_deg", lat_deg), ("lon_deg", lon_deg), ("alt_amsl_m", alt_amsl_m)):
            if not math.isfinite(v):
                raise ValueError(f"mission origin {name}: expected a finite number, found {v!r}")
        if not -90.0 < lat_deg < 90.0:
            raise ValueError(f"mission origin latitude: expected (-90, 90) degrees, found {lat_deg!r}")
        self.origin = Origin(float(lat_deg), float(lon_deg), float(alt_amsl_m))
        # pyproj is imported here, by the processes that convert (a vehicle, a planner on MAVLink,
        # an export): about 0.1 s of every other command's start (a study, a check) otherwise.
        from pyproj import Transformer

        # geodetic (lat, lon in degrees, h in m) -> topocentric ENU (m) about the origin
        self._geo_enu = Transformer.from_pipeline(
            "+proj=pipeline"
            " +step +proj=axisswap +order=2,1"
            " +step +proj=unitconvert +xy_in=deg +xy_out=rad"
            " +step +proj=cart +ellps=WGS84"
            f" +step +proj=topocentric +ellps=WGS84 +lat_0={lat_deg!r} +lon_0={lon_deg!r} +h_0={alt_amsl_m!r}"
        )
        # ENU <-> NED about the same origin: N = y, E = x, D = -z
        self._enu_ned = Transformer.from_pipeline("+proj=pipeline +step +proj=axisswap +order=2,1,-3")

    @classmethod
    def of_origin(cls, origin: Origin) -> MissionFrame:
        """The frame about ``origin``."""
        return cls(origin.lat_deg, origin.lon_deg, origin.alt_m)

    @classmethod
    def of_mission(cls, mission: HasOrigin) -> MissionFrame:
        """The frame of a ``missions.format.schema.Mission`` (its ``origin`` section)."""
        return cls.of_origin(mission.origin.to_origin())

    def to_global(self, x_m: float, y_m: float, z_m: float) -> GeoPoint:
        """Mission ENU (m) → WGS-84 (deg, deg, m AMSL = origin altitude + z)."""
        lat, lon, alt = self.to_global_many(np.array([[x_m, y_m, z_m]], dtype=float))[0]
        return GeoPoint(float(lat), float(lon), float(alt))

    def to_global_many(self, enu_m: np.ndarray) -> np.ndarray:
        """Mission ENU (n, 3) m → WGS-84 (n, 3) of (lat deg, lon deg, m AMSL = origin altitude
        + z), many points at once."""
        p = np.asarray(enu_m, dtype=float).reshape(-1, 3)
        h0 = self.origin.alt_m
        # Find the tangent-plane height t of each point at the origin's height above (x, y):
        # start on the plane, then move t so that the ellipsoidal height is h0 (Newton on a
        # derivative of ~1; converges in two steps).
        t = np.zeros(len(p))
        lat = lon = np.zeros(len(p))
        for _ in range(5):
            lat, lon, h = self._geo_enu.transform(p[:, 0], p[:, 1], t, direction="INVERSE")
            if np.all(np.abs(h - h0) < _HORIZONTAL_TOL_M):
                break
            t = t - (h - h0)
        return np.column_stack([lat, lon, h0 + p[:, 2]])

    def to_enu(self, lat_deg: float, lon_deg: float, alt_amsl_m: float) -> tuple[float, float, float]:
        """WGS-84 (deg, deg, m AMSL) → mission ENU (m): (x, y) of the point at the origin's
        height, z = altitude − origin altitude."""
        h0 = self.origin.alt_m
        x, y, _ = self._geo_enu.transform(lat_deg, lon_deg, h0)
        return float(x), float(y), float(alt_amsl_m) - h0

    def to_enu_many(self, lat_lon_alt: np.ndarray) -> np.ndarray:
        """WGS-84 (n, 3) of (lat deg, lon deg, m AMSL) → mission ENU (n, 3), m, many points at
        once (the convention of :meth:`to_enu`)."""
        g = np.asarray(lat_lon_alt, dtype=float).reshape(-1, 3)
        h0 = self.origin.alt_m
        x, y, _ = self._geo_enu.transform(g[:, 0], g[:, 1], np.full(len(g), h0))
        return np.column_stack([x, y, g[:, 2] - h0])

    def matches(self, lat_deg: float, lon_deg: float, alt_amsl_m: float, tol_m: float = 0.05) -> bool:
        """True when a WGS-84 point (e.g. a vehicle's EKF origin) is the mission origin within
        ``tol_m`` metres horizontally and vertically."""
        x, y, z = self.to_enu(lat_deg, lon_deg, alt_amsl_m)
        return math.hypot(x, y) <= tol_m and abs(z) <= tol_m

    def topocentric_to_geodetic(self, x_m: float, y_m: float, z_m: float) -> tuple[float, float, float]:
        """Topocentric ENU (m, the tangent frame at the origin) -> (latitude deg, longitude
        deg, ellipsoidal height m), exact (the simulated vehicle's convention, see the module
        doc)."""
        lat, lon, h = self._geo_enu.transform(x_m, y_m, z_m, direction="INVERSE")
        return float(lat), float(lon), float(h)

    def geodetic_to_topocentric(self, lat_deg: float, lon_deg: float, h_m: float) -> tuple[float, float, float]:
        """(latitude deg, longitude deg, ellipsoidal height m) -> topocentric ENU (m), exact
        (inverse of :meth:`topocentric_to_geodetic`)."""
        x, y, z = self._geo_enu.transform(lat_deg, lon_deg, h_m)
        return float(x), float(y), float(z)

    def enu_to_ned(self, x_m: float, y_m: float, z_m: float) -> tuple[float, float, float]:
        """ENU (m or m/s) -> NED about the same origin: (y, x, -z)."""
        n, e, d = self._enu_ned.transform(x_m, y_m, z_m)
        return float(n), float(e), float(d)

    def ned_to_enu(self, n_m: float, e_m: float, d_m: float) -> tuple[float, float, float]:
        """NED (m or m/s) -> ENU about the same origin: (e, n, -d)."""
        x, y, z = self._enu_ned.transform(n_m, e_m, d_m, direction="INVERSE")
        return float(x), float(y), float(z)

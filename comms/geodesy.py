"""The mission frame and WGS-84, at the MAVLink edge, through pyproj (never by hand).

Frames and conventions (DESIGN.md):

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
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from pyproj import Transformer

#: Convergence of the horizontal inverse (m); two iterations reach it within 10 km.
_HORIZONTAL_TOL_M = 1e-6


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
    """What :meth:`MissionFrame.of_mission` reads of ``missions.schema.Origin`` (duck-typed:
    comms does not import missions)."""

    @property
    def lat_deg(self) -> float: ...
    @property
    def lon_deg(self) -> float: ...
    @property
    def alt_m(self) -> float: ...


class HasOrigin(Protocol):
    """A mission (``missions.schema.Mission``): anything with an :class:`OriginSection`."""

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
        self.origin = GeoPoint(float(lat_deg), float(lon_deg), float(alt_amsl_m))
        # geodetic (lat, lon in degrees, h in m) -> topocentric ENU (m) about the origin
        self._geo_enu = Transformer.from_pipeline(
            "+proj=pipeline"
            " +step +proj=axisswap +order=2,1"
            " +step +proj=unitconvert +xy_in=deg +xy_out=rad"
            " +step +proj=cart +ellps=WGS84"
            f" +step +proj=topocentric +ellps=WGS84 +lat_0={lat_deg!r} +lon_0={lon_deg!r} +h_0={alt_amsl_m!r}"
        )

    @classmethod
    def of_mission(cls, mission: HasOrigin) -> MissionFrame:
        """The frame of a ``missions.schema.Mission`` (its ``origin`` section)."""
        o = mission.origin
        return cls(o.lat_deg, o.lon_deg, o.alt_m)

    def to_global(self, x_m: float, y_m: float, z_m: float) -> GeoPoint:
        """Mission ENU (m) → WGS-84 (deg, deg, m AMSL = origin altitude + z)."""
        lat, lon, alt = self.to_global_many(np.array([[x_m, y_m, z_m]], dtype=float))[0]
        return GeoPoint(float(lat), float(lon), float(alt))

    def to_global_many(self, enu_m: np.ndarray) -> np.ndarray:
        """Mission ENU (n, 3) m → WGS-84 (n, 3) of (lat deg, lon deg, m AMSL = origin altitude
        + z), many points at once."""
        p = np.asarray(enu_m, dtype=float).reshape(-1, 3)
        h0 = self.origin.alt_amsl_m
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
        h0 = self.origin.alt_amsl_m
        x, y, _ = self._geo_enu.transform(lat_deg, lon_deg, h0)
        return float(x), float(y), float(alt_amsl_m) - h0

    def matches(self, lat_deg: float, lon_deg: float, alt_amsl_m: float, tol_m: float = 0.05) -> bool:
        """True when a WGS-84 point (e.g. a vehicle's EKF origin) is the mission origin within
        ``tol_m`` metres horizontally and vertically."""
        x, y, z = self.to_enu(lat_deg, lon_deg, alt_amsl_m)
        return math.hypot(x, y) <= tol_m and abs(z) <= tol_m

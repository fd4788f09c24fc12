"""Frame conversions at the MAVLink edge, all through pyproj (never by hand).

* Mission frame: ENU (x east, y north, z up, metres) about the mission origin.
* Vehicle LOCAL_NED frame: the same frame about the same origin, axes N = y, E = x, D = -z
  (pyproj ``axisswap +order=2,1,-3``).
* Geodetic: WGS84 latitude/longitude (degrees) and height (m); the ENU frame is the
  topocentric frame tangent at the origin (pyproj ``topocentric``), exact on the ellipsoid.
"""

from __future__ import annotations

from pyproj import Transformer

from vehicle_sim.config import Origin

_AXIS_ENU_NED = "+proj=pipeline +step +proj=axisswap +order=2,1,-3"


class LocalFrame:
    """Conversions between the mission ENU frame, the vehicle NED frame and WGS84."""

    def __init__(self, origin: Origin) -> None:
        self.origin = origin
        self._geo_enu = Transformer.from_pipeline(
            "+proj=pipeline"
            " +step +proj=axisswap +order=2,1"
            " +step +proj=unitconvert +xy_in=deg +xy_out=rad"
            " +step +proj=cart +ellps=WGS84"
            f" +step +proj=topocentric +ellps=WGS84 +lat_0={origin.lat_deg!r} +lon_0={origin.lon_deg!r}"
            f" +h_0={origin.alt_m!r}"
        )
        self._enu_ned = Transformer.from_pipeline(_AXIS_ENU_NED)

    def enu_to_ned(self, x_m: float, y_m: float, z_m: float) -> tuple[float, float, float]:
        """ENU (m) -> NED (m) about the same origin."""
        n, e, d = self._enu_ned.transform(x_m, y_m, z_m)
        return float(n), float(e), float(d)

    def ned_to_enu(self, n_m: float, e_m: float, d_m: float) -> tuple[float, float, float]:
        """NED (m) -> ENU (m) about the same origin."""
        x, y, z = self._enu_ned.transform(n_m, e_m, d_m, direction="INVERSE")
        return float(x), float(y), float(z)

    def enu_to_geodetic(self, x_m: float, y_m: float, z_m: float) -> tuple[float, float, float]:
        """ENU (m) -> (latitude deg, longitude deg, altitude m AMSL)."""
        lat, lon, h = self._geo_enu.transform(x_m, y_m, z_m, direction="INVERSE")
        return float(lat), float(lon), float(h)

    def geodetic_to_enu(self, lat_deg: float, lon_deg: float, alt_m: float) -> tuple[float, float, float]:
        """(latitude deg, longitude deg, altitude m AMSL) -> ENU (m)."""
        x, y, z = self._geo_enu.transform(lat_deg, lon_deg, alt_m)
        return float(x), float(y), float(z)

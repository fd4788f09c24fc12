"""The simulated vehicle's frames (comms.geodesy.MissionFrame, topocentric convention) against
an independent reference: WGS-84 -> ECEF by pyproj (EPSG:4979 -> EPSG:4978), then the closed-form
ENU rotation about the origin. (Before vehicle_sim.geo.LocalFrame was removed, the same sample
points were checked bit for bit against it: the vehicle's numbers did not change.)"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from pyproj import Transformer

from comms.geodesy import MissionFrame
from vehicle_sim.config import Origin

ORIGINS = (Origin(), Origin(45, 7, 100), Origin(47.397742, 8.545594, 488.0), Origin(-89.5, -179.9, -20.0), Origin(60.0, 180.0, 8000.0))
POINTS = tuple(itertools.product((-1500.0, -3.25, 0.0, 10.0, 2000.0), (-700.0, 0.0, 150.0), (-5.0, 0.0, 8.0, 120.0)))
TO_ECEF = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True)


def _enu_rotation(origin: Origin) -> np.ndarray:
    """Rows: east, north, up unit vectors at the origin, in ECEF."""
    lat, lon = math.radians(origin.lat_deg), math.radians(origin.lon_deg)
    sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
    return np.array([[-so, co, 0.0], [-sl * co, -sl * so, cl], [cl * co, cl * so, sl]])


def _reference_enu(origin: Origin, lat_deg: float, lon_deg: float, h_m: float) -> np.ndarray:
    p = np.array(TO_ECEF.transform(lon_deg, lat_deg, h_m))
    o = np.array(TO_ECEF.transform(origin.lon_deg, origin.lat_deg, origin.alt_m))
    return _enu_rotation(origin) @ (p - o)


@pytest.mark.parametrize("origin", ORIGINS)
def test_vehicle_frame_against_ecef_closed_form(origin: Origin) -> None:
    frame = MissionFrame.of_origin(origin)
    for x, y, z in POINTS:
        lat, lon, h = frame.topocentric_to_geodetic(x, y, z)
        np.testing.assert_allclose(_reference_enu(origin, lat, lon, h), (x, y, z), rtol=0, atol=1e-6)
        np.testing.assert_allclose(frame.geodetic_to_topocentric(lat, lon, h), (x, y, z), rtol=0, atol=1e-6)
        assert frame.enu_to_ned(x, y, z) == (y, x, -z)
        assert frame.ned_to_enu(y, x, -z) == (x, y, z)
        # a lat/lon read at the origin's height: both conventions give the same (x, y)
        assert frame.to_enu(lat, lon, origin.alt_m)[:2] == frame.geodetic_to_topocentric(lat, lon, origin.alt_m)[:2]


def test_vehicle_height_includes_the_curvature_the_mission_convention_does_not() -> None:
    """The vehicle reports the ellipsoidal height of its tangent-frame position (≈ z + d²/2R);
    the mission convention maps z to the origin's altitude + z exactly."""
    frame = MissionFrame.of_origin(Origin())
    _, _, h = frame.topocentric_to_geodetic(1000.0, 0.0, 10.0)
    assert h - Origin().alt_m - 10.0 == pytest.approx(1000.0**2 / (2 * 6.371e6), rel=0.02)
    assert frame.to_global(1000.0, 0.0, 10.0).alt_amsl_m == Origin().alt_m + 10.0

"""The simulated vehicle's frames are comms.geodesy's MissionFrame (topocentric convention):
bit-identical to the vehicle's former pyproj frame (vehicle_sim.geo.LocalFrame) on sample points."""

from __future__ import annotations

import itertools

import pytest

from comms.geodesy import MissionFrame
from vehicle_sim.config import Origin
from vehicle_sim.geo import LocalFrame

ORIGINS = (Origin(), Origin(45, 7, 100), Origin(47.397742, 8.545594, 488.0), Origin(-89.5, -179.9, -20.0), Origin(60.0, 180.0, 8000.0))
POINTS = tuple(itertools.product((-1500.0, -3.25, 0.0, 10.0, 2000.0), (-700.0, 0.0, 150.0), (-5.0, 0.0, 8.0, 120.0)))


@pytest.mark.parametrize("origin", ORIGINS)
def test_mission_frame_topocentric_is_the_old_vehicle_frame(origin: Origin) -> None:
    old = LocalFrame(origin)
    new = MissionFrame.of_origin(origin)
    for x, y, z in POINTS:
        geo = old.enu_to_geodetic(x, y, z)
        assert new.topocentric_to_geodetic(x, y, z) == geo
        assert new.geodetic_to_topocentric(*geo) == old.geodetic_to_enu(*geo)
        assert new.enu_to_ned(x, y, z) == old.enu_to_ned(x, y, z)
        assert new.ned_to_enu(x, y, z) == old.ned_to_enu(x, y, z)
        # the horizontal of a lat/lon at the origin's height: the mission convention's to_enu
        assert new.to_enu(geo[0], geo[1], origin.alt_m)[:2] == old.geodetic_to_enu(geo[0], geo[1], origin.alt_m)[:2]

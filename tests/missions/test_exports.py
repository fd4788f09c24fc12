"""KML and GeoJSON of a run (missions/study/exports.py), read back with the libraries and checked
against the simulator's ENU positions through an independent geodetic → ENU pipeline (pyproj's
topocentric conversion about the mission origin, written out here)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from pyproj import Transformer

from missions.study.exports import write_exports
from missions.format.loader import load_mission
from missions.study.simulator import RunSpec, simulate


def enu_of(mission, lon_lat_alt: np.ndarray) -> np.ndarray:
    """(lon, lat, m AMSL) → mission ENU (m): horizontal by the topocentric pipeline at the
    origin's height, vertical as altitude − origin altitude (the mission frame's convention)."""
    o = mission.origin
    t = Transformer.from_pipeline(
        "+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad +step +proj=cart +ellps=WGS84"
        f" +step +proj=topocentric +ellps=WGS84 +lat_0={o.lat_deg} +lon_0={o.lon_deg} +h_0={o.alt_m}")
    x, y, _ = t.transform(lon_lat_alt[:, 0], lon_lat_alt[:, 1], np.full(len(lon_lat_alt), o.alt_m))
    return np.column_stack([x, y, lon_lat_alt[:, 2] - o.alt_m])


def test_kml_and_geojson_hold_the_flight_in_real_coordinates(tmp_path: Path) -> None:
    from fastkml import kml

    mission = load_mission("paper/heterogeneous")
    res = simulate(RunSpec(mission, "A", 1, 40))
    write_exports(res, tmp_path)
    n = mission.drones.count
    pos = res.positions_m[:, 0]  # (K+1, N, 3)

    gj = json.loads((tmp_path / "trajectories.geojson").read_text())
    lines = [f for f in gj["features"] if f["properties"]["kind"] == "trajectory"]
    assert [f["properties"]["drone"] for f in lines] == list(range(1, n + 1))
    for f in lines:
        c = np.array(f["geometry"]["coordinates"])
        assert f["geometry"]["type"] == "LineString" and c.shape == (41, 3)
        np.testing.assert_allclose(enu_of(mission, c), pos[:, f["properties"]["drone"] - 1], atol=1e-3)
    (src,) = [f for f in gj["features"] if f["properties"]["kind"] == "source"]
    np.testing.assert_allclose(enu_of(mission, np.array([src["geometry"]["coordinates"]]))[0], mission.source.position_m, atol=1e-3)
    ests = [f for f in gj["features"] if f["properties"]["kind"] == "estimate"]
    np.testing.assert_allclose(enu_of(mission, np.array([f["geometry"]["coordinates"] for f in ests])), res.estimates_m[-1, 0], atol=1e-3)

    doc = kml.KML.parse(tmp_path / "trajectories.kml")
    (document,) = doc.features
    folders = {f.name: f for f in document.features}
    tracks = folders["trajectories"].features
    assert len(tracks) == n and tracks[0].name == "drone 1 (ranging)"
    c = np.array(tracks[2].kml_geometry.geometry.coords)
    np.testing.assert_allclose(enu_of(mission, c), pos[:, 2], atol=1e-3)

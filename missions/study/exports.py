"""A run's flight in the mission's real coordinates: KML (Google Earth) and GeoJSON (QGIS).

For the first trial of a run (a ``fimnav launch`` has one): each drone's trajectory as a 3-D
line, its final source estimate as a point, and the true source (its position at the end of
the run), in WGS-84 longitude, latitude and altitude above mean sea level (the mission
origin's altitude plus the ENU height, as the planner's setpoints use it,
:class:`comms.geodesy.MissionFrame`). KML lines are ``absolute`` altitude, extruded to the
ground; GeoJSON positions are (longitude, latitude, altitude m) as RFC 7946 orders them.
Written with fastkml and geojson.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Literal, TypedDict

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:  # pragma: no cover - types only
    from missions.study.simulator import SimulationResult


class Feature(TypedDict):
    """One feature of :func:`flight_features`."""

    kind: Literal["trajectory", "estimate", "source"]
    name: str
    drone: int | None  # 1-based
    role: str | None
    lonlatalt: NDArray[np.float64]  # (n, 3): lon deg, lat deg, m AMSL


def flight_features(result: SimulationResult) -> list[Feature]:
    """The run's features, frame-converted: dicts with ``kind`` (trajectory, estimate,
    source), ``name``, ``drone`` (1-based or None), ``role`` and ``lonlatalt`` ((n, 3): lon deg,
    lat deg, m AMSL)."""
    from comms.geodesy import MissionFrame

    mission = result.spec.mission
    frame = MissionFrame.of_mission(mission)
    pos = np.asarray(result.positions_m[:, 0])  # (K+1, N, 3), m, ENU
    est = np.asarray(result.estimates_m[-1, 0])  # (N, 3)
    src = np.asarray(result.source_m[-1], dtype=float).reshape(3)
    roles = mission.drones.roles

    n = pos.shape[1]
    # One conversion for every point: the trajectories, then the estimates, then the source.
    g = frame.to_global_many(np.concatenate([pos.transpose(1, 0, 2).reshape(-1, 3), est, src[None]]))
    lla = np.column_stack([g[:, 1], g[:, 0], g[:, 2]])
    k1 = pos.shape[0]
    out: list[Feature] = [
        {"kind": "trajectory", "name": f"drone {i + 1} ({roles[i]})", "drone": i + 1, "role": roles[i], "lonlatalt": lla[i * k1 : (i + 1) * k1]}
        for i in range(n)
    ]
    out.extend(
        {"kind": "estimate", "name": f"drone {i + 1}'s source estimate", "drone": i + 1, "role": roles[i], "lonlatalt": lla[n * k1 + i][None]}
        for i in range(n)
    )
    out.append({"kind": "source", "name": "source", "drone": None, "role": None, "lonlatalt": lla[-1:]})
    # Points never known (a drone of a launch whose planner never flew: NaN) are left out, and
    # so is a feature without enough of them (a line needs two points).
    for f in out:
        f["lonlatalt"] = f["lonlatalt"][np.isfinite(f["lonlatalt"]).all(axis=1)]
    return [f for f in out if len(f["lonlatalt"]) >= (2 if f["kind"] == "trajectory" else 1)]


def write_kml(features: list[Feature], name: str, path: Path) -> None:
    """The run's flight (:func:`flight_features`) as KML (fastkml) named ``name``: a folder of
    trajectories, one of estimates, the source."""
    from fastkml import geometry as kg
    from fastkml import kml
    from fastkml.containers import Document, Folder
    from fastkml.enums import AltitudeMode
    from fastkml.features import Placemark
    from pygeoif import geometry as geo

    from planner.geometry import vec3

    folders: dict[str, list[Placemark]] = {"trajectory": [], "estimate": [], "source": []}
    for f in features:
        c = [vec3(row) for row in f["lonlatalt"]]
        g: kg.LineString | kg.Point
        if f["kind"] == "trajectory":
            g = kg.LineString(altitude_mode=AltitudeMode.absolute, extrude=True, geometry=geo.LineString(c))
        else:
            g = kg.Point(altitude_mode=AltitudeMode.absolute, geometry=geo.Point(*c[0]))
        folders[f["kind"]].append(Placemark(name=f["name"], kml_geometry=g))
    names = {"trajectory": "trajectories", "estimate": "source estimates (last step)", "source": "source (true)"}
    doc = Document(name=name, features=[Folder(name=names[k], features=v) for k, v in folders.items()])
    path.write_text(kml.KML(features=[doc]).to_string(prettyprint=True))


def write_geojson(features: list[Feature], path: Path) -> None:
    """The run's flight (:func:`flight_features`) as a GeoJSON FeatureCollection (geojson)."""
    import geojson

    feats = []
    for f in features:
        c = [tuple(map(float, row)) for row in f["lonlatalt"]]
        # 9 decimals of a degree (0.1 mm): the library rounds to 6 (11 cm) by default.
        g = geojson.LineString(c, precision=9) if f["kind"] == "trajectory" else geojson.Point(c[0], precision=9)
        feats.append(geojson.Feature(geometry=g, properties={"kind": f["kind"], "name": f["name"], "drone": f["drone"], "role": f["role"]}))
    path.write_text(geojson.dumps(geojson.FeatureCollection(feats), indent=1))


def write_exports(result: SimulationResult, run_dir: Path) -> None:
    """``trajectories.kml`` and ``trajectories.geojson`` in ``run_dir``."""
    features = flight_features(result)
    write_kml(features, f"fimnav {result.spec.mission.id}", run_dir / "trajectories.kml")
    write_geojson(features, run_dir / "trajectories.geojson")

"""A run's flight in the mission's real coordinates: KML (Google Earth) and GeoJSON (QGIS).

For the first trial of a run (a ``fimnav launch`` has one): each drone's trajectory as a 3-D
line, its final source estimate as a point, and the true source (its position at the end of
the run), in WGS-84 longitude, latitude and altitude above mean sea level (the mission
origin's altitude plus the ENU height, as the planner's setpoints use it,
:class:`comms.geodesy.MissionFrame`). KML lines are ``absolute`` altitude, extruded to the
ground; GeoJSON positions are (longitude, latitude, altitude m) as RFC 7946 orders them.
Written as text (KML 2.2 and JSON).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Literal, TypedDict
from xml.sax.saxutils import escape

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:  # pragma: no cover - types only
    from missions.study.records import SimulationResult


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


def _kml_coordinates(lonlatalt: NDArray[np.float64]) -> str:
    """KML's ``lon,lat,alt`` tuples, space separated, each number as Python's shortest repr
    (the float read back is the float written)."""
    return " ".join(f"{lon!r},{lat!r},{alt!r}" for lon, lat, alt in lonlatalt.astype(float).tolist())


def write_kml(features: list[Feature], name: str, path: Path) -> None:
    """The run's flight (:func:`flight_features`) as KML 2.2 named ``name``: a folder of
    trajectories (``LineString``, ``absolute`` altitude, extruded to the ground), one of
    estimates, the source (``Point``). Written as text: a KML library costs a study more time
    than its whole results directory (tests/missions/test_exports.py reads it back with
    fastkml)."""
    names = {"trajectory": "trajectories", "estimate": "source estimates (last step)", "source": "source (true)"}
    folders: dict[str, list[str]] = {kind: [] for kind in names}
    for f in features:
        coords = _kml_coordinates(f["lonlatalt"] if f["kind"] == "trajectory" else f["lonlatalt"][:1])
        tag = "LineString" if f["kind"] == "trajectory" else "Point"
        extrude = "\n          <extrude>1</extrude>" if tag == "LineString" else ""
        folders[f["kind"]].append(
            f"      <Placemark>\n        <name>{escape(f['name'])}</name>\n        <{tag}>{extrude}\n"
            f"          <altitudeMode>absolute</altitudeMode>\n          <coordinates>{coords}</coordinates>\n"
            f"        </{tag}>\n      </Placemark>\n"
        )
    body = "".join(f"    <Folder>\n      <name>{escape(names[kind])}</name>\n{''.join(marks)}    </Folder>\n" for kind, marks in folders.items())
    path.write_text(
        '<?xml version="1.0" encoding="UTF-8"?>\n<kml xmlns="http://www.opengis.net/kml/2.2">\n  <Document>\n'
        f"    <name>{escape(name)}</name>\n{body}  </Document>\n</kml>\n"
    )


def write_geojson(features: list[Feature], path: Path) -> None:
    """The run's flight (:func:`flight_features`) as an RFC 7946 GeoJSON FeatureCollection:
    (longitude, latitude, altitude m) to 9 decimals (0.1 mm of a degree)."""
    feats = []
    for f in features:
        c = [[round(v, 9) for v in row] for row in f["lonlatalt"].astype(float).tolist()]
        geometry = {"type": "LineString", "coordinates": c} if f["kind"] == "trajectory" else {"type": "Point", "coordinates": c[0]}
        feats.append(
            {"type": "Feature", "geometry": geometry, "properties": {"kind": f["kind"], "name": f["name"], "drone": f["drone"], "role": f["role"]}}
        )
    # One feature per line (json's C encoder: an indented dump takes its Python one, 20 x slower).
    path.write_text('{"type": "FeatureCollection", "features": [\n' + ",\n".join(json.dumps(f) for f in feats) + "\n]}\n")


def write_exports(result: SimulationResult, run_dir: Path) -> None:
    """``trajectories.kml`` and ``trajectories.geojson`` in ``run_dir``."""
    features = flight_features(result)
    write_kml(features, f"fimnav {result.spec.mission.id}", run_dir / "trajectories.kml")
    write_geojson(features, run_dir / "trajectories.geojson")

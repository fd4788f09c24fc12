"""The maps of ``fimnav localize``: KML (Google Earth), GeoJSON (QGIS) and a PNG.

In WGS-84 (KML and GeoJSON: longitude, latitude, altitude m, as :mod:`missions.exports`): the
flight (the samples used, a 3-D line), the 95 % confidence region (polygons at the emitter's
height, the outline of the profile-likelihood region on its refined grid; on the coarse grid
when the region reaches the edge of the search area) and, only when the log localizes the
emitter, the estimate as a point. A log that does not localize it gets no point: the region
and the reasons say what is known. The PNG is the same in the local frame (metres east and
north), the samples coloured by power, censored ones grey.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from planner.radio.localize import Localization, RegionGrid

if TYPE_CHECKING:  # pragma: no cover - types only
    from comms.geodesy import MissionFrame
    from planner.radio.localize import RadioLog

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class MapPoint:
    """A labelled point to draw (e.g. a reference position), local frame (3,) m."""

    name: str
    position_m: FloatArray


def region_outlines(region: RegionGrid) -> list[FloatArray]:
    """The outlines of the region {deviance ≤ threshold}, each (k, 2) m (x, y), closed."""
    import contourpy

    z = np.where(np.isfinite(region.deviance), region.deviance, np.inf)
    gen = contourpy.contour_generator(region.x_m, region.y_m, np.minimum(z, 1e12))
    out = []
    for line in gen.lines(region.threshold):
        pts = np.asarray(line, dtype=float)
        if len(pts) >= 3:
            if not np.allclose(pts[0], pts[-1]):
                pts = np.vstack([pts, pts[:1]])
            out.append(pts)
    return out


def map_region(result: Localization) -> RegionGrid:
    """The grid the maps draw: the refined one, or the coarse one when the region reaches the
    edge of the search area (the refined grid covers only part of it then)."""
    coarse = result.coarse
    mask = coarse.mask
    if np.concatenate([mask[0], mask[-1], mask[:, 0], mask[:, -1]]).any():
        return coarse
    return result.region


def _lonlatalt(frame: MissionFrame, enu: FloatArray) -> FloatArray:
    g = frame.to_global_many(enu)
    return np.column_stack([g[:, 1], g[:, 0], g[:, 2]])


def features(result: Localization, log: RadioLog, frame: MissionFrame, extra: list[MapPoint] | None = None) -> list[dict[str, Any]]:
    """The map's features: dicts with ``kind`` (flight, region, estimate, reference), ``name``
    and ``lonlatalt`` ((k, 3) lon deg, lat deg, m)."""
    z = float(result.estimate_m[2])
    feats: list[dict[str, Any]] = [{"kind": "flight", "name": "flight (samples used)", "lonlatalt": _lonlatalt(frame, log.positions_m)}]
    for i, line in enumerate(region_outlines(map_region(result))):
        enu = np.column_stack([line, np.full(len(line), z)])
        feats.append({"kind": "region", "name": f"95 % confidence region (part {i + 1})", "lonlatalt": _lonlatalt(frame, enu)})
    if result.localized:
        feats.append({"kind": "estimate", "name": "emitter estimate", "lonlatalt": _lonlatalt(frame, result.estimate_m[None])})
    feats.extend({"kind": "reference", "name": p.name, "lonlatalt": _lonlatalt(frame, np.asarray(p.position_m, float)[None])} for p in extra or [])
    return feats


def write_kml(feats: list[dict[str, Any]], name: str, path: Path) -> None:
    """The features as KML (fastkml): the flight as an absolute-altitude line, regions as
    polygons, points as points."""
    from fastkml import geometry as kg
    from fastkml import kml
    from fastkml.containers import Document
    from fastkml.enums import AltitudeMode
    from fastkml.features import Placemark
    from pygeoif import geometry as geo

    marks = []
    for f in feats:
        c = [(float(row[0]), float(row[1]), float(row[2])) for row in f["lonlatalt"]]
        g: kg.LineString | kg.Polygon | kg.Point
        if f["kind"] == "flight":
            g = kg.LineString(altitude_mode=AltitudeMode.absolute, geometry=geo.LineString(c))
        elif f["kind"] == "region":
            g = kg.Polygon(altitude_mode=AltitudeMode.absolute, geometry=geo.Polygon(c))
        else:
            g = kg.Point(altitude_mode=AltitudeMode.absolute, geometry=geo.Point(*c[0]))
        marks.append(Placemark(name=f["name"], kml_geometry=g))
    path.write_text(kml.KML(features=[Document(name=name, features=marks)]).to_string(prettyprint=True))


def write_geojson(feats: list[dict[str, Any]], properties: dict[str, Any], path: Path) -> None:
    """The features as a GeoJSON FeatureCollection (geojson); ``properties`` go on the
    collection (the verdict, the PEB)."""
    import geojson

    out = []
    for f in feats:
        c = [tuple(float(v) for v in row) for row in f["lonlatalt"]]
        if f["kind"] == "flight":
            g: Any = geojson.LineString(c, precision=9)
        elif f["kind"] == "region":
            g = geojson.Polygon([c], precision=9)
        else:
            g = geojson.Point(c[0], precision=9)
        out.append(geojson.Feature(geometry=g, properties={"kind": f["kind"], "name": f["name"]}))
    collection = geojson.FeatureCollection(out)
    collection["properties"] = properties
    path.write_text(geojson.dumps(collection, indent=1))


def write_png(result: Localization, log: RadioLog, title: str, path: Path, extra: list[MapPoint] | None = None) -> None:
    """The localization in the local frame (m east, m north): samples coloured by power
    (censored grey), the region's outline, the estimate (only if localized), ``extra`` points."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 6.5))
    p = log.positions_m
    det = ~log.censored & np.isfinite(log.power_db)
    cen = log.censored
    if cen.any():
        ax.scatter(p[cen, 0], p[cen, 1], s=4, c="0.7", marker="x", linewidths=0.5, label=f"censored ({int(cen.sum())})")
    sc = ax.scatter(p[det, 0], p[det, 1], s=5, c=log.power_db[det], cmap="viridis", label=f"detected ({int(det.sum())})")
    fig.colorbar(sc, ax=ax, label="received power (dB)")
    for i, line in enumerate(region_outlines(map_region(result))):
        ax.plot(line[:, 0], line[:, 1], color="crimson", lw=1.5, label="95 % region" if i == 0 else None)
    if result.localized:
        ax.plot(*result.estimate_m[:2], marker="*", ms=14, color="crimson", mec="k", ls="none", label="estimate")
    markers = iter(("D", "s", "^", "v", "P"))
    for pt in extra or []:
        ax.plot(pt.position_m[0], pt.position_m[1], marker=next(markers, "o"), ms=8, ls="none", mec="k", label=pt.name)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)

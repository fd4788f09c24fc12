"""``fimnav localize LOG``: an emitter's position from a recorded flight's received power.

LOG is a CSV log or a ``fimnav launch`` results directory (:mod:`missions.format.radiolog`). The
estimate (:mod:`planner.radio.localize`) treats the transmit power as unknown (``--power
known`` uses the mission's reference power), undetected samples as censored, and says plainly
when the log cannot localize the emitter (the flight never came near it, the evidence is
flat, two places fit): then it prints the reasons and gives no point. Written to ``--out``:
``localization.json`` (everything printed, and more), ``localization.kml``,
``localization.geojson`` and ``localization.png``. Exit status 0 whether localized or not; 2
for a malformed log or argument.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

from comms.errors import UsageError

if TYPE_CHECKING:  # pragma: no cover - types only
    from missions.format.radiolog import FlightLog
    from planner.radio.localize import Localization, LocalizeOptions, Thinning

#: A log whose altitudes span at least this (m) includes its take-off: its lowest altitude is the
#: ground, the default emitter height.
TAKEOFF_SPAN_M: float = 10.0
#: Without a take-off in the log (or a mission's search box), the emitter's height is searched
#: this far below the lowest altitude flown (m).
GROUND_SEARCH_M: float = 100.0
#: The antenna patterns (:data:`planner.radio.pathloss.PATTERNS`, not imported here: ``fimnav
#: --help`` stays quick).
PATTERN_NAMES: tuple[str, ...] = ("isotropic", "dipole", "dipole-pair")
#: Files ``fimnav localize`` writes in its output directory.
OUTPUTS: tuple[str, ...] = ("localization.json", "localization.kml", "localization.geojson", "localization.png")


def register(subparsers: Any) -> None:
    """Add the ``localize`` subcommand."""
    p = subparsers.add_parser(
        "localize",
        help="estimate an emitter's position from a recorded flight's received power (CSV log or launch results)",
        description="Estimate an emitter's position, its 95 %% confidence region and its PEB from a received-power log "
        "(a CSV with time, latitude, longitude, altitude, power in dB, optionally bearing and lock/quality columns; or a "
        "fimnav launch results directory). Unknown transmit power, censored samples; says when the log cannot localize it.",
    )
    p.add_argument("log", type=Path, metavar="LOG", help="a CSV log or a fimnav launch results directory")
    add_log_arguments(p)
    p.add_argument(
        "--out", type=Path, help="output directory (default: <LOG name>_localization/ here; RESULTS/localization/ for a results directory)"
    )
    p.add_argument("--overwrite", action="store_true", help="replace the outputs of an earlier localize in --out")
    p.add_argument("--power", choices=("unknown", "known"), default="unknown", help="the transmit power: estimated (default) or known")
    p.add_argument("--reference-power-db", type=float, help="with --power known: the power 1 m from the emitter, dB (default: the mission's channel)")
    p.add_argument(
        "--exponent",
        default=None,
        metavar="GAMMA|free",
        help="the path-loss exponent, or 'free' to estimate it (default: the mission's; free without one)",
    )
    p.add_argument(
        "--emitter-alt",
        default=None,
        metavar="METRES|free",
        help="the emitter's height in the log's altitude (or the mission's z); 'free' to estimate it "
        "(default: free in the mission's search box, else the log's lowest altitude: an emitter on the ground)",
    )
    p.add_argument("--margin-m", type=float, default=300.0, help="search this far around the flight (default 300 m; a mission's search box wins)")
    p.add_argument("--bearing-sigma-deg", type=float, help="σ of a bearing column, degrees (default: the mission's, else 10)")
    p.add_argument("--grid", type=int, default=48, help="grid points per axis of the search (default 48)")
    p.set_defaults(func=run)


def add_log_arguments(p: argparse.ArgumentParser) -> None:
    """The options ``localize`` and ``calibrate`` share: the mission, censoring, spacing, pattern."""
    p.add_argument("--mission", metavar="MISSION", help="a mission file or bundled name: its origin, buildings (LOS/NLOS) and channel")
    p.add_argument(
        "--threshold-db",
        type=float,
        help="detection threshold: samples below it are censored (default: the lowest detected power, if any sample is unlocked)",
    )
    p.add_argument("--min-quality", type=float, help="samples whose quality column is below this are unlocked (censored)")
    p.add_argument(
        "--spacing-m",
        default="auto",
        metavar="METRES|auto",
        help="use one sample per this much flight (default auto: the residual's correlation distance; 0: every sample)",
    )
    p.add_argument(
        "--pattern",
        choices=PATTERN_NAMES,
        default="isotropic",
        help="the antennas: isotropic (default), a vertical dipole at the emitter (a zenith null), or vertical dipoles at both ends",
    )


def parse_spacing(text: str) -> float | None:
    """``--spacing-m``: None for auto, else metres ≥ 0."""
    if text == "auto":
        return None
    try:
        v = float(text)
    except ValueError:
        raise UsageError(f"--spacing-m: expected metres (a number >= 0) or 'auto', found {text!r}") from None
    if not (math.isfinite(v) and v >= 0.0):
        raise UsageError(f"--spacing-m: expected metres (a number >= 0) or 'auto', found {text!r}")
    return v


def read_log(args: argparse.Namespace) -> FlightLog:
    """The log of ``args.log`` with ``--mission``, ``--threshold-db``, ``--min-quality``."""
    from missions.format.loader import load_mission
    from missions.format.radiolog import read_flight_log

    mission = load_mission(args.mission) if args.mission else None
    return read_flight_log(args.log, mission, args.threshold_db, args.min_quality)


def _float_or_free(name: str, text: str | None) -> float | str | None:
    if text is None or text == "free":
        return text
    try:
        v = float(text)
    except ValueError:
        raise UsageError(f"{name}: expected a number or 'free', found {text!r}") from None
    if not math.isfinite(v):
        raise UsageError(f"{name}: expected a finite number or 'free', found {text!r}")
    return v


def _search_area(args: argparse.Namespace, flight: FlightLog) -> tuple[tuple[float, float], tuple[float, float], tuple[float, float], bool]:
    """(area min, area max, heights searched, from a mission's search box) of the search."""
    mission = flight.mission
    box = mission.source.search_box if mission is not None else None
    if box is not None:
        return (box.min_m[0], box.min_m[1]), (box.max_m[0], box.max_m[1]), (box.min_m[2], box.max_m[2]), True
    if not (math.isfinite(args.margin_m) and args.margin_m > 0.0):
        raise UsageError(f"--margin-m: expected a positive number of metres, found {args.margin_m}")
    pos = flight.log.positions_m
    low = float(pos[:, 2].min())
    return (
        (float(pos[:, 0].min() - args.margin_m), float(pos[:, 1].min() - args.margin_m)),
        (float(pos[:, 0].max() + args.margin_m), float(pos[:, 1].max() + args.margin_m)),
        (low - GROUND_SEARCH_M, low),
        False,
    )


def _emitter_height(args: argparse.Namespace, flight: FlightLog, z_range: tuple[float, float], boxed: bool, notes: list[str]) -> float | None:
    """The emitter's height (m), or None to estimate it: ``--emitter-alt``, else free in a
    mission's search box, else the log's lowest altitude when the log holds its take-off."""
    alt = _float_or_free("--emitter-alt", args.emitter_alt)
    pos = flight.log.positions_m
    span = float(pos[:, 2].max() - pos[:, 2].min())
    if alt == "free" or (alt is None and (boxed or span < TAKEOFF_SPAN_M)):
        if not boxed:
            notes.append(
                f"emitter height estimated between {z_range[0]:.1f} and {z_range[1]:.1f} m (the log holds no take-off; --emitter-alt to set it)"
            )
        return None
    if alt is None:
        low = float(pos[:, 2].min())
        notes.append(f"emitter height {low:.1f} m: the log's lowest altitude, its take-off point (an emitter on the ground; --emitter-alt to set)")
        return low
    return float(alt)


def _channel_knowns(args: argparse.Namespace, flight: FlightLog) -> tuple[float | None, float | None]:
    """(γ, P0): each the value known, or None to estimate it (``--exponent``, ``--power``)."""
    mission = flight.mission
    exponent = _float_or_free("--exponent", args.exponent)
    gamma: float | None = None
    if isinstance(exponent, float):
        if not exponent > 0.0:
            raise UsageError(f"--exponent: expected a positive exponent or 'free', found {args.exponent!r}")
        gamma = exponent
    elif exponent is None and mission is not None:
        gamma = mission.channel.path_loss_exponent
    if args.power != "known":
        return gamma, None
    reference = args.reference_power_db
    if reference is None and mission is not None:
        reference = mission.channel.reference_power_db
    if reference is None and args.log.is_dir():
        reference = 0.0  # a launch's ranges are read as power with 0 dB at 1 m
    if reference is None:
        raise UsageError(
            "--power known: expected --reference-power-db or a mission whose channel has reference_power_db (fimnav calibrate writes it)"
        )
    return gamma, float(reference)


def options_from_args(args: argparse.Namespace, flight: FlightLog) -> tuple[LocalizeOptions, list[str]]:
    """The :class:`planner.radio.localize.LocalizeOptions` of the arguments, the mission and the
    log, and notes saying what was assumed."""
    import numpy as np

    from planner.radio.localize import LocalizeOptions
    from planner.radio.pathloss import Pattern

    mission = flight.mission
    notes: list[str] = []
    area_min, area_max, z_range, boxed = _search_area(args, flight)
    emitter_z = _emitter_height(args, flight, z_range, boxed, notes)
    gamma, reference = _channel_knowns(args, flight)
    if args.bearing_sigma_deg:
        sigma_b = math.radians(args.bearing_sigma_deg)
    else:
        sigma_b = mission.channel.sigma_bearing_rad if mission is not None else math.radians(10.0)
    boxes_min, boxes_max = mission.obstacle_bounds() if mission is not None else (np.zeros((0, 3)), np.zeros((0, 3)))
    factor = mission.channel.sigma_ratio_nlos / mission.channel.sigma_ratio_los if mission is not None else 1.0
    try:
        options = LocalizeOptions(
            area_min_m=area_min,
            area_max_m=area_max,
            emitter_z_m=emitter_z,
            z_range_m=z_range,
            reference_power_db=reference,
            gamma=gamma,
            nlos_sigma_factor=factor,
            pattern=Pattern(args.pattern),
            bearing_sigma_rad=sigma_b,
            boxes_min=boxes_min,
            boxes_max=boxes_max,
            grid=args.grid,
        )
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return options, notes


def default_out(log_path: Path) -> Path:
    """``RESULTS/localization`` for a results directory, ``<stem>_localization`` here for a file."""
    if log_path.is_dir():
        return log_path / "localization"
    return Path(f"{log_path.stem}_localization")


def run(args: argparse.Namespace) -> int:
    """Localize, print the verdict and write the outputs."""
    from planner.radio.localize import localize, thinning

    out = args.out or default_out(args.log)
    taken = [name for name in OUTPUTS if (out / name).exists()]
    if taken and not args.overwrite:
        raise UsageError(f"{out}: already holds {', '.join(taken)} of an earlier localize (--overwrite to replace, or another --out)")
    flight = read_log(args)
    options, notes = options_from_args(args, flight)
    spacing = parse_spacing(args.spacing_m)
    try:
        thin = thinning(flight.log, options, spacing)
        used = flight.log.subset(thin.kept)
        result = localize(used, options)
    except ValueError as exc:
        raise UsageError(f"{args.log}: {exc}") from None
    report = build_report(args.log, flight, options, thin, result, [*flight.notes, *notes])
    from missions.runtime.rundir import make_results_dir, writing

    make_results_dir(out)
    with writing(out):
        write_outputs(out, report, result, flight, thin)
    print_report(report, out)
    return 0


def build_report(
    log_path: Path, flight: FlightLog, options: LocalizeOptions, thin: Thinning, result: Localization, notes: list[str]
) -> dict[str, Any]:
    """The JSON report of a localization (the answer only when localized)."""
    frame = flight.frame
    p = result.estimate_m
    g = frame.to_global(float(p[0]), float(p[1]), float(p[2]))
    point = {"lat_deg": g.lat_deg, "lon_deg": g.lon_deg, "alt_m": g.alt_amsl_m, "enu_m": [float(v) for v in p]}

    def est(e: Any) -> Any:
        return None if e is None else {"value": e.value, "low95": e.low, "high95": e.high}

    return {
        "log": str(log_path),
        "samples": len(flight.log),
        "used": len(thin.kept),
        "spacing_m": thin.spacing_m,
        "residual_correlation_m": thin.correlation_m,
        "detected": result.detected,
        "censored": result.censored,
        "threshold_db": flight.threshold_db,
        "localized": result.localized,
        "reasons": list(result.reasons),
        "estimate": point if result.localized else None,
        "best_fit_not_an_answer": None if result.localized else point,
        "peb_m": result.peb_m if math.isfinite(result.peb_m) else None,
        "region": {
            "level": options.level,
            "threshold": result.region.threshold,
            "area_m2": result.region_area_m2,
            "radius_m": result.region_radius_m,
            "components": result.components,
        },
        "reference_power_db": est(result.reference_power) if options.reference_power_db is None else {"given": options.reference_power_db},
        "gamma": est(result.gamma) if options.gamma is None else {"given": options.gamma},
        "sigma_db": result.sigma_db,
        "loglik": result.loglik,
        "emitter_height_m": options.emitter_z_m if options.emitter_z_m is not None else "estimated",
        "pattern": options.pattern.name,
        "frame_origin": {"lat_deg": frame.origin.lat_deg, "lon_deg": frame.origin.lon_deg, "alt_m": frame.origin.alt_m},
        "notes": notes,
    }


def write_outputs(out: Path, report: dict[str, Any], result: Localization, flight: FlightLog, thin: Thinning) -> None:
    """``localization.json``, ``.kml``, ``.geojson`` and ``.png`` in ``out``."""
    from missions.study.radiomap import features, write_geojson, write_kml, write_png

    used = flight.log.subset(thin.kept)
    (out / "localization.json").write_text(json.dumps(report, indent=1) + "\n")
    feats = features(result, used, flight.frame)
    write_kml(feats, f"fimnav localize {report['log']}", out / "localization.kml")
    props = {k: report[k] for k in ("log", "localized", "reasons", "peb_m", "estimate")}
    write_geojson(feats, props, out / "localization.geojson")
    write_png(result, used, title_of(report), out / "localization.png")


def title_of(report: dict[str, Any]) -> str:
    """The PNG's title: the verdict in one or two lines."""
    if report["localized"]:
        e = report["estimate"]
        return f"localized: {e['lat_deg']:.6f}, {e['lon_deg']:.6f}; PEB {report['peb_m']:.1f} m, 95 % region {report['region']['area_m2']:.0f} m²"
    return "NOT LOCALIZED: " + "; ".join(report["reasons"])[:160]


def print_report(report: dict[str, Any], out: Path) -> None:
    """The verdict on stdout, a few lines."""
    used = report["used"]
    corr = report["residual_correlation_m"]
    if report["spacing_m"] > 0.0:
        spacing = f"one per {report['spacing_m']:.1f} m of flight" + (" (the residual's correlation distance)" if corr is not None else "")
    else:
        spacing = "every sample" + (": the residual is uncorrelated from one sample to the next" if corr is not None else "")
    print(f"{report['log']}: {report['samples']} samples, {used} used ({spacing}); {report['detected']} detected, {report['censored']} censored")
    if report["localized"]:
        e = report["estimate"]
        print(f"emitter: {e['lat_deg']:.7f}, {e['lon_deg']:.7f}, {e['alt_m']:.1f} m")
        print(
            f"95 % region: {report['region']['area_m2']:.0f} m², within {report['region']['radius_m']:.1f} m of the estimate; PEB {report['peb_m']:.2f} m"
        )
    else:
        print("emitter: NOT LOCALIZED")
        for reason in report["reasons"]:
            print(f"  - {reason}")
    parts = []
    for key, name, unit in (("reference_power_db", "P0", " dB"), ("gamma", "γ", "")):
        v = report[key]
        parts.append(
            f"{name} {v['given']:g}{unit} (given)" if "given" in v else f"{name} {v['value']:.2f}{unit} [{v['low95']:.2f}, {v['high95']:.2f}]"
        )
    print(f"channel: {', '.join(parts)}, σ {report['sigma_db']:.2f} dB")
    for note in report["notes"]:
        print(f"note: {note}")
    print(f"wrote {', '.join(str(out / name) for name in OUTPUTS)}")

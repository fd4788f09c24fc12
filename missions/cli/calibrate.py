"""``fimnav calibrate LOG --source LAT,LON,ALT``: fit the radio channel to a flight around a
known emitter and write the mission's ``channel`` section.

The log-distance model (:mod:`planner.radio.pathloss`) is fitted by maximum likelihood with the
undetected samples censored: the reference power P₀ (dB at 1 m, in the receiver's units), the
path-loss exponent γ and the shadowing σ_sh, one for line-of-sight links and one for links a
mission's buildings block, with 95 % confidence intervals. Samples are spaced by the residual's
correlation distance (``--spacing-m auto``), so the intervals are not those of thousands of
samples that say the same thing. The channel section (γ, σ_sh/γ for LOS and NLOS, P₀) goes to
``--out``: the whole mission with its channel replaced when ``--mission`` is given, else a
``channel:`` mapping; without ``--out`` it is printed.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from comms.errors import UsageError

if TYPE_CHECKING:  # pragma: no cover - types only
    from missions.format.radiolog import FlightLog
    from missions.format.schema import ChannelSpec, Mission
    from planner.radio.pathloss import ChannelFit


def register(subparsers: Any) -> None:
    """Add the ``calibrate`` subcommand."""
    from missions.cli.localize import add_log_arguments

    p = subparsers.add_parser(
        "calibrate",
        help="fit the radio channel (reference power, exponent, shadowing) to a log flown around a known emitter",
        description="Fit the log-distance channel (reference power, path-loss exponent, shadowing σ for LOS and NLOS links) "
        "with 95 %% confidence intervals to a received-power log (the CSV of fimnav localize) flown around an emitter at "
        "a known position; write the mission's channel section.",
    )
    p.add_argument("log", type=Path, metavar="LOG", help="a CSV log (or a fimnav launch results directory)")
    p.add_argument(
        "--source",
        required=True,
        metavar="LAT,LON,ALT",
        help="the emitter's position: degrees, degrees, metres (the log's altitude); a negative latitude as --source=-35.36,149.17,584",
    )
    add_log_arguments(p)
    p.add_argument("--out", type=Path, help="write the mission (with --mission) or its channel section here (default: print the section)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.set_defaults(func=run)


def parse_source(text: str) -> tuple[float, float, float]:
    """``--source LAT,LON,ALT`` → (lat deg, lon deg, alt m)."""
    parts = text.split(",")
    try:
        lat, lon, alt = (float(v) for v in parts)
    except ValueError:
        raise UsageError(f"--source: expected LAT,LON,ALT (degrees, degrees, metres), found {text!r}") from None
    if not all(math.isfinite(v) for v in (lat, lon, alt)) or not (-90.0 < lat < 90.0 and -180.0 <= lon <= 180.0):
        raise UsageError(f"--source: expected a latitude in (-90, 90), a longitude in [-180, 180] and a finite altitude, found {text!r}")
    return lat, lon, alt


@dataclass(frozen=True)
class Calibration:
    """A fitted channel and how it was fitted.

    Attributes:
        fit: the :class:`planner.radio.pathloss.ChannelFit`.
        used: samples used (spaced). spacing_m: their spacing (m).
        correlation_m: the residual's correlation distance (m) when measured (auto spacing).
        source_m: the emitter in the log's frame (3,), m.
        distance_m: the distance of every sample of the log from the emitter (n,), m.
        mean_db: the fitted model's mean power at every sample of the log (n,), dB.
    """

    fit: ChannelFit
    used: int
    spacing_m: float
    correlation_m: float | None
    source_m: np.ndarray
    distance_m: np.ndarray
    mean_db: np.ndarray


def calibrate(flight: FlightLog, source_m: np.ndarray, pattern_name: str, spacing_m: float | None) -> Calibration:
    """Fit the channel of ``flight`` around the emitter at ``source_m`` (the log's frame, m):
    on every sample first, then (auto) on samples spaced by that fit's residual correlation
    distance, or by ``spacing_m``."""
    from planner.geometry import line_of_sight
    from planner.radio.pathloss import Pattern, decorrelation_distance, fit_channel, link_terms, path_length_m, thin_by_distance

    log = flight.log
    mask = log.power_mask
    pos = log.positions_m
    terms = link_terms(source_m, pos, Pattern(pattern_name), derivatives=False)
    d = np.maximum(np.linalg.norm(pos - source_m, axis=1), 1.0)
    if flight.mission is not None:
        bmin, bmax = flight.mission.obstacle_bounds()
        los = line_of_sight(pos, source_m, bmin, bmax)
    else:
        los = np.ones(len(d), dtype=bool)
    path = path_length_m(pos)

    def fit_on(idx: np.ndarray) -> ChannelFit:
        return fit_channel(d[idx], log.power_db[idx], log.censored[idx], log.threshold_db[idx], los[idx], terms.gain[idx])

    everything = np.nonzero(mask)[0]
    try:
        first = fit_on(everything)
        mean = first.reference_power_db.value - first.gamma.value * 10.0 * np.log10(d) + terms.gain
        corr: float | None = None
        if spacing_m is None:
            det = mask & ~log.censored
            corr = decorrelation_distance(path[det], (log.power_db - mean)[det])
            spacing = corr
        else:
            spacing = spacing_m
        kept = np.intersect1d(thin_by_distance(path, spacing), everything)
        fit = fit_on(kept)
    except ValueError as exc:
        raise UsageError(f"{flight.path}: {exc}") from None
    mean = fit.reference_power_db.value - fit.gamma.value * 10.0 * np.log10(d) + terms.gain
    return Calibration(fit, len(kept), float(spacing), corr, source_m, d, mean)


def channel_section(fit: ChannelFit, base: ChannelSpec | None) -> ChannelSpec:
    """The mission's channel with the fitted γ, σ_sh/γ (LOS, and NLOS when some link was NLOS)
    and reference power; the rest from ``base`` (the mission's) or the defaults."""
    from pydantic import ValidationError

    from missions.format.schema import ChannelSpec

    data = (base or ChannelSpec()).model_dump()
    data.update(
        path_loss_exponent=round(fit.gamma.value, 4),
        sigma_ratio_los=round(fit.sigma_ratio_los, 4),
        reference_power_db=round(fit.reference_power_db.value, 3),
    )
    if fit.sigma_ratio_nlos is not None:
        data["sigma_ratio_nlos"] = round(fit.sigma_ratio_nlos, 4)
    try:
        return ChannelSpec.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        raise UsageError(
            f"calibrate: the fitted channel is not a valid mission channel: {'.'.join(map(str, first['loc']))}: {first['msg']}"
        ) from None


def section_yaml(channel: ChannelSpec, fit: ChannelFit, log_path: Path) -> str:
    """A ``channel:`` mapping with the fit's intervals as comments."""
    import yaml

    body = yaml.safe_dump({"channel": channel.model_dump(mode="json")}, sort_keys=False, allow_unicode=True)
    return f"# fitted by fimnav calibrate {log_path}\n{interval_comments(fit)}{body}"


def interval_comments(fit: ChannelFit) -> str:
    """The fit's 95 % intervals as YAML comment lines."""
    lines = [
        f"# reference power P0 {fit.reference_power_db.value:.2f} dB, 95 % [{fit.reference_power_db.low:.2f}, {fit.reference_power_db.high:.2f}]",
        f"# path-loss exponent {fit.gamma.value:.3f}, 95 % [{fit.gamma.low:.3f}, {fit.gamma.high:.3f}]",
        f"# shadowing LOS {fit.sigma_los_db.value:.2f} dB, 95 % [{fit.sigma_los_db.low:.2f}, {fit.sigma_los_db.high:.2f}]",
    ]
    if fit.sigma_nlos_db is not None:
        lines.append(f"# shadowing NLOS {fit.sigma_nlos_db.value:.2f} dB, 95 % [{fit.sigma_nlos_db.low:.2f}, {fit.sigma_nlos_db.high:.2f}]")
    lines.append(f"# {fit.detected} detected and {fit.censored} censored samples ({fit.nlos} NLOS)")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    """Fit, print, write."""
    from missions.cli.localize import parse_spacing, read_log
    from missions.format.loader import mission_to_yaml

    lat, lon, alt = parse_source(args.source)
    spacing = parse_spacing(args.spacing_m)
    if args.out is not None and args.out.exists() and not args.overwrite:
        raise UsageError(f"{args.out}: exists (--overwrite to replace it)")
    flight = read_log(args)
    source_m = np.array(flight.frame.to_enu(lat, lon, alt))
    cal = calibrate(flight, source_m, args.pattern, spacing)
    fit = cal.fit
    how = f"one per {cal.spacing_m:.1f} m of flight" + (" (the residual's correlation distance)" if cal.correlation_m is not None else "")
    print(f"{args.log}: {len(flight.log)} samples, {cal.used} used ({how}); {fit.detected} detected, {fit.censored} censored, {fit.nlos} NLOS")
    print(interval_comments(fit).replace("# ", "").rstrip())
    ratio = f"σ_sh/γ LOS {fit.sigma_ratio_los:.2f}" + (f", NLOS {fit.sigma_ratio_nlos:.2f}" if fit.sigma_ratio_nlos is not None else "")
    print(f"{ratio} (the paper: 1.7 and 3.2); residual RMS {fit.residual_rms_db:.2f} dB")
    for note in flight.notes:
        print(f"note: {note}")
    mission: Mission | None = flight.mission
    channel = channel_section(fit, mission.channel if mission is not None else None)
    if args.out is None:
        print(section_yaml(channel, fit, args.log), end="")
        return 0
    if mission is not None:
        text = interval_comments(fit) + mission_to_yaml(mission.model_copy(update={"channel": channel}))
    else:
        text = section_yaml(channel, fit, args.log)
    try:
        args.out.write_text(text)
    except OSError as exc:
        raise UsageError(f"{args.out}: cannot write the channel: {exc.strerror or exc}") from None
    print(f"wrote {args.out}")
    return 0

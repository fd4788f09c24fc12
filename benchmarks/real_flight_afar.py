"""fimnav calibrate and fimnav localize on a real flight: the AERPAW "Find A Rover" run of
2023-12-13 12:33 (Lake Wheeler Field, one copter at 40 m, a ground rover sending a
channel-sounder probe). Not a test: the data are not in the repository.

    git clone https://github.com/SunLab-UGA/AERPAW_AFAR /some/where/AERPAW_AFAR
    python benchmarks/real_flight_afar.py --repo /some/where/AERPAW_AFAR [--out DIR]

The repository states no licence: its data are read from the user's clone and never copied
into fimnav; the converted log goes to ``--out`` (default: a new temporary directory).

What it does:

1. **Power**: ``aerpaw_final_analysis/parse_and_filter/logs/<run>_power_log.txt`` (30 Hz, each
   line ``[date time] counter value``), joined by counter with ``<run>_quality_log.txt``; the
   times are the power log's own.
2. **Positions**: the copter's positions (about 4 Hz) from
   ``aerpaw_final_analysis/aerpaw_vis/pickles/<pickle>/data.pickle``, a pickle from outside:
   read with :class:`RestrictedUnpickler`, which admits plain containers and numbers, the
   ``datetime.datetime`` of its time stamps and float numpy scalars rebuilt from their bytes
   (nothing else: any other global, e.g. a function or a class to instantiate, is refused).
   Each record's position is taken at its ``gps_timestamp`` (when the record was written);
   its ``radio_timestamp`` lags the power log's own time by up to 12 s and is not used.
3. **Alignment**: the position at each power sample's own time, linearly interpolated between
   the position updates; samples outside the position track or below ``--min-alt-m`` (on the
   ground) are dropped. Written as the CSV of ``fimnav localize`` (time, latitude, longitude,
   altitude, power, quality).
4. ``fimnav calibrate`` at the rover's listed position (the ``readme.txt`` next to the pickle,
   also the first line of ``aerpaw_final_analysis/final_positions.txt``) and
   ``fimnav localize`` with the power unknown, the exponent free, the receiver's lock from
   ``--min-quality`` and the censoring threshold ``--threshold-db``; then variants (a dipole's
   zenith null, other thresholds, no censoring).
5. Printed: the fitted channel against the paper's, the censoring and the power straight above
   the rover against the model (the zenith null), the residual's size and correlation
   distance, each localization with its region and PEB and its distance to the listed rover
   position and to the team's own estimate (the "10 MIN REPORTED POSITION" of
   ``<run>_vehicle_log.txt``). Also written: ``afar.json`` with the same figures.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import datetime as dt
import io
import json
import math
import pickle
import re
import struct
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path[:1]:
    sys.path.insert(0, str(REPO))

from comms.geodesy import MissionFrame  # noqa: E402
from missions.cli.calibrate import calibrate  # noqa: E402
from missions.cli.localize import options_from_args  # noqa: E402
from missions.cli.main import build_parser  # noqa: E402
from missions.cli.main import main as fimnav  # noqa: E402
from missions.format.radiolog import read_flight_log  # noqa: E402
from planner.radio.localize import profile_loglik  # noqa: E402
from planner.radio.pathloss import Pattern, link_terms, path_length_m, thin_by_distance  # noqa: E402

RUN = "2023-12-13_12_33_02"
PICKLE = "2023-12-13_12-45-02"
#: The pickle is refused beyond this size (bytes): the run's is 4 MB.
MAX_PICKLE_BYTES = 64 << 20


# ------------------------------------------------------------------------ reading the data
class _DtypeStub:
    """Stands for ``numpy.dtype(name, align, copy)`` in the pickle: records the type name only."""

    def __init__(self, name: object, align: object = False, copy: object = False) -> None:
        if name not in ("f4", "f8"):
            raise pickle.UnpicklingError(f"expected a float dtype (f4 or f8), found {name!r}")
        self.name = str(name)

    def __setstate__(self, state: object) -> None:
        # (version, byte order, ...): only little-endian (or not applicable) is accepted.
        if not (isinstance(state, tuple) and len(state) >= 2 and state[1] in ("<", "|", "=")):
            raise pickle.UnpicklingError(f"expected a little-endian dtype state, found {state!r}")


def _scalar(dtype: object, data: object) -> float:
    """``numpy.core.multiarray.scalar(dtype, bytes)`` rebuilt as a float from its bytes."""
    if not (isinstance(dtype, _DtypeStub) and isinstance(data, bytes)):
        raise pickle.UnpicklingError("expected a float scalar (dtype and bytes)")
    fmt = "<f" if dtype.name == "f4" else "<d"
    if len(data) != struct.calcsize(fmt):
        raise pickle.UnpicklingError(f"expected {struct.calcsize(fmt)} bytes of a {dtype.name} scalar, found {len(data)}")
    return float(struct.unpack(fmt, data)[0])


def _datetime(state: object, tz: object = None) -> dt.datetime:
    """``datetime.datetime`` from its 10-byte pickle state (no time zone)."""
    if not (isinstance(state, bytes) and len(state) == 10 and tz is None):
        raise pickle.UnpicklingError("expected a naive datetime's 10-byte state")
    return dt.datetime(state)  # type: ignore[call-overload]  # the C type's pickle constructor


class RestrictedUnpickler(pickle.Unpickler):
    """An unpickler for untrusted data: plain containers and numbers, naive ``datetime``s and
    float numpy scalars (rebuilt from bytes by :func:`_scalar`); every other global refused."""

    ALLOWED: ClassVar[dict[tuple[str, str], Callable[..., Any]]] = {
        ("datetime", "datetime"): _datetime,
        ("numpy.core.multiarray", "scalar"): _scalar,
        ("numpy._core.multiarray", "scalar"): _scalar,
        ("numpy", "dtype"): _DtypeStub,
    }

    def find_class(self, module: str, name: str) -> Callable[..., Any]:
        found = self.ALLOWED.get((module, name))
        if found is None:
            raise pickle.UnpicklingError(f"refused global {module}.{name} (only plain data is read)")
        return found


def load_pickle(path: Path) -> Any:
    """The pickle at ``path`` through :class:`RestrictedUnpickler`."""
    data = path.read_bytes()
    if len(data) > MAX_PICKLE_BYTES:
        raise SystemExit(f"{path}: expected at most {MAX_PICKLE_BYTES >> 20} MiB, found {len(data) >> 20} MiB")
    return RestrictedUnpickler(io.BytesIO(data)).load()


_LINE = re.compile(r"^\[(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d(?:\.\d+)?)\]\s+(\d+)\s+(\S+)\s*$")


def read_radio_log(path: Path) -> dict[str, tuple[dt.datetime, float]]:
    """counter → (the log's own time, value) of a power or quality log."""
    out: dict[str, tuple[dt.datetime, float]] = {}
    for line in path.read_text().splitlines():
        m = _LINE.match(line)
        if m:
            out[m.group(2)] = (dt.datetime.fromisoformat(m.group(1)), float(m.group(3)))
    return out


def team_estimate(vehicle_log: Path) -> tuple[float, float] | None:
    """(lat, lon) of the last "Refined reported position" of the run's vehicle log."""
    found = None
    for line in vehicle_log.read_text().splitlines():
        if "Refined reported position" in line:
            payload = json.loads(line.split("Refined reported position:", 1)[1].strip())
            found = (float(payload["lat"]), float(payload["lon"]))
    return found


def listed_rover(repo: Path, pickle_dir: Path) -> tuple[float, float]:
    """(lat, lon) of the rover of the run: the pickle directory's readme.txt (lon, lat), else
    the first line of final_positions.txt (lat, lon)."""
    readme = pickle_dir / "readme.txt"
    if readme.is_file():
        lon, lat = (float(v) for v in readme.read_text().strip().split(",")[:2])
        return lat, lon
    first = (repo / "aerpaw_final_analysis" / "final_positions.txt").read_text().splitlines()[0]
    lat, lon = (float(v) for v in first.split(",")[:2])
    return lat, lon


def convert(repo: Path, run: str, pickle_name: str, min_alt_m: float, csv_path: Path) -> dict[str, Any]:
    """Write the run as a ``fimnav localize`` CSV; return what the conversion found."""
    base = repo / "aerpaw_final_analysis"
    logs = base / "parse_and_filter" / "logs"
    power = read_radio_log(logs / f"{run}_power_log.txt")
    quality = read_radio_log(logs / f"{run}_quality_log.txt")
    records = load_pickle(base / "aerpaw_vis" / "pickles" / pickle_name / "data.pickle")
    if not (isinstance(records, list) and records and all(isinstance(r, dict) for r in records)):
        raise SystemExit("data.pickle: expected a list of records (dicts)")
    # The position track: each record's position at its gps_timestamp, where it changes.
    t0 = min(t for t, _ in power.values())
    gps_t = np.array([(r["gps_timestamp"] - t0).total_seconds() for r in records])
    pos = np.array([[float(v) for v in r["position"]] for r in records])
    changed = np.concatenate([[True], np.any(np.diff(pos, axis=0) != 0.0, axis=1)])
    track_t, track = gps_t[changed], pos[changed]
    lag = np.array([(r["radio_timestamp"] - r["gps_timestamp"]).total_seconds() for r in records])
    keys = sorted((k for k in power if k in quality), key=lambda k: power[k][0])
    t = np.array([(power[k][0] - t0).total_seconds() for k in keys])
    pw = np.array([power[k][1] for k in keys])
    q = np.array([quality[k][1] for k in keys])
    inside = (t >= track_t[0]) & (t <= track_t[-1])
    lat = np.interp(t, track_t, track[:, 0])
    lon = np.interp(t, track_t, track[:, 1])
    alt = np.interp(t, track_t, track[:, 2])
    keep = inside & (alt >= min_alt_m)
    with csv_path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["time_s", "lat_deg", "lon_deg", "alt_m", "power_db", "quality"])
        for i in np.nonzero(keep)[0]:
            w.writerow([f"{t[i]:.4f}", f"{lat[i]:.8f}", f"{lon[i]:.8f}", f"{alt[i]:.3f}", f"{pw[i]:.4f}", f"{q[i]:.3f}"])
    # The pickle's radio time stamps against the power log's own, matched by value (float32).
    by_value: dict[float, list[dt.datetime]] = {}
    for k in keys:
        by_value.setdefault(struct.unpack("<f", struct.pack("<f", power[k][1]))[0], []).append(power[k][0])
    drift = [(r["radio_timestamp"] - by_value[r["Channel"]][0]).total_seconds() for r in records if len(by_value.get(r["Channel"], [])) == 1]
    return {
        "ground_alt_m": float(pos[0, 2]),
        "power_samples": len(keys),
        "records": len(records),
        "position_updates": int(changed.sum()),
        "position_rate_hz": float(changed.sum() / (track_t[-1] - track_t[0])),
        "samples_written": int(keep.sum()),
        "airborne_s": float(t[keep][-1] - t[keep][0]),
        "radio_timestamp_lag_s": {"median": float(np.median(drift)), "max": float(np.max(drift))} if drift else None,
        "gps_after_radio_record_s": float(np.median(-lag)),
    }


# ------------------------------------------------------------------------------- analysis
def run_cli(argv: list[str]) -> str:
    """``fimnav ARGV`` in this process; its standard output (the exit status must be 0)."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        code = fimnav(argv)
    if code != 0:
        raise SystemExit(f"fimnav {' '.join(argv)}: exit status {code}")
    return buf.getvalue()


def horizontal_m(frame: MissionFrame, lat_lon: tuple[float, float], other: tuple[float, float]) -> float:
    """Horizontal distance (m) between two (lat, lon)."""
    a = frame.to_enu(lat_lon[0], lat_lon[1], 0.0)
    b = frame.to_enu(other[0], other[1], 0.0)
    return math.hypot(a[0] - b[0], a[1] - b[1])


def deviance_at(argv: list[str], csv_path: Path, report: dict[str, Any], point_m: np.ndarray) -> float:
    """2(ℓ̂ − ℓ_p(point)) of a ``fimnav localize`` run (its argv and report), the emitter at
    ``point_m`` (the log's frame, m): the same samples (the report's spacing), the same options."""
    args = build_parser().parse_args(argv)
    flight = read_flight_log(csv_path, None, args.threshold_db, args.min_quality)
    options, _ = options_from_args(args, flight)
    used = flight.log.subset(thin_by_distance(path_length_m(flight.log.positions_m), report["spacing_m"]))
    point = np.array([point_m[0], point_m[1], options.emitter_z_m if options.emitter_z_m is not None else point_m[2]])
    return float(2.0 * (report["loglik"] - float(profile_loglik(used, options, point))))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repo", type=Path, required=True, help="a clone of github.com/SunLab-UGA/AERPAW_AFAR")
    ap.add_argument("--run", default=RUN, help=f"the run's log prefix (default {RUN})")
    ap.add_argument("--pickle", default=PICKLE, help=f"the run's pickle directory (default {PICKLE})")
    ap.add_argument("--out", type=Path, help="where to write the converted log and the outputs (default: a new temporary directory)")
    ap.add_argument("--min-alt-m", type=float, default=2.0, help="samples below this altitude (on the ground) are dropped (default 2)")
    ap.add_argument("--min-quality", type=float, default=70.0, help="the receiver is locked at this quality or above (default 70)")
    ap.add_argument("--threshold-db", type=float, default=5.0, help="censoring threshold, dB (default 5: where lock is lost, 100-110 m out)")
    ap.add_argument("--grid", type=int, default=48)
    args = ap.parse_args(argv)
    repo = args.repo.resolve()
    pickle_dir = repo / "aerpaw_final_analysis" / "aerpaw_vis" / "pickles" / args.pickle
    if not pickle_dir.is_dir():
        ap.error(f"{pickle_dir}: not found (is --repo a clone of SunLab-UGA/AERPAW_AFAR?)")
    out = args.out or Path(tempfile.mkdtemp(prefix="fimnav-afar-"))
    out.mkdir(parents=True, exist_ok=True)
    if REPO in out.resolve().parents or out.resolve() == REPO:
        ap.error(f"--out {out}: inside the fimnav repository; the data must stay outside it")
    csv_path = out / "afar_run.csv"
    conv = convert(repo, args.run, args.pickle, args.min_alt_m, csv_path)
    rover = listed_rover(repo, pickle_dir)
    team = team_estimate(repo / "aerpaw_final_analysis" / "parse_and_filter" / "logs" / f"{args.run}_vehicle_log.txt")
    print(
        f"converted {args.run}: {conv['samples_written']} samples over {conv['airborne_s']:.0f} s airborne, positions at {conv['position_rate_hz']:.1f} Hz"
    )
    if conv["radio_timestamp_lag_s"]:
        print(
            f"  the pickle's radio time stamps lag the power log's by {conv['radio_timestamp_lag_s']['median']:.1f} s (median), up to {conv['radio_timestamp_lag_s']['max']:.1f} s: not used"
        )
    flight = read_flight_log(csv_path, None, args.threshold_db, args.min_quality)
    frame = flight.frame
    # The rover on the ground: the copter's altitude before take-off (the first position).
    rover_alt = conv["ground_alt_m"]
    result: dict[str, Any] = {
        "conversion": conv,
        "rover_listed": rover,
        "team_estimate": team,
        "threshold_db": args.threshold_db,
        "min_quality": args.min_quality,
    }

    # --- calibrate at the listed rover position
    src = f"{rover[0]},{rover[1]},{rover_alt}"
    common = ["--min-quality", str(args.min_quality), "--threshold-db", str(args.threshold_db), "--emitter-alt", f"{rover_alt:.3f}"]
    cal_text = run_cli(["calibrate", str(csv_path), "--source", src, *common[:4], "--out", str(out / "channel.yaml"), "--overwrite"])
    print("\n$ fimnav calibrate afar_run.csv --source LISTED_ROVER " + " ".join(common[:4]))
    print(cal_text.rstrip())
    source_m = np.array(frame.to_enu(rover[0], rover[1], rover_alt))
    cal = calibrate(flight, source_m, "isotropic", None)
    cal_all = calibrate(read_flight_log(csv_path, None, None, None), source_m, "isotropic", None)
    fit = cal.fit
    result["calibration"] = {
        "censored": {
            "P0_db": fit.reference_power_db.__dict__,
            "gamma": fit.gamma.__dict__,
            "sigma_db": fit.sigma_los_db.__dict__,
            "used": cal.used,
            "spacing_m": cal.spacing_m,
        },
        "every_sample_as_measured": {
            "P0_db": cal_all.fit.reference_power_db.value,
            "gamma": cal_all.fit.gamma.value,
            "sigma_db": cal_all.fit.sigma_los_db.value,
        },
        "sigma_ratio_los": fit.sigma_ratio_los,
        "residual_correlation_m": cal.correlation_m,
    }
    print(f"every sample as a measurement (no censoring): γ {cal_all.fit.gamma.value:.2f}, σ {cal_all.fit.sigma_los_db.value:.2f} dB")
    print(
        f"the paper's channel: σ_sh/γ = 1.7 (LOS); this flight: {fit.sigma_ratio_los:.2f} with γ {fit.gamma.value:.2f} (σ_sh {fit.sigma_los_db.value:.1f} dB)"
    )

    # --- censoring and the zenith null against distance from the listed position
    log = flight.log
    h = np.hypot(*(log.positions_m[:, :2] - source_m[:2]).T)
    resid = log.power_db - cal.mean_db
    dipole = link_terms(source_m, log.positions_m, Pattern("dipole"), derivatives=False).gain
    pair = 2.0 * dipole
    rows = []
    print("\n| horizontal distance | samples | unlocked | median residual | a dipole's gain | a dipole pair's |")
    print("|---|---:|---:|---:|---:|---:|")
    for lo, hi in ((0, 10), (10, 20), (20, 30), (30, 40), (40, 60), (60, 80), (80, 100), (100, 110), (110, 130)):
        m = (h >= lo) & (h < hi)
        if not m.any():
            continue
        det = m & ~log.censored
        med = float(np.median(resid[det])) if det.any() else math.nan
        rows.append(
            {
                "from_m": lo,
                "to_m": hi,
                "samples": int(m.sum()),
                "unlocked": float(log.censored[m].mean()),
                "median_residual_db": med,
                "dipole_gain_db": float(np.median(dipole[m])),
            }
        )
        print(
            f"| {lo}-{hi} m | {int(m.sum())} | {100 * log.censored[m].mean():.0f} % | {med:.1f} dB | {np.median(dipole[m]):.1f} dB | {np.median(pair[m]):.1f} dB |"
        )
    result["by_distance"] = rows

    # --- localize: the main run and variants
    spacing_listed = f"{cal.correlation_m:.1f}" if cal.correlation_m else "0"
    known = ["--power", "known", "--reference-power-db", f"{fit.reference_power_db.value:.3f}", "--exponent", f"{fit.gamma.value:.4f}"]
    gammas = {name: calibrate(flight, source_m, name, None).fit.gamma.value for name in ("dipole", "dipole-pair")}
    result["calibration"]["gamma_by_pattern"] = {"isotropic": fit.gamma.value, **gammas}
    print(
        "γ calibrated at the listed position with the pattern: "
        + ", ".join(f"{k} {v:.2f}" for k, v in result["calibration"]["gamma_by_pattern"].items())
    )
    variants = [("unknown power, γ free, isotropic", ["--pattern", "isotropic", *common])]
    for name in ("dipole", "dipole-pair"):
        variants.append((f"unknown power, γ free, {name}", ["--pattern", name, *common]))
        variants.append(
            (
                f"unknown power, {name}, γ {gammas[name]:.2f} (calibrated at the listed position)",
                ["--pattern", name, *common, "--exponent", f"{gammas[name]:.4f}"],
            )
        )
    variants += [
        ("threshold 0 dB", ["--pattern", "isotropic", *common[:2], "--threshold-db", "0", *common[4:]]),
        ("threshold 10 dB", ["--pattern", "isotropic", *common[:2], "--threshold-db", "10", *common[4:]]),
        ("no censoring: every sample a measurement", ["--pattern", "isotropic", *common[4:]]),
        ("spacing 0: every sample, as if independent", ["--pattern", "isotropic", *common, "--spacing-m", "0"]),
        (
            f"spacing {spacing_listed} m: the correlation distance at the listed position",
            ["--pattern", "isotropic", *common, "--spacing-m", spacing_listed],
        ),
        (
            f"power and γ known: P0 {fit.reference_power_db.value:.1f} dB, γ {fit.gamma.value:.2f} (calibrated at the listed position)",
            ["--pattern", "isotropic", *common, *known],
        ),
    ]
    result["localize"] = []
    for i, (name, extra) in enumerate(variants):
        dest = out / f"localize_{i}"
        argv = ["localize", str(csv_path), "--out", str(dest), "--overwrite", "--grid", str(args.grid), *extra]
        text = run_cli(argv)
        report = json.loads((dest / "localization.json").read_text())
        point = report["estimate"] or report["best_fit_not_an_answer"]
        ll = (point["lat_deg"], point["lon_deg"])
        row = {
            "variant": name,
            "args": extra,
            "localized": report["localized"],
            "reasons": report["reasons"],
            "point": ll,
            "to_listed_m": horizontal_m(frame, ll, rover),
            "to_team_m": horizontal_m(frame, ll, team) if team else None,
            "peb_m": report["peb_m"],
            "region_area_m2": report["region"]["area_m2"],
            "region_radius_m": report["region"]["radius_m"],
            "gamma": report["gamma"],
            "sigma_db": report["sigma_db"],
            "threshold": report["region"]["threshold"],
            "used": report["used"],
            "spacing_m": report["spacing_m"],
        }
        row["deviance_listed"] = deviance_at(argv, csv_path, report, np.array(frame.to_enu(rover[0], rover[1], rover_alt)))
        row["listed_inside_region"] = row["deviance_listed"] <= report["region"]["threshold"]
        result["localize"].append(row)
        if i == 0:
            print("\n$ fimnav localize afar_run.csv " + " ".join(extra))
            print(text.rstrip())
    print("\n| variant | samples used | verdict | to listed | to team | PEB | 95 % region | deviance at listed | γ |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---:|")
    for row in result["localize"]:
        verdict = "localized" if row["localized"] else "not localized"
        team_d = f"{row['to_team_m']:.1f} m" if row["to_team_m"] is not None else "—"
        peb = f"{row['peb_m']:.1f} m" if row["peb_m"] is not None else "∞"
        g = row["gamma"]
        gamma = f"{g['given']:.2f} (given)" if "given" in g else f"{g['value']:.2f} [{g['low95']:.2f}, {g['high95']:.2f}]"
        region = f"{row['region_area_m2']:.0f} m² (r {row['region_radius_m']:.0f} m)"
        print(
            f"| {row['variant']} | {row['used']} | {verdict} | {row['to_listed_m']:.1f} m | {team_d} | {peb} | {region} | {row['deviance_listed']:.1f} | {gamma} |"
        )
    inside = sum(bool(r["listed_inside_region"]) for r in result["localize"])
    print(
        f"(the region is deviance <= {result['localize'][0]['threshold']:.2f}; the listed position is inside it in {inside} of {len(result['localize'])} variants)"
    )
    if team:
        print(f"\nthe team's own estimate is {horizontal_m(frame, team, rover):.1f} m from the listed rover position")
        result["team_to_listed_m"] = horizontal_m(frame, team, rover)
    (out / "afar.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
    print(f"wrote {out / 'afar.json'} (and the converted log {csv_path}: keep it out of any repository)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

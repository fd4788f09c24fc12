"""Reading a received-power log for ``fimnav calibrate`` and ``fimnav localize``.

Two kinds of log:

* **A CSV file** with a header row. Columns (names case-insensitive; the first name is the
  canonical one, the others are accepted):

  =================  ========================================  ===================================
  column             names                                     value
  =================  ========================================  ===================================
  time (required)    ``time_s``, ``time``, ``t``, ``timestamp``  seconds, or an ISO 8601 date-time
  latitude (req.)    ``lat_deg``, ``lat``, ``latitude``          degrees WGS-84
  longitude (req.)   ``lon_deg``, ``lon``, ``longitude``, ``lng``  degrees WGS-84
  altitude (req.)    ``alt_m``, ``alt``, ``altitude``            metres (any datum: the emitter's
                                                               height is given in the same one)
  power (required)   ``power_db``, ``power``, ``rss_db``,        received power, dB (any reference);
                     ``rssi_db``, ``rss``, ``rssi``               empty or ``nan``: not detected
  bearing            ``bearing_deg``, ``bearing``                compass bearing from the receiver
                                                               to the emitter, degrees clockwise
                                                               from north; empty: none
  lock               ``locked``, ``lock``                        1/0, true/false, yes/no,
                                                               locked/unlocked
  quality            ``quality``                                 a number; with ``--min-quality Q``
                                                               a sample below Q is unlocked
  =================  ========================================  ===================================

  Other columns are ignored (and named in a note). Rows in time order.

* **A results directory of** ``fimnav launch``: its planners' step logs (``logs/planner_*.jsonl``)
  and its ``mission.yaml``. Each ranging record d̂ becomes the power −10γ log₁₀ d̂ dB (the
  mission's γ: the log-distance model the paper's ranges come from, reference power 0 dB at
  1 m), each bearing in line of sight a bearing.

**Censoring.** A sample the receiver did not detect (unlocked, below ``--min-quality``, or no
power value) is *censored*: all it says is that the power was below the detection threshold.
The threshold is ``--threshold-db`` when given (and then every sample below it is censored
too), otherwise the lowest power among the detected samples (the maximum-likelihood estimate of
a sharp lock threshold).

A malformed log raises :class:`comms.errors.UsageError` with one line naming the file, the line
and the column.
"""

from __future__ import annotations

import csv
import datetime as dt
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from comms.errors import UsageError
from planner.radio.localize import RadioLog

if TYPE_CHECKING:  # pragma: no cover - types only
    from comms.geodesy import MissionFrame
    from missions.format.schema import Mission

FloatArray = NDArray[np.float64]

#: Column → accepted header names (lower case), canonical first.
COLUMNS: dict[str, tuple[str, ...]] = {
    "time": ("time_s", "time", "t", "timestamp"),
    "lat": ("lat_deg", "lat", "latitude"),
    "lon": ("lon_deg", "lon", "longitude", "lng"),
    "alt": ("alt_m", "alt", "altitude"),
    "power": ("power_db", "power", "rss_db", "rssi_db", "rss", "rssi"),
    "bearing": ("bearing_deg", "bearing"),
    "lock": ("locked", "lock"),
    "quality": ("quality",),
}
REQUIRED: tuple[str, ...] = ("time", "lat", "lon", "alt", "power")
#: Largest CSV read (bytes): a day of samples at 100 Hz is well below.
MAX_LOG_BYTES: int = 1 << 30
_TRUE = {"1", "true", "yes", "locked", "y", "t"}
_FALSE = {"0", "false", "no", "unlocked", "n", "f"}


@dataclass(frozen=True)
class FlightLog:
    """A log read into the local frame.

    Attributes:
        path: the file or directory read.
        log: the samples (:class:`planner.radio.localize.RadioLog`, local ENU m).
        frame: the frame of ``log`` (a mission's, or one about the first sample).
        lonlatalt: the samples' (longitude, latitude, altitude) (n, 3), for maps.
        threshold_db: the detection threshold applied (dB), None when no sample is censored.
        threshold_given: the threshold came from the user (else from the detected samples).
        unlocked: samples flagged unlocked (by the lock or quality column, or with no power).
        mission: the mission of a results directory, else None.
        notes: what the reader decided, one line each (ignored columns, the threshold).
    """

    path: Path
    log: RadioLog
    frame: MissionFrame
    lonlatalt: FloatArray
    threshold_db: float | None
    threshold_given: bool
    unlocked: int
    mission: Mission | None = None
    notes: tuple[str, ...] = field(default=())


def _header_map(path: Path, header: Sequence[str]) -> dict[str, int]:
    """Column → index from the header row; UsageError for a missing or repeated column."""
    names = [h.strip().lower() for h in header]
    found: dict[str, int] = {}
    for key, aliases in COLUMNS.items():
        hits = [i for i, n in enumerate(names) if n in aliases]
        if len(hits) > 1:
            raise UsageError(f"{path}: line 1: expected one {key} column, found {len(hits)} ({', '.join(header[i].strip() for i in hits)})")
        if hits:
            found[key] = hits[0]
    missing = [k for k in REQUIRED if k not in found]
    if missing:
        want = "; ".join(f"{k}: one of {', '.join(COLUMNS[k])}" for k in missing)
        raise UsageError(f"{path}: line 1: expected a header naming the columns ({want}), found {', '.join(h.strip() for h in header) or 'nothing'}")
    return found


def _number(path: Path, line: int, column: str, text: str, allow_empty: bool = False) -> float:
    t = text.strip()
    if allow_empty and t.lower() in ("", "nan", "na", "none", "null"):
        return math.nan
    try:
        v = float(t)
    except ValueError:
        raise UsageError(f"{path}: line {line}: {column}: expected a number, found {t!r}") from None
    if not math.isfinite(v):
        raise UsageError(f"{path}: line {line}: {column}: expected a finite number, found {t!r}")
    return v


def _time(path: Path, line: int, text: str) -> float:
    """Seconds: a number, or an ISO 8601 date-time (POSIX seconds)."""
    t = text.strip()
    try:
        v = float(t)
    except ValueError:
        try:
            stamp = dt.datetime.fromisoformat(t.replace("Z", "+00:00"))
        except ValueError:
            raise UsageError(f"{path}: line {line}: time: expected seconds or an ISO 8601 date-time, found {t!r}") from None
        if stamp.tzinfo is None:
            stamp = stamp.replace(tzinfo=dt.timezone.utc)
        return stamp.timestamp()
    if not math.isfinite(v):
        raise UsageError(f"{path}: line {line}: time: expected a finite number, found {t!r}")
    return v


def _flag(path: Path, line: int, text: str) -> bool:
    t = text.strip().lower()
    if t in _TRUE:
        return True
    if t in _FALSE:
        return False
    raise UsageError(f"{path}: line {line}: locked: expected 1/0, true/false, yes/no or locked/unlocked, found {text.strip()!r}")


@dataclass
class _Rows:
    """Columns as read, before censoring."""

    time: list[float] = field(default_factory=list)
    lat: list[float] = field(default_factory=list)
    lon: list[float] = field(default_factory=list)
    alt: list[float] = field(default_factory=list)
    power: list[float] = field(default_factory=list)
    bearing: list[float] = field(default_factory=list)
    locked: list[bool] = field(default_factory=list)


def read_csv_rows(path: Path, min_quality: float | None) -> tuple[_Rows, list[str]]:
    """The rows of a CSV log (see the module doc) and the reader's notes."""
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise UsageError(f"{path}: cannot read the log: {exc.strerror or exc}") from None
    if size > MAX_LOG_BYTES:
        raise UsageError(f"{path}: expected a log of at most {MAX_LOG_BYTES >> 20} MiB, found {size >> 20} MiB")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise UsageError(f"{path}: expected UTF-8 text (a CSV log), found the byte 0x{exc.object[exc.start]:02x} at offset {exc.start}") from None
    except OSError as exc:
        raise UsageError(f"{path}: cannot read the log: {exc.strerror or exc}") from None
    if "\x00" in text:
        raise UsageError(f"{path}: expected a CSV text log, found a NUL byte (a binary file?)")
    lines = text.splitlines()
    reader = csv.reader(lines)
    try:
        header = next(reader)
    except StopIteration:
        raise UsageError(f"{path}: expected a header row and samples, found an empty file") from None
    cols = _header_map(path, header)
    notes: list[str] = []
    known = set(cols.values())
    ignored = [h.strip() for i, h in enumerate(header) if i not in known and h.strip()]
    if ignored:
        notes.append(f"ignored columns: {', '.join(ignored)}")
    if "quality" in cols and min_quality is None:
        notes.append("quality column present but no --min-quality: every sample with a power counts as locked")
    if min_quality is not None and "quality" not in cols:
        raise UsageError(f"{path}: --min-quality given, but the log has no quality column (expected a header named quality)")
    rows = _Rows()
    width = len(header)
    for line_no, fields in enumerate(reader, start=2):
        if not fields or all(not f.strip() for f in fields):
            continue
        if len(fields) != width:
            raise UsageError(f"{path}: line {line_no}: expected {width} fields like the header, found {len(fields)}")
        rows.time.append(_time(path, line_no, fields[cols["time"]]))
        lat = _number(path, line_no, "latitude", fields[cols["lat"]])
        lon = _number(path, line_no, "longitude", fields[cols["lon"]])
        if not -90.0 < lat < 90.0:
            raise UsageError(f"{path}: line {line_no}: latitude: expected degrees in (-90, 90), found {lat:g}")
        if not -180.0 <= lon <= 180.0:
            raise UsageError(f"{path}: line {line_no}: longitude: expected degrees in [-180, 180], found {lon:g}")
        rows.lat.append(lat)
        rows.lon.append(lon)
        rows.alt.append(_number(path, line_no, "altitude", fields[cols["alt"]]))
        power = _number(path, line_no, "power", fields[cols["power"]], allow_empty=True)
        rows.power.append(power)
        rows.bearing.append(_number(path, line_no, "bearing", fields[cols["bearing"]], allow_empty=True) if "bearing" in cols else math.nan)
        locked = math.isfinite(power)
        if "lock" in cols:
            locked = locked and _flag(path, line_no, fields[cols["lock"]])
        if min_quality is not None:
            locked = locked and _number(path, line_no, "quality", fields[cols["quality"]]) >= min_quality
        rows.locked.append(locked)
    if not rows.time:
        raise UsageError(f"{path}: expected samples after the header, found none")
    t = np.asarray(rows.time)
    back = np.nonzero(np.diff(t) < 0.0)[0]
    if len(back):
        raise UsageError(f"{path}: line {int(back[0]) + 3}: time: expected samples in time order, found {t[back[0] + 1]:g} after {t[back[0]]:g}")
    return rows, notes


def censoring(
    power: FloatArray, locked: NDArray[np.bool_], threshold_db: float | None
) -> tuple[NDArray[np.bool_], FloatArray, float | None, str | None]:
    """(censored, threshold per sample, the threshold, a note) of samples with ``power`` (dB,
    NaN where none) and lock flags: the rules of the module doc."""
    if threshold_db is not None:
        censored = ~locked | ~(power >= threshold_db)
        return censored, np.full(power.shape, threshold_db), threshold_db, None
    if locked.all():
        return np.zeros(power.shape, dtype=bool), np.full(power.shape, np.nan), None, None
    if not locked.any():
        return ~locked, np.full(power.shape, np.nan), None, None
    thr = float(power[locked].min())
    note = f"{int((~locked).sum())} samples unlocked or without power: censored below {thr:.2f} dB (the lowest detected power; --threshold-db to set)"
    return ~locked, np.full(power.shape, thr), thr, note


def read_flight_log(
    path: Path,
    mission: Mission | None = None,
    threshold_db: float | None = None,
    min_quality: float | None = None,
) -> FlightLog:
    """Read a CSV log or a launch's results directory into the local frame.

    Args:
        path: the CSV file or the results directory.
        mission: the mission whose frame (origin) to use; a results directory brings its own
            (``mission.yaml``) when none is given. Without either, the frame is about the first
            sample's latitude and longitude, with z the log's altitude.
        threshold_db, min_quality: the censoring rules (module doc).

    Raises:
        UsageError: a missing or malformed log, one line.
    """
    from comms.geodesy import MissionFrame

    if path.is_dir():
        return _read_results_dir(path, mission)
    if not path.exists():
        raise UsageError(f"{path}: no such log (expected a CSV file or a fimnav launch results directory)")
    rows, notes = read_csv_rows(path, min_quality)
    lat, lon, alt = np.asarray(rows.lat), np.asarray(rows.lon), np.asarray(rows.alt)
    frame = MissionFrame.of_mission(mission) if mission is not None else MissionFrame(float(lat[0]), float(lon[0]), 0.0)
    enu = frame.to_enu_many(np.column_stack([lat, lon, alt]))
    power = np.asarray(rows.power)
    locked = np.asarray(rows.locked, dtype=bool)
    censored, thr, used, note = censoring(power, locked, threshold_db)
    if note:
        notes.append(note)
    if censored.any() and used is None:
        raise UsageError(f"{path}: expected at least one detected sample (locked, with a power), found none among {len(power)}")
    bearing = np.asarray(rows.bearing)
    # Compass bearing (clockwise from north) → ENU azimuth (from east towards north).
    azimuth = np.where(np.isfinite(bearing), np.deg2rad(90.0 - bearing), np.nan)
    log = RadioLog(
        positions_m=enu,
        power_db=np.where(censored, np.nan, power),
        censored=censored,
        threshold_db=thr,
        azimuth_rad=azimuth if np.isfinite(azimuth).any() else None,
        time_s=np.asarray(rows.time) - rows.time[0],
    )
    return FlightLog(
        path=path,
        log=log,
        frame=frame,
        lonlatalt=np.column_stack([lon, lat, alt]),
        threshold_db=used,
        threshold_given=threshold_db is not None,
        unlocked=int((~locked).sum()),
        mission=mission,
        notes=tuple(notes),
    )


def _read_results_dir(path: Path, mission: Mission | None) -> FlightLog:
    """A ``fimnav launch`` results directory: its planners' step logs as a power log."""
    from comms.geodesy import MissionFrame
    from missions.format.loader import load_mission

    logs = sorted((path / "logs").glob("planner_*.jsonl"))
    if not logs:
        raise UsageError(f"{path}: expected a CSV log or a fimnav launch results directory (logs/planner_*.jsonl), found neither")
    if mission is None:
        if not (path / "mission.yaml").is_file():
            raise UsageError(f"{path}: expected the launch's mission.yaml next to its logs/, found none (or pass --mission)")
        mission = load_mission(path / "mission.yaml")
    gamma = mission.channel.path_loss_exponent
    t, pos, power, az = [], [], [], []
    skipped = 0
    for file in logs:
        lines = file.read_text(encoding="utf-8", errors="replace").splitlines()
        for n, line in enumerate(lines, start=1):
            try:
                row = json.loads(line)
                p = [float(v) for v in row["position_m"]]
                m = row["measurement"]
                step_t = float(row["t_s"])
                rng, azimuth, los = m.get("range_m"), m.get("azimuth_rad"), bool(m.get("los"))
                rng = None if rng is None else float(rng)
                azimuth = None if azimuth is None else float(azimuth)
            except (ValueError, KeyError, TypeError, AttributeError):
                if n == len(lines):
                    continue  # a torn last line: the planner was stopped while writing it
                raise UsageError(f"{file}: line {n}: expected a step-log row (JSON with t_s, position_m, measurement), found {line[:60]!r}") from None
            if len(p) != 3 or not all(math.isfinite(v) for v in p):
                raise UsageError(f"{file}: line {n}: position_m: expected 3 finite numbers, found {row['position_m']!r}")
            if rng is not None and not rng > 0.0:
                skipped += 1
                rng = None
            bearing_ok = azimuth is not None and los
            if rng is None and not bearing_ok:
                continue
            t.append(step_t)
            pos.append(p)
            power.append(-10.0 * gamma * math.log10(rng) if rng is not None else math.nan)
            az.append(azimuth if bearing_ok else math.nan)
    if not t:
        raise UsageError(f"{path}: expected ranging or bearing records in logs/planner_*.jsonl, found none")
    order = np.argsort(np.asarray(t), kind="stable")
    positions = np.asarray(pos, dtype=float)[order]
    pw = np.asarray(power)[order]
    azimuth_all = np.asarray(az)[order]
    frame = MissionFrame.of_mission(mission)
    g = frame.to_global_many(positions)
    notes = [f"{len(logs)} planner step logs; ranges as power −10·{gamma:g}·log10(d̂) dB (reference power 0 dB at 1 m)"]
    if skipped:
        notes.append(f"{skipped} ranges not positive: not used")
    log = RadioLog(
        positions_m=positions,
        power_db=pw,
        censored=np.zeros(len(pw), dtype=bool),  # every range is a measurement
        threshold_db=np.full(len(pw), np.nan),
        azimuth_rad=azimuth_all if np.isfinite(azimuth_all).any() else None,
        time_s=np.asarray(t, dtype=float)[order],
    )
    return FlightLog(
        path=path,
        log=log,
        frame=frame,
        lonlatalt=np.column_stack([g[:, 1], g[:, 0], g[:, 2]]),
        threshold_db=None,
        threshold_given=False,
        unlocked=0,
        mission=mission,
        notes=tuple(notes),
    )

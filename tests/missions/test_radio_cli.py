"""``fimnav localize`` and ``fimnav calibrate`` in process: a synthetic CSV log with known truth
end to end (outputs, verdict, the channel section written back into a mission), a launch's
results directory (step logs written by the planner node's own writer), a flight that never
comes near the emitter, and malformed logs and arguments (one line, exit 2)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from comms.geodesy import MissionFrame
from comms.messages import Record
from missions.cli.main import main
from missions.format.loader import load_mission, mission_to_yaml
from planner.node.steplog import StepLog

ORIGIN = (35.7273, -78.6962)
SOURCE_ENU = np.array([40.0, -70.0, 1.5])
FRAME = MissionFrame(ORIGIN[0], ORIGIN[1], 0.0)


def survey(half: float = 150.0, legs: int = 7, per: int = 60, alt: float = 40.0, takeoff: bool = True) -> np.ndarray:
    rows = [np.column_stack([np.zeros(10), np.zeros(10), np.linspace(0.0, alt, 10)])] if takeoff else []
    for i, y in enumerate(np.linspace(-half, half, legs)):
        x = np.linspace(-half, half, per)
        rows.append(np.column_stack([x if i % 2 == 0 else x[::-1], np.full(per, y), np.full(per, alt)]))
    return np.concatenate(rows)


def write_log(path: Path, pos: np.ndarray, seed: int = 5, lock_threshold: float = -55.0, quality: bool = False) -> None:
    """A CSV log of the log-distance model (P0 20 dB, γ 3.5, σ 6 dB) around SOURCE_ENU; samples
    below ``lock_threshold`` unlocked with no power."""
    rng = np.random.default_rng(seed)
    d = np.linalg.norm(pos - SOURCE_ENU, axis=1)
    y = 20.0 - 35.0 * np.log10(d) + 6.0 * rng.standard_normal(len(d))
    lock = y > lock_threshold
    g = FRAME.to_global_many(pos)
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["time_s", "lat_deg", "lon_deg", "alt_m", "power_db", "locked"] + (["quality"] if quality else []) + ["notes"])
        for i in range(len(d)):
            row = [f"{0.5 * i:.2f}", f"{g[i, 0]:.8f}", f"{g[i, 1]:.8f}", f"{g[i, 2]:.2f}", f"{y[i]:.2f}" if lock[i] else "", int(lock[i])]
            w.writerow(row + ([f"{72.0 if lock[i] else 40.0:.1f}"] if quality else []) + ["x"])


def source_latlon() -> tuple[float, float]:
    g = FRAME.to_global(*SOURCE_ENU)
    return g.lat_deg, g.lon_deg


def horizontal_error_m(report: dict) -> float:
    e = report["estimate"]
    x, y, _ = FRAME.to_enu(e["lat_deg"], e["lon_deg"], 0.0)
    return math.hypot(x - SOURCE_ENU[0], y - SOURCE_ENU[1])


def test_localize_a_csv_log_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "flight.csv"
    write_log(log, survey())
    out = tmp_path / "loc"
    assert main(["localize", str(log), "--out", str(out), "--grid", "32"]) == 0
    text = capsys.readouterr().out
    assert "emitter: 35." in text and "95 % region" in text and "PEB" in text
    assert "ignored columns: notes" in text  # an unknown column is named, not an error
    report = json.loads((out / "localization.json").read_text())
    assert report["localized"] is True and report["reasons"] == []
    assert report["censored"] > 50 and report["detected"] > 100
    assert horizontal_error_m(report) < 3.0 * report["peb_m"]
    assert report["emitter_height_m"] == pytest.approx(0.0)  # the take-off point: the ground
    assert report["gamma"]["low95"] <= 3.5 <= report["gamma"]["high95"]
    kml = (out / "localization.kml").read_text()
    assert "<Polygon>" in kml.replace(" ", "") or "Polygon" in kml
    assert "emitter estimate" in kml
    gj = json.loads((out / "localization.geojson").read_text())
    kinds = [f["properties"]["kind"] for f in gj["features"]]
    assert kinds.count("estimate") == 1 and "region" in kinds and "flight" in kinds
    assert gj["properties"]["localized"] is True
    assert (out / "localization.png").stat().st_size > 10_000
    # A second run refuses to overwrite, unless asked.
    assert main(["localize", str(log), "--out", str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err


def test_a_far_flight_is_reported_not_localized_and_mapped_without_a_point(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pos = survey(half=60.0, legs=2, per=100, takeoff=False) + np.array([0.0, 900.0, 0.0])
    log = tmp_path / "far.csv"
    write_log(log, pos, lock_threshold=-200.0)
    out = tmp_path / "far"
    assert main(["localize", str(log), "--out", str(out), "--grid", "24", "--emitter-alt", "1.5"]) == 0
    text = capsys.readouterr().out
    assert "NOT LOCALIZED" in text
    report = json.loads((out / "localization.json").read_text())
    assert report["localized"] is False and report["estimate"] is None and report["reasons"]
    gj = json.loads((out / "localization.geojson").read_text())
    assert "estimate" not in [f["properties"]["kind"] for f in gj["features"]]


def test_calibrate_writes_the_channel_into_the_mission(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "cal.csv"
    write_log(log, survey(), quality=True)
    mission = load_mission("paper/ranging_los")
    mfile = tmp_path / "m.yaml"
    mfile.write_text(
        mission_to_yaml(
            mission.model_copy(update={"origin": mission.origin.model_copy(update={"lat_deg": ORIGIN[0], "lon_deg": ORIGIN[1], "alt_m": 0.0})})
        )
    )
    lat, lon = source_latlon()
    out = tmp_path / "calibrated.yaml"
    argv = ["calibrate", str(log), "--source", f"{lat},{lon},1.5", "--mission", str(mfile), "--min-quality", "60", "--out", str(out)]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "path-loss exponent" in text and "95 %" in text
    calibrated = load_mission(out)
    ch = calibrated.channel
    assert 2.9 < ch.path_loss_exponent < 4.1
    assert ch.reference_power_db is not None and abs(ch.reference_power_db - 20.0) < 12.0
    assert ch.sigma_ratio_los * ch.path_loss_exponent == pytest.approx(6.0, rel=0.2)
    assert calibrated.drones == mission.drones  # nothing else changed
    # Without --out the channel section is printed, and it is valid YAML of the format.
    assert main(["calibrate", str(log), "--source", f"{lat},{lon},1.5"]) == 0
    printed = capsys.readouterr().out
    assert "channel:\n  path_loss_exponent:" in printed
    # The calibrated mission localizes with the power known.
    out_loc = tmp_path / "known"
    assert main(["localize", str(log), "--mission", str(out), "--power", "known", "--out", str(out_loc), "--grid", "24", "--emitter-alt", "1.5"]) == 0
    report = json.loads((out_loc / "localization.json").read_text())
    assert report["reference_power_db"] == {"given": ch.reference_power_db}
    assert report["localized"]


def _launch_results(tmp: Path) -> tuple[Path, int]:
    """A results directory as ``fimnav launch`` leaves it: mission.yaml and the planners' step
    logs, written by the planner node's own StepLog (ranges of the paper's model); and how many
    of the ranges are positive (the paper's noise can draw a negative one: it is skipped)."""
    mission = load_mission("paper/ranging_los")
    res = tmp / "results"
    (res / "logs").mkdir(parents=True)
    (res / "mission.yaml").write_text(mission_to_yaml(mission))
    src = np.asarray(mission.source.position_m)
    ch = mission.channel.to_planner()
    rng = np.random.default_rng(3)
    n = mission.drones.count
    start = np.column_stack([rng.uniform(-120, 120, n), rng.uniform(60, 160, n), rng.uniform(5, 25, n)])
    vel = rng.normal(0.0, 1.0, (n, 3)) * [1.0, 1.0, 0.0]
    positive = 0
    for i in range(n):
        log = StepLog(res / "logs" / f"planner_{i}.jsonl", append=False)
        for k in range(40):
            p = start[i] + k * vel[i]
            d = float(np.linalg.norm(src - p))
            z = d + ch.sigma_r0_los * d ** (ch.gamma / 2) * rng.standard_normal()
            positive += z > 0.0
            rec = Record(i + 1, k, float(k), tuple(p), True, False, True, z, math.nan, math.nan)
            step = SimpleNamespace(next_position=p, active=np.zeros(4, bool), singular=False, filtered=False)
            result = SimpleNamespace(step=step, cost=SimpleNamespace(value=1.0), loiter=False)
            view = SimpleNamespace(saved_steps=[k] * n, hops=[1] * n)
            state = SimpleNamespace(estimate_m=src, observable=True)
            log.write_step(k, float(k), p, rec, view, state, result, 1, {"plan": 0.001})
        log.close()
    with (res / "logs" / "planner_0.jsonl").open("a") as f:
        f.write('{"step": 40, "t_s": 40.0, "posit')  # a torn last line: the planner was killed
    return res, positive


def test_localize_a_launch_results_directory(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    res, positive = _launch_results(tmp_path)
    assert positive < 400  # the case of a skipped range is exercised
    assert main(["localize", str(res), "--grid", "20", "--power", "known"]) == 0
    text = capsys.readouterr().out
    assert "planner step logs" in text and f"{400 - positive} ranges not positive: not used" in text
    report = json.loads((res / "localization" / "localization.json").read_text())
    assert report["samples"] == positive
    assert report["reference_power_db"] == {"given": 0.0}
    point = report["estimate"] or report["best_fit_not_an_answer"]
    mission = load_mission(res / "mission.yaml")
    x, y, _ = MissionFrame.of_mission(mission).to_enu(point["lat_deg"], point["lon_deg"], 0.0)
    assert math.hypot(x - mission.source.position_m[0], y - mission.source.position_m[1]) < 25.0


def _csv(tmp: Path, text: str, name: str = "bad.csv") -> Path:
    p = tmp / name
    p.write_text(text)
    return p


GOOD_HEADER = "time_s,lat_deg,lon_deg,alt_m,power_db\n"
GOOD_ROW = "0.0,35.7273,-78.6962,40.0,-50.0\n"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "found an empty file"),
        ("time_s,lat_deg,lon_deg,alt_m\n" + "0,35.7,-78.6,40\n", "expected a header naming the columns (power: one of power_db"),
        ("time,t,lat,lon,alt,power\n", "line 1: expected one time column, found 2"),
        (GOOD_HEADER, "expected samples after the header, found none"),
        (GOOD_HEADER + "0.0,35.7273,-78.6962,40.0,abc\n", "line 2: power: expected a number, found 'abc'"),
        (GOOD_HEADER + "0.0,135.7,-78.6962,40.0,-50\n", "line 2: latitude: expected degrees in (-90, 90), found 135.7"),
        (GOOD_HEADER + "0.0,35.7,-78.6962,inf,-50\n", "line 2: altitude: expected a finite number, found 'inf'"),
        (GOOD_HEADER + GOOD_ROW + "0.0,35.7273,-78.6962\n", "line 3: expected 5 fields like the header, found 3"),
        (GOOD_HEADER + "5.0,35.7273,-78.6962,40.0,-50.0\n" + GOOD_ROW, "line 3: time: expected samples in time order, found 0 after 5"),
        (GOOD_HEADER + "yesterday,35.7273,-78.6962,40.0,-50.0\n", "line 2: time: expected seconds or an ISO 8601 date-time, found 'yesterday'"),
        ("time_s,lat_deg,lon_deg,alt_m,power_db,locked\n0.0,35.7273,-78.6962,40.0,-50.0,maybe\n", "line 2: locked: expected 1/0, true/false"),
        (GOOD_HEADER + "0.0,35.7273,-78.6962,40.0,\n" * 3, "expected at least one detected sample"),
    ],
    ids=[
        "empty",
        "no-power-column",
        "two-time-columns",
        "no-rows",
        "not-a-number",
        "latitude",
        "infinite",
        "short-row",
        "time-order",
        "bad-time",
        "bad-lock",
        "nothing-detected",
    ],
)
def test_a_malformed_log_gets_one_line_and_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, message: str) -> None:
    log = _csv(tmp_path, text)
    assert main(["localize", str(log), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert err.startswith("fimnav localize: error: ") and message in err, err
    assert "Traceback" not in err
    assert not (tmp_path / "o").exists()  # nothing written


def test_binary_and_missing_logs_and_bad_arguments(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    binary = tmp_path / "b.csv"
    binary.write_bytes(b"time_s,lat\x00\xff\xfe")
    cases = [
        (["localize", str(binary)], "expected UTF-8 text"),
        (["localize", str(tmp_path / "none.csv")], "no such log"),
        (["localize", str(tmp_path)], "expected a CSV log or a fimnav launch results directory"),
        (["localize", str(_csv(tmp_path, GOOD_HEADER + GOOD_ROW, "q.csv")), "--min-quality", "50"], "no quality column"),
        (["localize", str(_csv(tmp_path, GOOD_HEADER + GOOD_ROW, "s.csv")), "--spacing-m", "soon"], "--spacing-m: expected metres"),
        (["localize", str(_csv(tmp_path, GOOD_HEADER + GOOD_ROW, "e.csv")), "--exponent", "steep"], "--exponent: expected a number or 'free'"),
        (["localize", str(_csv(tmp_path, GOOD_HEADER + GOOD_ROW, "k.csv")), "--power", "known"], "--power known: expected --reference-power-db"),
        (["calibrate", str(_csv(tmp_path, GOOD_HEADER + GOOD_ROW, "c.csv")), "--source", "35.7,-78.6"], "--source: expected LAT,LON,ALT"),
        (
            ["calibrate", str(_csv(tmp_path, GOOD_HEADER + GOOD_ROW, "d.csv")), "--source", "35.7,-78.6,1"],
            "d.csv: expected at least 3 detected samples to fit the channel, found 1",
        ),
    ]
    for argv, message in cases:
        assert main([*argv, "--out", str(tmp_path / "x")] if argv[0] == "localize" else argv) == 2, argv
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and message in err, (argv, err)


def test_a_results_directory_with_a_broken_step_log_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    res, _ = _launch_results(tmp_path)
    lines = (res / "logs" / "planner_3.jsonl").read_text().splitlines()
    lines[5] = "{not json"
    (res / "logs" / "planner_3.jsonl").write_text("\n".join(lines) + "\n")
    assert main(["localize", str(res)]) == 2
    err = capsys.readouterr().err
    assert "planner_3.jsonl: line 6: expected a step-log row" in err and err.count("\n") == 1


def test_the_pattern_choices_are_the_cores() -> None:
    from missions.cli.localize import PATTERN_NAMES
    from planner.radio.pathloss import PATTERNS

    assert PATTERN_NAMES == PATTERNS


def test_an_unwritable_output_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "flight.csv"
    write_log(log, survey(legs=3, per=30))
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["localize", str(log), "--out", str(blocker / "sub"), "--grid", "12"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is a file, not a directory" in err
    lat, lon = source_latlon()
    assert main(["calibrate", str(log), "--source", f"{lat},{lon},1.5", "--out", str(blocker / "channel.yaml")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot write the channel" in err


def test_calibrate_splits_los_and_nlos_by_the_missions_buildings(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A flight at 20 m around an emitter among paper/ranging_nlos's 30 m buildings: samples the
    buildings hide have 12 dB shadowing, the others 4 dB; calibrate fits both σ's and writes
    both ratios."""
    mission = load_mission("paper/ranging_nlos")
    frame = MissionFrame.of_mission(mission)
    src = np.array([0.0, 50.0, 1.5])
    rng = np.random.default_rng(8)
    pos = np.column_stack([rng.uniform(-120, 120, 1500), rng.uniform(-60, 180, 1500), np.full(1500, 20.0)])
    bmin, bmax = mission.obstacle_bounds()
    inside = ((pos[:, None, :] >= bmin) & (pos[:, None, :] <= bmax)).all(-1).any(-1)
    pos = pos[~inside]
    from planner.geometry import line_of_sight

    los = line_of_sight(pos, src, bmin, bmax)
    d = np.linalg.norm(pos - src, axis=1)
    y = 10.0 - 30.0 * np.log10(d) + np.where(los, 4.0, 12.0) * rng.standard_normal(len(d))
    g = frame.to_global_many(pos)
    log = tmp_path / "nlos.csv"
    with log.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["time_s", "lat_deg", "lon_deg", "alt_m", "power_db"])
        w.writerows([[i, f"{g[i, 0]:.9f}", f"{g[i, 1]:.9f}", f"{g[i, 2]:.3f}", f"{y[i]:.3f}"] for i in range(len(y))])
    s = frame.to_global(*src)
    out = tmp_path / "cal.yaml"
    argv = [
        "calibrate",
        str(log),
        f"--source={s.lat_deg},{s.lon_deg},{s.alt_amsl_m}",
        "--mission",
        "paper/ranging_nlos",
        "--spacing-m",
        "0",
        "--out",
        str(out),
    ]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert f"{int((~los).sum())} NLOS" in text
    ch = load_mission(out).channel
    assert ch.sigma_ratio_los * ch.path_loss_exponent == pytest.approx(4.0, rel=0.15)
    assert ch.sigma_ratio_nlos * ch.path_loss_exponent == pytest.approx(12.0, rel=0.15)


def test_a_bearing_column_is_a_compass_bearing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Accurate compass bearings (clockwise from north, 2°) with weak power: the bearings carry
    the estimate, which lands on the emitter only if they are read as compass bearings (an
    east-based angle would point them elsewhere), and they shrink the PEB."""
    pos = survey(half=150.0, legs=4, per=40)
    rng = np.random.default_rng(2)
    d = np.linalg.norm(pos - SOURCE_ENU, axis=1)
    y = 20.0 - 35.0 * np.log10(d) + 6.0 * rng.standard_normal(len(d))
    v = SOURCE_ENU[None, :2] - pos[:, :2]
    compass = (np.degrees(np.arctan2(v[:, 0], v[:, 1])) + 2.0 * rng.standard_normal(len(d))) % 360.0
    g = FRAME.to_global_many(pos)
    reports = {}
    for name, with_bearing in (("with", True), ("without", False)):
        log = tmp_path / f"{name}.csv"
        with log.open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["time_s", "lat_deg", "lon_deg", "alt_m", "power_db"] + (["bearing_deg"] if with_bearing else []))
            for i in range(len(d)):
                w.writerow(
                    [0.5 * i, f"{g[i, 0]:.9f}", f"{g[i, 1]:.9f}", f"{g[i, 2]:.3f}", f"{y[i]:.3f}"] + ([f"{compass[i]:.3f}"] if with_bearing else [])
                )
        out = tmp_path / name
        assert main(["localize", str(log), "--out", str(out), "--grid", "24", "--bearing-sigma-deg", "2"]) == 0
        reports[name] = json.loads((out / "localization.json").read_text())
    capsys.readouterr()
    assert reports["with"]["localized"]
    assert horizontal_error_m(reports["with"]) < 3.0
    assert reports["with"]["peb_m"] < 0.5 * reports["without"]["peb_m"]

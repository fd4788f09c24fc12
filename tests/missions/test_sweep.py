"""``fimnav sweep``: the grid of the --vary values, each cell a Monte Carlo run with the same
seeds; its rows against the in-process simulator of each cell's mission (the reference), a
real Ctrl-C in the middle of a sweep and the rerun that resumes it, and the errors of bad
--vary items."""

from __future__ import annotations

import csv
import json
import signal
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.stats import t as student_t

from missions.cli.main import main
from missions.format.loader import load_mission, parse_overrides
from missions.study.results import final_peb_interval
from missions.study.simulator import SAFETY_FAMILIES, RunSpec, simulate
from missions.study.sweep import parse_vary, plan_sweep, split_values
from tests.support.proc import Proc, fimnav, with_default_interrupt

#: a 2 x 2 sweep of the joint mission in rows (the size changes the start)
SWEEP = ["sweep", "paper/joint", "--vary", "drones.count=4,6", "--vary", "comms.d_hop_m=10,100", "--set", "drones.start.rows.spacing_m=8"]
SWEEP += ["--trials", "2", "--steps", "6", "--chunk-trials", "1", "--no-figures"]
#: columns that are wall times
TIMING = ("runtime_s",)


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


def _reference_row(count: int, d_hop: float) -> dict[str, Any]:
    """What the sweep's row of a cell must hold, from simulate() of the cell's mission."""
    sets = parse_overrides(["drones.start.rows.spacing_m=8", f"drones.count={count}", f"comms.d_hop_m={d_hop:g}"])
    result = simulate(RunSpec(load_mission("paper/joint", sets), "A", 2, 6))
    final = result.peb_m[-1]  # (M, N), every view finite here
    per_trial = final.mean(-1)
    half = student_t.ppf(0.975, 1) * per_trial.std(ddof=1) / np.sqrt(2)
    return {
        "final_peb_mean_m": final.mean(),
        "ci": (per_trial.mean() - half, per_trial.mean() + half),
        "error": np.median(result.estimate_error_m[-1]),
        "violations": result.violations(),
    }


def test_a_sweep_interrupted_by_ctrl_c_resumes_where_it_stopped(tmp_path: Path) -> None:
    """Ctrl-C after the first finished cell: exit 130, the finished cells are on disk; the same
    command again reads them (not rewritten) and runs the rest; every row is the in-process
    simulator's for that cell, the grid in order."""
    out = tmp_path / "sweep"
    argv = fimnav(*SWEEP, "--jobs", "2", "--out", str(out))
    first = Proc(with_default_interrupt(argv), cwd=tmp_path)
    try:
        first.expect(r"cell \d/4 done", 120, stream="err")
        first.send_signal(signal.SIGINT)
        assert first.wait(60) == 130, first.tail()
    finally:
        first.stop()
    assert "interrupted by SIGINT" in first.err
    kept = {p.parent.name: p.stat().st_mtime_ns for p in out.glob("cells/*/cell.json")}
    assert 1 <= len(kept) < 4, kept
    second = Proc(argv, cwd=tmp_path)
    try:
        assert second.wait(180) == 0, second.tail()
    finally:
        second.stop()
    assert f"{len(kept)} of 4 cells already in {out}, read" in second.err
    assert {p.parent.name: p.stat().st_mtime_ns for p in out.glob("cells/*/cell.json") if p.parent.name in kept} == kept
    rows = _rows(out / "sweep.csv")
    assert [(r["drones.count"], r["comms.d_hop_m"]) for r in rows] == [("4", "10"), ("4", "100"), ("6", "10"), ("6", "100")]
    for r in rows:
        ref = _reference_row(int(r["drones.count"]), float(r["comms.d_hop_m"]))
        assert float(r["final_peb_mean_m"]) == pytest.approx(ref["final_peb_mean_m"], rel=1e-12)
        assert (float(r["final_peb_ci95_low_m"]), float(r["final_peb_ci95_high_m"])) == pytest.approx(ref["ci"], rel=1e-9)
        assert float(r["final_estimate_error_median_m"]) == pytest.approx(ref["error"], rel=1e-12)
        assert {f: int(r[f"violations_{f}"]) for f in SAFETY_FAMILIES} == ref["violations"]
        assert int(r["drones"]) == int(r["drones.count"]) and r["criterion"] == "A" and float(r["runtime_s"]) > 0
    # the hop distance matters (10 m links only neighbours in a row), so the cells differ
    assert rows[0]["final_peb_mean_m"] != rows[1]["final_peb_mean_m"]


def test_the_sweep_is_the_same_in_process_and_on_workers(tmp_path: Path) -> None:
    """One process and two: the same CSV (but times), the same sweep.json cells; figures drawn
    per varied key; an uninterrupted run resumed does nothing."""
    args = [a for a in SWEEP if a != "--no-figures"]
    assert main([*args, "--out", str(tmp_path / "one")]) == 0
    assert main([*args, "--jobs", "2", "--out", str(tmp_path / "two"), "--no-figures"]) == 0
    one, two = (_rows(tmp_path / d / "sweep.csv") for d in ("one", "two"))
    assert [{k: v for k, v in r.items() if k not in TIMING} for r in one] == [{k: v for k, v in r.items() if k not in TIMING} for r in two]
    assert sorted(p.name for p in (tmp_path / "one" / "figures").iterdir()) == ["final_peb_vs_comms.d_hop_m.png", "final_peb_vs_drones.count.png"]
    doc = json.loads((tmp_path / "one" / "sweep.json").read_text())
    assert [c["values"] for c in doc["cells"]] == [
        {"drones.count": a, "comms.d_hop_m": b} for a in ("4", "6") for b in ("10", "100")
    ]
    before = {p: p.stat().st_mtime_ns for p in (tmp_path / "one").glob("cells/*/cell.json")}
    assert main([*args, "--out", str(tmp_path / "one"), "--no-figures"]) == 0
    assert {p: p.stat().st_mtime_ns for p in (tmp_path / "one").glob("cells/*/cell.json")} == before


def test_another_sweep_in_the_same_directory_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["sweep", "paper/joint", "--vary", "comms.h_max=1,2", "--trials", "2", "--steps", "2", "--no-figures", "--out", str(tmp_path / "s")]
    assert main(args) == 0
    capsys.readouterr()
    assert main([*args, "--steps", "3"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "holds another sweep" in err and "use another --out" in err


def test_the_default_directory_is_the_same_for_the_same_sweep() -> None:
    from missions.study.sweep import default_out

    a, b, c = (plan_sweep("paper/joint", parse_vary([v]), trials=2, steps=2) for v in ("comms.h_max=1,2", "comms.h_max=1,2", "comms.h_max=1,3"))
    assert default_out(a) == default_out(b) != default_out(c)
    assert default_out(a).name.startswith("sweep-paper_joint-")


@pytest.mark.parametrize(
    ("vary", "message"),
    [
        (["comms.h_max"], "--vary: expected KEY=V1,V2,... with a dotted key such as comms.h_max=1,2,3, found 'comms.h_max'"),
        (["comms..h_max=1"], "--vary: expected KEY=V1,V2,... with a dotted key"),
        (["comms.h_max=1,,2"], "--vary: comms.h_max: expected values separated by commas, found an empty value in '1,,2'"),
        (["comms.h_max=1,1"], "--vary: comms.h_max: expected different values, found '1,1'"),
        (["comms.h_max=[1"], "--vary: comms.h_max: expected a YAML value, found '[1'"),
        (["comms.h_max=1", "comms.h_max=2"], "--vary: comms.h_max: varied twice; give its values in one --vary"),
        (["drones.count=4,x"], "--vary drones.count=x: paper/joint: (override) drones.count: expected a valid integer, found 'x' (text)"),
        (["drones.cont=4,5"], "unknown key, did you mean 'count'?"),
        (["drones.count=4,60"], "--vary drones.count=60: paper/joint: line 16: drones.start: expected start positions at least d_uav_m = 1 m apart"),
        (["comms.h_max=1,0"], "--vary comms.h_max=0: paper/joint: (override) comms.h_max: expected a number greater than or equal to 1, found 0"),
    ],
)
def test_bad_vary_items_are_one_clear_error(vary: list[str], message: str, capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    args = ["sweep", "paper/joint", *(a for v in vary for a in ("--vary", v)), "--trials", "1", "--steps", "1", "--out", str(tmp_path / "s")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("fimnav sweep: error: ") and message in err and err.count("\n") == 1, err
    assert not (tmp_path / "s").exists()


def test_a_key_in_both_set_and_vary_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sweep", "paper/joint", "--vary", "comms.h_max=1,2", "--set", "comms.h_max=3"]) == 2
    assert "--vary: comms.h_max: also given with --set; give it in one of them" in capsys.readouterr().err


def test_values_split_at_the_commas_outside_brackets_and_quotes() -> None:
    assert split_values("[0,150,8],[0, 200, 8]") == ["[0,150,8]", "[0, 200, 8]"]
    assert split_values("'a,b',{x: 1, y: 2},3") == ["'a,b'", "{x: 1, y: 2}", "3"]
    (v,) = parse_vary(["drones.start.rows.center_m=[0,150,8],[0,200,8]"])
    assert v.values == ([0, 150, 8], [0, 200, 8])


def test_the_interval_is_students_over_the_trials_means() -> None:
    """Closed form on a result whose final PEB is set by hand; a trial with every view singular
    is left out, as in the mean."""
    result = simulate(RunSpec(load_mission("paper/joint"), "A", 4, 1))
    peb = np.array([[1.0, 3.0], [2.0, 4.0], [np.inf, np.inf], [5.0, 7.0]])
    fake = type(result)(**{**result.__dict__, "peb_m": peb[None]})
    means = np.array([2.0, 3.0, 6.0])
    half = student_t.ppf(0.975, 2) * means.std(ddof=1) / np.sqrt(3)
    assert final_peb_interval(fake) == pytest.approx([means.mean() - half, means.mean() + half], rel=1e-12)
    assert final_peb_interval(type(result)(**{**result.__dict__, "peb_m": peb[None, :1]})) is None

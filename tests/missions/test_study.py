"""A study as a library call (missions.study.montecarlo.run_study): a run's trials are simulated
in chunks on an executor and merged, and the results are the same, bit for bit, whatever the
executor and the number of workers; without injected faults they are those of the in-process
simulator over the whole run (the reference)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from missions.cli.main import main
from missions.format.loader import parse_overrides
from missions.study.executors import Chunk, InProcess, LocalPool, chunk_bounds, simulate_chunk
from missions.study.montecarlo import TRIAL_AXIS_FIELDS, expand_runs, merge_chunks, run_study, study_size
from missions.study.results import summarize
from missions.study.simulator import RunSpec, SimulationResult, simulate
from tests.simulator.conftest import paper_mission

LOSS = parse_overrides(["comms.faults.loss=0.2", "comms.faults.extra_delay_steps=1"])
#: summary entries that are wall times (they differ between any two runs)
TIMING = ("runtime_s", "drone_steps_per_s", "baseline_runtime_s")


def _untimed(summary: dict[str, Any]) -> dict[str, Any]:
    out = {k: v for k, v in summary.items() if k not in TIMING}
    if "faults" in out:
        out["faults"] = _untimed(out["faults"])
    return out


def _assert_same(a: SimulationResult, b: SimulationResult) -> None:
    """Every array of two results equal bit for bit (NaN where NaN), and the same counts."""
    for name in TRIAL_AXIS_FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), name
    assert a.margins_m.keys() == b.margins_m.keys()
    for name in a.margins_m:
        assert np.array_equal(a.margins_m[name], b.margins_m[name], equal_nan=True), name
    assert np.array_equal(a.active, b.active) and a.active.dtype == b.active.dtype
    assert np.array_equal(a.source_m, b.source_m)
    assert a.spec == b.spec
    assert {k: v for k, v in a.extra.items()} == {k: v for k, v in b.extra.items()}


@pytest.mark.parametrize(("trials", "least", "most", "chunks"), [(100, 50, 4, 2), (99, 50, 4, 1), (1000, 50, 4, 4), (20, 2, 4, 4), (7, 2, 4, 3), (1, 2, 4, 1), (9, 1, 1, 1)])
def test_chunk_bounds_cover_the_trials_in_order(trials: int, least: int, most: int, chunks: int) -> None:
    bounds = chunk_bounds(trials, least, most)
    assert len(bounds) == chunks
    assert [f for f, _ in bounds] == list(np.cumsum([0] + [c for _, c in bounds[:-1]]))
    assert sum(c for _, c in bounds) == trials
    sizes = [c for _, c in bounds]
    assert max(sizes) - min(sizes) <= 1 and sizes == sorted(sizes, reverse=True)
    assert chunks == 1 or min(sizes) >= least


def test_without_faults_the_chunks_merge_to_the_whole_run() -> None:
    """Reference: simulate() over all the trials at once."""
    spec = RunSpec(paper_mission("joint"), "A", 7, 12)
    whole = simulate(spec)
    study = run_study([spec], chunk_trials=2)  # 7 trials: chunks of 2, 2, 3
    assert chunk_bounds(7, 2) == [(0, 3), (3, 2), (5, 2)]
    _assert_same(study.results[0], whole)
    assert study.penalties == [None] and study.extras == [None]


def test_a_study_is_the_same_on_any_number_of_workers() -> None:
    """Runs with and without injected faults (the faults' baselines simulated too), in this
    process, on two and on three workers: every array and every summary the same bit for bit."""
    specs = [RunSpec(paper_mission("heterogeneous"), "D", 5, 10), dataclasses.replace(expand_runs(["paper/joint"], LOSS, trials=6, steps=10)[0])]
    assert specs[1].mission.comms.faults.enabled
    runs = (("in-process", InProcess()), ("2 workers", LocalPool(2)), ("3 workers", LocalPool(3)))
    done = {name: run_study(specs, executor=ex, chunk_trials=2) for name, ex in runs}
    ref = done["in-process"]
    for name, study in done.items():
        for a, b in zip(study.results, ref.results, strict=True):
            _assert_same(a, b)
        assert [p and _untimed(p) for p in study.penalties] == [p and _untimed(p) for p in ref.penalties], name
        assert [_untimed(summarize(r, p)) for r, p in zip(study.results, study.penalties)] == [
            _untimed(summarize(r, p)) for r, p in zip(ref.results, ref.penalties)
        ], name
    assert ref.penalties[0] is None and ref.penalties[1] is not None
    assert 0.0 < ref.penalties[1]["lost_fraction"] < 1.0


def test_the_merged_loss_fraction_is_made_of_the_summed_counts() -> None:
    spec = expand_runs(["paper/joint"], LOSS, trials=5, steps=8)[0]
    parts = [simulate_chunk(Chunk(dataclasses.replace(spec, first_trial=f, trials=c))) for f, c in chunk_bounds(5, 2, 2)]
    merged = merge_chunks(spec, parts)
    lost = sum(int(p.extra["fault_lost"]) for p in parts)
    decided = sum(int(p.extra["fault_decided"]) for p in parts)
    assert decided > 0 and merged.extra["fault_lost_fraction"] == lost / decided
    assert merged.spec == spec and merged.positions_m.shape[1] == 5
    assert np.array_equal(merged.active, parts[0].active + parts[1].active)


def test_merge_refuses_chunks_that_are_not_the_runs_trials() -> None:
    spec = RunSpec(paper_mission("joint"), "A", 4, 3)
    a, b = (simulate(dataclasses.replace(spec, first_trial=f, trials=2)) for f in (0, 2))
    with pytest.raises(ValueError, match="expected trial 0 next, found 2"):
        merge_chunks(spec, [b, a])
    with pytest.raises(ValueError, match="the chunks hold 2 trials, the run 4"):
        merge_chunks(spec, [a])


def test_every_field_of_a_result_has_a_merge_rule() -> None:
    """A field added to SimulationResult must be given a rule in merge_chunks (it says so)."""
    spec = RunSpec(paper_mission("joint"), "A", 2, 2)
    parts = [simulate(dataclasses.replace(spec, first_trial=f, trials=1)) for f in (0, 1)]
    merge_chunks(spec, parts)  # today's fields: all known

    @dataclasses.dataclass(frozen=True)
    class Larger(SimulationResult):
        new_field: int = 0

    import missions.study.montecarlo as mc

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(mc, "SimulationResult", Larger)
        with pytest.raises(ValueError, match="no rule to merge SimulationResult.new_field"):
            mc.merge_chunks(spec, parts)


def test_study_size_counts_the_baselines_it_will_simulate() -> None:
    specs = [RunSpec(paper_mission("joint"), "A", 3, 4), expand_runs(["paper/joint"], LOSS, trials=2, steps=5)[0]]
    assert study_size(specs) == 3 * 4 + 2 * 5 * 2
    seen: list[int] = []
    run_study(specs, progress=seen.append, chunk_trials=1)
    assert sum(seen) == study_size(specs)


def test_montecarlo_jobs_do_not_change_the_summary(tmp_path: Path) -> None:
    """``fimnav montecarlo --jobs 1`` and ``--jobs 2`` on a run of 100 trials (two chunks, and
    two of its baseline): the same summary.json (but wall times)."""
    assert len(chunk_bounds(100)) == 2
    args = ["montecarlo", "paper/joint", "--trials", "100", "--steps", "3", "--no-figures", "--set", "comms.faults.loss=0.3"]
    for jobs in (1, 2):
        assert main([*args, "--jobs", str(jobs), "--out", str(tmp_path / f"jobs{jobs}")]) == 0
    one, two = (json.loads((tmp_path / f"jobs{j}" / "summary.json").read_text())["runs"] for j in (1, 2))
    assert [_untimed(s) for s in one] == [_untimed(s) for s in two]
    assert one[0]["faults"]["lost_fraction"] > 0.0


def test_the_live_view_watches_each_runs_first_trial_in_the_worker(tmp_path: Path) -> None:
    """``fimnav montecarlo --view``'s watch (the recording only, no server here) on two workers:
    one recording per run, of its first trial, step by step the simulator's positions; the
    fault-free baseline of a run with faults is not watched."""
    import functools

    from missions.cli.montecarlo import _watch_run
    from tests.missions.test_liveview import read_entity

    specs = [RunSpec(paper_mission("heterogeneous"), "A", 3, 6), expand_runs(["paper/joint"], LOSS, trials=2, steps=4)[0]]
    study = run_study(specs, executor=LocalPool(2), chunk_trials=1, watch=functools.partial(_watch_run, None, str(tmp_path)))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["paper_heterogeneous_A.rrd", "paper_joint_A.rrd"]
    for spec, result in zip(specs, study.results):
        drones = read_entity(tmp_path / f"{spec.mission.id}_{spec.criterion}.rrd", "/world/drones", "Points3D:positions")
        assert sorted(drones) == list(range(spec.steps))
        for k in range(spec.steps):
            np.testing.assert_allclose(np.asarray(drones[k]), result.positions_m[k, 0], atol=1e-4)


def test_write_study_writes_each_run_when_it_is_done_and_the_same_files_as_write_results(tmp_path: Path) -> None:
    """write_study (fimnav montecarlo's path): a run's directory exists, with its summary, once
    the next run has started (the study keeps one run in memory), and the results directory is
    write_results' of run_study's results: the same summaries but for wall times, the same
    per-run files, the same figure names."""
    from missions.study.montecarlo import write_study
    from missions.study.results import write_results

    specs = expand_runs(["paper/joint", "paper/bearing"], {}, "A", None, 3, 8, None)
    first = tmp_path / "streamed" / "runs" / "paper_joint_A" / "summary.json"
    seen_at_second_run: list[bool] = []
    done = [0]

    def progress(n: int) -> None:
        done[0] += n
        if done[0] > specs[0].trials * specs[0].steps and not seen_at_second_run:
            seen_at_second_run.append(first.exists())

    streamed = write_study(specs, tmp_path / "streamed", progress=progress)
    assert seen_at_second_run == [True]
    study = run_study(specs)
    whole = write_results(study.results, tmp_path / "whole", penalties=study.penalties, extras=study.extras)
    assert [_untimed(s) for s in streamed] == [_untimed(s) for s in whole]
    for run in ("paper_joint_A", "paper_bearing_A"):
        a, b = tmp_path / "streamed" / "runs" / run, tmp_path / "whole" / "runs" / run
        assert sorted(p.name for p in a.iterdir()) == sorted(p.name for p in b.iterdir())
        for name in ("peb.csv", "trajectories.csv", "trajectories.kml", "trajectories.geojson", "mission.yaml"):
            assert (a / name).read_bytes() == (b / name).read_bytes(), (run, name)
    assert sorted(p.name for p in (tmp_path / "streamed" / "figures").iterdir()) == sorted(p.name for p in (tmp_path / "whole" / "figures").iterdir())
    top = json.loads((tmp_path / "streamed" / "summary.json").read_text())
    assert [r["run"] for r in top["runs"]] == ["paper_joint_A", "paper_bearing_A"]


def test_trajectories_csv_rows_are_what_csv_writer_writes_of_every_number_and_role() -> None:
    import csv
    import io

    from missions.study import results

    r = simulate(RunSpec(paper_mission("heterogeneous"), "A", 2, 12))
    pos, peb = r.positions_m.copy(), r.peb_m.copy()
    pos[3, 0, 1, 0], pos[4, 0, 2, 1], pos[5, 0, 3, 2], pos[6, 0, 0, 0] = np.nan, -np.inf, -0.0, 1e-300
    peb[2, 0, :] = np.inf
    r = dataclasses.replace(r, positions_m=pos, peb_m=peb)
    mission = r.spec.mission
    roles = ["joint", "a,b", 'say "hi"', "line\nbreak", "100%s"] + list(mission.drones.roles[5:])
    r = dataclasses.replace(r, spec=dataclasses.replace(r.spec, mission=mission.model_copy(update={"drones": mission.drones.model_copy(update={"roles": roles})})))
    # The reference: csv.writer, cell by cell, each number as results._fmt writes it.
    buf = io.StringIO()
    w = csv.writer(buf)
    K = r.estimates_m.shape[0]
    for k in range(K + 1):
        for i in range(r.positions_m.shape[2]):
            e = r.estimates_m[min(k, K - 1), 0, i]
            p = r.positions_m[k, 0, i]
            w.writerow([0, k, i + 1, roles[i], *(results._fmt(v) for v in p), *(results._fmt(v) for v in e), results._fmt(r.peb_m[min(k, K - 1), 0, i])])
    assert results._trajectory_rows(r) == buf.getvalue()

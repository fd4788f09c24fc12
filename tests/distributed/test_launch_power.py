"""End-to-end with the source's power unknown: ``fimnav launch`` (lockstep; real processes, Zenoh
and MAVLink on 127.0.0.1) flies ``source.power: unknown`` against a source 6 dB stronger than
nominal, reports the estimated offset, and computes what the in-process simulator computes (the
independent reference, float32 positions emulated)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from missions.format.loader import load_mission
from missions.study.simulator import RunSpec, simulate
from tests.support.launch import PAPER, Launch, read_trajectories

pytestmark = pytest.mark.integration


def test_lockstep_launch_with_unknown_power_reports_the_offset(tmp_path: Path, launches: list[Launch]) -> None:
    """20 steps of the paper's ranging swarm: the run completes with no violation; every planner's
    step log and the summary carry the estimated offset (dB); positions, estimates and offsets
    equal the simulator's (1 cm, 1 cm, 1e-3 dB; measured 8e-6 m and 8e-7 dB). Run with
    ``--no-figures`` (:class:`Launch`'s default): every result but the PNG figures is written."""
    out = tmp_path / "power"
    steps = 20
    run = Launch(
        PAPER / "ranging_los.yaml",
        out,
        "--steps",
        str(steps),
        "--set",
        "source.power=unknown",
        "--set",
        "source.power_offset_db=6",
        "--step-timeout",
        "60",
    )
    launches.append(run)
    code, _stdout, stderr = run.wait()
    assert code == 0, stderr[-3000:]
    assert "--no-figures" in run.process.argv
    assert not list(out.rglob("*.png"))
    run_dir = out / "runs" / "paper_ranging_los_A"
    assert (run_dir / "peb.csv").stat().st_size > 0 and (run_dir / "trajectories.csv").stat().st_size > 0
    summary = json.loads((out / "summary.json").read_text())["runs"][0]
    assert summary["violations"] == dict.fromkeys(summary["violations"], 0)
    block = summary["source_power"]
    assert block["model"] == "unknown" and block["true_offset_db"] == 6.0
    assert block["final_offset_estimated_fraction"] == 1.0 and np.isfinite(block["final_offset_mean_db"])

    mission = load_mission(out / "mission.yaml")
    n = mission.drones.count
    logged = np.full((steps, n), np.nan)
    for i in range(n):
        rows = [json.loads(line) for line in (out / "logs" / f"planner_{i + 1}.jsonl").read_text().splitlines()]
        assert len(rows) == steps
        for row in rows:
            logged[row["step"], i] = np.nan if row["power_offset_db"] is None else row["power_offset_db"]
    sim = simulate(RunSpec(mission, mission.criterion, 1, mission.steps), float32_positions=True)
    assert sim.power_offset_db is not None
    np.testing.assert_allclose(logged, sim.power_offset_db[:, 0], atol=1e-3, rtol=0)
    assert block["final_offset_mean_db"] == pytest.approx(float(np.mean(sim.power_offset_db[-1, 0])), abs=1e-3)
    pos, est = read_trajectories(out, mission)
    np.testing.assert_allclose(pos, sim.positions_m[:, 0], atol=0.01, rtol=0)
    np.testing.assert_allclose(est, sim.estimates_m[:, 0], atol=0.01, rtol=0)

"""A launch's results when a pilot flies a drone (taken over): the launcher's accounting, fed a
run made by the in-process simulator (its positions, estimates and views as the planners' step
logs and records), with drone 2 taken over for the last steps and flown by the pilot faster
than the planner's speed limit."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from comms.messages import Record
from missions.launch.launcher import Launcher
from missions.format.loader import load_mission
from missions.study.simulator import RunSpec, simulate

K, TAKEN_FROM, PILOT = 12, 8, 2  # steps, first taken-over step, the drone the pilot flies


def test_taken_over_steps_are_no_planner_commands_and_keep_the_last_estimate(tmp_path: Path) -> None:
    mission = load_mission("paper/heterogeneous", {"steps": K, "trials": 1})
    n = mission.drones.count
    sim = simulate(RunSpec(mission, "A", 1, K))
    pos, est = sim.positions_m[:, 0], sim.estimates_m[:, 0]
    launcher = Launcher(mission, tmp_path)
    (tmp_path / "logs").mkdir()
    vmax_step = mission.limits().step_max_m
    pilot = {k: pos[TAKEN_FROM, PILOT - 1] + np.array([2.5 * vmax_step * (k - TAKEN_FROM), 0.0, 0.0]) for k in range(TAKEN_FROM, K)}
    for j in range(1, n + 1):
        lines = []
        for k in range(K):
            if j == PILOT and k >= TAKEN_FROM:
                launcher.collected.records[(k, j)] = Record(j, k, k * mission.dt_s, tuple(pilot[k]), True, False, True,
                                                                 math.nan, math.nan, math.nan, taken_over=True)
                continue
            ages = sim.record_ages[k, 0, j - 1]
            lines.append(json.dumps({
                "step": k, "t_s": k * mission.dt_s, "position_m": pos[k, j - 1].tolist(), "measurement": {"los": True},
                "saved_steps": [int(k - a) if a >= 0 else -1 for a in ages], "estimate_m": est[k, j - 1].tolist(),
                "observable": True, "next_position_m": pos[k + 1, j - 1].tolist(), "active": {}, "singular": False, "filtered": False,
            }))
        (tmp_path / "logs" / f"planner_{j}.jsonl").write_text("\n".join(lines) + "\n")
    result = launcher._result(1.0)
    # The pilot's 2.5 × v_max steps are no planner command: no speed or turn-rate violation.
    assert result.violations()["speed"] == 0 and result.violations()["turn_rate"] == 0
    np.testing.assert_allclose(result.positions_m[TAKEN_FROM:K, 0, PILOT - 1], np.array([pilot[k] for k in range(TAKEN_FROM, K)]))
    # Its estimate and view stay those of its planner's last step.
    for k in range(TAKEN_FROM, K):
        np.testing.assert_allclose(result.estimates_m[k, 0, PILOT - 1], est[TAKEN_FROM - 1, PILOT - 1])
        assert result.peb_m[k, 0, PILOT - 1] == result.peb_m[TAKEN_FROM - 1, 0, PILOT - 1]
    assert np.isfinite(result.estimate_error_m[-1]).all()
    # The other drones' steps are the simulator's.
    others = [i for i in range(n) if i != PILOT - 1]
    np.testing.assert_allclose(result.estimates_m[:, 0, others], est[:, others])

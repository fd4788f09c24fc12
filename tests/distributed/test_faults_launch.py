"""End-to-end: ``fimnav launch`` with injected Zenoh loss and delay (issue 7), against the
in-process simulator with the same faults and against the brute-force memory buffer.

Real processes, real Zenoh and MAVLink on 127.0.0.1 (the Launch helper and the no-orphan check
of tests/distributed/test_launch.py).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from missions.format.loader import load_mission
from missions.format.schema import Mission
from missions.study.simulator import RunSpec, simulate
from tests.simulator.test_faults import ref_decisions, ref_saved
from tests.support.launch import PAPER, Launch, read_peb, read_trajectories

pytestmark = pytest.mark.integration

STEPS = 40
LOSS = 0.2
MAX_DELAY = 2


def _node_injects_faults(mission: Mission) -> bool:
    """Whether the planner node builds its delayed view with the mission's faults."""
    from planner.node import NodeOptions, PlannerNode

    node = PlannerNode(mission, NodeOptions(uav=1, mavlink="udpin:127.0.0.1:1"))
    return node.view.faults is not None


@pytest.mark.slow  # a lockstep launch with faults (6 s); tests/simulator/test_faults.py checks the fault rule in the default run
def test_lossy_delayed_launch_matches_the_simulator(tmp_path: Path, launches: list[Launch]) -> None:
    """The paper's heterogeneous mission, shortened, with 20 % of the peer records lost and up to
    2 steps of extra delay: it completes; every planner held exactly the records the brute-force
    buffer gives with its own decisions (so it fell back on saved records); its positions equal
    the simulator's with the same faults (float32 positions) to 1 cm; the summary reports the PEB
    penalty against the fault-free mission."""
    overrides = {"comms.faults.loss": LOSS, "comms.faults.extra_delay_steps": MAX_DELAY}
    if not _node_injects_faults(load_mission(PAPER / "heterogeneous.yaml", overrides)):
        pytest.fail("planner.node.core.build_view must build the DelayedView with "
                    "faults=mission.comms.faults.to_model(), seed=mission.seed")
    out = tmp_path / "faults"
    sets = [a for k, v in overrides.items() for a in ("--set", f"{k}={v}")]
    run = Launch(PAPER / "heterogeneous.yaml", out, "--steps", str(STEPS), "--step-timeout", "60", *sets)
    launches.append(run)
    code, stdout, stderr = run.wait()
    assert code == 0, stderr[-3000:]
    mission = load_mission(out / "mission.yaml")
    assert mission.comms.faults.loss == LOSS and mission.comms.faults.extra_delay_steps == MAX_DELAY
    n = mission.drones.count
    pos, _ = read_trajectories(out, mission)
    assert np.isfinite(pos).all()

    # Each planner's buffer against the brute-force rule, from the recorded positions.
    logs = [[json.loads(line) for line in (out / "logs" / f"planner_{i}.jsonl").open()] for i in range(1, n + 1)]
    old = 0
    for i in range(n):
        assert len(logs[i]) == STEPS
        lost, delay = ref_decisions(mission.seed, 0, i, STEPS, n, LOSS, MAX_DELAY)
        want = ref_saved(pos[:STEPS], i, mission.comms.d_hop_m, mission.comms.h_max, lost, delay)
        held = np.array([e["saved_steps"] for e in logs[i]])
        np.testing.assert_array_equal(held, want, err_msg=f"planner {i + 1}")
        old += int((np.arange(STEPS)[:, None] - held >= 1).sum())
    assert old > 0, "with loss and delay some planners must use saved (older) records"

    # The same faults in the in-process simulator: the same flight.
    sim = simulate(RunSpec(mission, mission.criterion, 1, STEPS), float32_positions=True)
    np.testing.assert_allclose(pos, sim.positions_m[:, 0], atol=0.01, rtol=0)
    sim_peb = sim.peb_stats()["mean"]
    peb = read_peb(out)
    assert abs(peb[-1] - sim_peb[-1]) <= 0.02 * sim_peb[-1]

    # The summary reports the PEB penalty against the fault-free mission.
    summary = json.loads((out / "summary.json").read_text())["runs"][0]
    faults = summary["faults"]
    assert faults["loss"] == LOSS and faults["extra_delay_steps"] == MAX_DELAY
    assert faults["final_peb_mean_m"] == pytest.approx(peb[-1], rel=1e-6)
    clean = simulate(RunSpec(load_mission(PAPER / "heterogeneous.yaml"), mission.criterion, 1, STEPS), float32_positions=True)
    assert faults["baseline_final_peb_mean_m"] == pytest.approx(float(clean.peb_stats()["mean"][-1]), rel=1e-9)
    assert faults["final_peb_penalty_m"] == pytest.approx(faults["final_peb_mean_m"] - faults["baseline_final_peb_mean_m"])
    assert faults["mean_record_age_steps"] > faults["baseline_mean_record_age_steps"] == 0.0

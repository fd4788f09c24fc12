"""With the true source, a swarm ends within 5 % of the optimal placement's PEB.

Reference: :func:`planner.placement.optimal_placement` (SLSQP over all drones at once, no
kinematics, no network) under the distances the safety filter requires, the ``filter`` row of
``fimnav optimum --oracle-estimate``. A run planning with the true source has no estimator in
its loop, so its trials differ only by the singular fallback's perturbations: one trial is the
run. The full table (every paper mission, A and D) is in docs/control.md, "How far from the
optimum, and why".
"""

from __future__ import annotations

import numpy as np
import pytest

from missions.study.simulator import RunSpec, simulate
from planner.placement import optimal_placement, placement_bounds
from tests.simulator.conftest import paper_mission


@pytest.mark.parametrize(("name", "criterion"), [("ranging_los", "A"), ("bearing", "A")])
def test_a_swarm_planning_with_the_true_source_ends_near_the_optimum(name: str, criterion: str) -> None:
    m = paper_mission(name)
    r = simulate(RunSpec(m, criterion, 1, m.steps), oracle_estimate=True)
    assert sum(r.violations().values()) == 0
    bmin, bmax = m.obstacle_bounds()
    best = optimal_placement(
        m.source.position_at(m.duration_s), m.drones.ranging_mask(), m.drones.bearing_mask(), m.channel.to_planner(),
        placement_bounds(m.limits(), "filter", oracle_estimate=True), bmin, bmax, criterion, starts=3, seed=0,
    )
    ratio = float(np.nanmean(r.peb_m[-1])) / best.peb_m
    assert 1.0 <= ratio <= 1.05, f"{name} {criterion}: final PEB / optimum = {ratio:.3f}"

"""A peer never heard of yet (its first records late or lost, comms.faults) is still a drone:
``planner.agent.plan`` keeps clear of it at its start position, which the mission gives every
drone, aged by the current step (it is within (k + 1) v_max Δt of it at the end of step k).

Before, such a peer was no constraint at all: with records up to 3 steps late the first steps
of paper/bearing had drones meeting peers they had not heard of (the fault grid's early
inter-drone violations). Deterministic, a few milliseconds.
"""

from __future__ import annotations

import numpy as np
import pytest

from types import SimpleNamespace

from planner.agent import PlanView, plan
from planner.config import PlannerConfig
from planner.estimator import EstimatorConfig
from planner.params import Channel, Limits

LIM = Limits()  # d_U* = 1 m, 0.5-1 m per step, 50° per step
NO_BOX = np.zeros((0, 3))


def step_towards_unheard_peer(step_index: int, with_start: bool) -> tuple[float, float]:
    """Drone 0 at (0, 0, 10) flying east (its last step +x), drone 1's start position 2.9 m
    ahead on its left (2.5, 1.5, 10), of which it holds no record. Its estimate is not observable yet, so it keeps its
    heading (the singular fallback, zero perturbation). Returns (distance to drone 1's start
    now, after the step), m."""
    own = np.array([0.0, 0.0, 10.0])
    start = np.array([[0.0, 0.0, 10.0], [2.5, 1.5, 10.0]])
    config = PlannerConfig(
        channel=Channel(),
        limits=LIM,
        criterion="A",
        component_masks={"range": np.array([True, True]), "bearing": np.array([False, False])},
        boxes_min_m=NO_BOX,
        boxes_max_m=NO_BOX,
        d_hop_m=100.0,
        start_positions_m=start if with_start else None,
        estimator=EstimatorConfig(),
    )
    view = PlanView(
        own_mask=np.array([True, False]),
        positions_m=np.array([own, [0.0, 0.0, 0.0]]),  # no record of drone 1: its row is unused
        valid=np.array([True, False]),
        los=np.array([True, False]),
        age_steps=np.array([0, 0]),
        hops=np.array([0, 1]),  # drone 1 is a neighbour (it is within d_hop), just not heard yet
    )
    estimate = SimpleNamespace(estimate_m=np.array([0.0, 500.0, 2.0]), information=np.zeros((3, 3)), observable=np.array(False))
    r = plan(config, own, np.array([1.0, 0.0, 0.0]), view, estimate, np.array([0.5, 0.5]), step_index=step_index)
    return float(np.linalg.norm(own - start[1])), float(np.linalg.norm(r.step.next_position - start[1]))


@pytest.mark.parametrize("step_index", [0, 2])
def test_a_peer_not_heard_of_is_kept_clear_of_at_its_start(step_index: int) -> None:
    before, after = step_towards_unheard_peer(step_index, with_start=True)
    # The requirement d_U* + (k + 1) v_max Δt + 2b is out of reach in one step: the drone
    # turns away so as not to close on the peer's reachable ball (the lower bound on their
    # distance, |p − start| − k v_max Δt, does not shrink).
    assert after >= before - 1e-9, (before, after)


def test_without_the_start_positions_the_unheard_peer_is_ignored() -> None:
    """The same step without the start positions (as fimnav did): straight at the peer."""
    before, after = step_towards_unheard_peer(2, with_start=False)
    assert after < before - 0.7, (before, after)

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

from planner.agent import plan
from planner.params import Limits
from tests.planner.stepping import drone_state, planner_config, step_scene

LIM = Limits()  # d_U* = 1 m, 0.5-1 m per step, 50° per step


def step_towards_unheard_peer(step_index: int, with_start: bool) -> tuple[float, float]:
    """Drone 0 at (0, 0, 10) flying east (its last step +x), drone 1's start position 2.9 m
    ahead on its left (2.5, 1.5, 10), of which it holds no record. Its estimate is not observable yet, so it keeps its
    heading (the singular fallback, zero perturbation). Returns (distance to drone 1's start
    now, after the step), m."""
    own = np.array([0.0, 0.0, 10.0])
    start = np.array([[0.0, 0.0, 10.0], [2.5, 1.5, 10.0]])
    config = planner_config([True, True], [False, False], LIM, start_positions_m=start if with_start else None)
    scene = step_scene(
        0,
        np.array([own, [0.0, 0.0, 0.0]]),  # no record of drone 1: its row is unused
        [True, False],
        step_index=step_index,
        view_los=[True, False],
        hops=[0, 1],  # drone 1 is a neighbour (it is within d_hop), just not heard yet
        estimate_m=[0.0, 500.0, 2.0],
        information=np.zeros((3, 3)),
        observable=False,
    )
    r = plan(config, scene, drone_state(2, previous_step_m=[1.0, 0.0, 0.0]))
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

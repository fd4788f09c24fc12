"""A peer's drift from a drone's records of it (the carried state's ``drift_m``,
planner.step.DroneState, updated by planner.agent.plan) and the filter's preference for steps
that keep clear of a peer's dead-reckoned position.

References: a peer flying a known straight track (its drift is its velocity per step, whatever
records are lost), hand-computed distances to the dead-reckoned position, and two drones flying
side by side down a corridor with records three steps late, measured step by step.
"""

from __future__ import annotations

import numpy as np

from planner.control import kernel_limits
from planner import FimStatus, Limits
from planner import kernels as K
from planner.agent import DRIFT_MAX_GAP_STEPS, plan
from planner.step import DroneState
from tests.planner.stepping import control_step_of, planner_config, step_scene

LIM = Limits()  # d_U* = 1 m, 0.5-1 m per step
FAR_SOURCE = np.array([0.0, 1e5, 10.0])
VELOCITY = np.array([0.8, -0.3, 0.1])  # m per step


def track(step: int) -> np.ndarray:
    return np.array([10.0, 5.0, 12.0]) + step * VELOCITY


def drifts(saved_steps: list[int]) -> list[np.ndarray]:
    """Drone 0's drift of drone 1 (m per step) after each of its planning steps k = 0, 1, ...,
    holding at step k drone 1's record of step ``saved_steps[k]`` (from its straight track)."""
    config = planner_config([True, True], [False, False])
    state = DroneState.initial((), 2)
    out = []
    for k, saved in enumerate(saved_steps):
        view = np.stack([np.array([0.0, -40.0, 10.0]), track(saved)])
        scene = step_scene(0, view, [True, True], step_index=k, saved_steps=[k, saved], estimate_m=FAR_SOURCE, observable=False)
        state = plan(config, scene, state).state
        out.append(state.drift_m[1].copy())
    return out


def test_drift_is_the_peers_step_whatever_records_are_lost() -> None:
    # Records of steps 0, 1, 3 (2 lost), 3 again (nothing new), 6.
    seen = drifts([0, 1, 3, 3, 6])
    assert np.isnan(seen[0]).all()  # one record: no drift yet
    for d in seen[1:]:
        np.testing.assert_allclose(d, VELOCITY, atol=1e-12)


def test_a_gap_longer_than_the_limit_gives_no_drift() -> None:
    far = 1 + DRIFT_MAX_GAP_STEPS + 1
    seen = drifts([0, 1, far, far + 2])
    np.testing.assert_allclose(seen[1], VELOCITY, atol=1e-12)
    assert np.isnan(seen[2]).all()
    np.testing.assert_allclose(seen[3], VELOCITY, atol=1e-12)


def test_steps_nearer_the_dead_reckoned_peer_are_left_out() -> None:
    # Drone at the origin; the peer's record (age 3) is at (-3, 1.8, 0) and it flies +x at
    # 1 m per step: dead-reckoned at (0, 1.8, 0) now and (1, 1.8, 0) after the step.
    p = np.zeros(3)
    now, nxt = np.array([[0.0, 1.8, 0.0]]), np.array([[1.0, 1.8, 0.0]])
    cand = np.array([[1.0, -0.3, 0.0], [1.0, 0.3, 0.0], [0.7, 0.7, 0.0], [0.0, -1.0, 0.0]])
    kept, known = K.dead_reckoning_batch(p, cand, now, nxt, kernel_limits(LIM))
    assert known
    # |(1, -0.3) - (1, 1.8)| = 2.1 >= 1.8; |(1, 0.3) - (1, 1.8)| = 1.5; |(0.7, 0.7) - (1, 1.8)| = 1.14;
    # |(0, -1) - (1, 1.8)| = 2.97.
    assert kept.tolist() == [True, False, False, True]
    # Every one of them keeps "not nearer the record": that rule alone does not tell them apart.
    record = np.array([-3.0, 1.8, 0.0])
    assert (np.linalg.norm(cand - record, axis=-1) >= np.linalg.norm(record)).all()
    # A peer with no drift known (not inside its reachable ball): nothing to prefer.
    assert not K.dead_reckoning_batch(p, cand, now * np.nan, nxt * np.nan, kernel_limits(LIM))[1]


def _corridor(use_drift: bool, steps: int = 30, delay: int = 3, gap: float = 1.8, z: float = 24.5) -> np.ndarray:
    """Two drones flying +x side by side ``gap`` apart between two walls 6 m off each, each
    pulled toward the other, each knowing the other's position ``delay`` steps late. Drone 0's
    last step is 0.01 rad off the corridor's axis, toward its wall: exactly symmetric, both fly
    straight and nothing happens (any asymmetry from −1e-15 to −0.01 rad gives the same
    outcome). Returns the distance between them after each step (m) where both steps were
    filtered."""
    bmin = np.array([[-100.0, -56.0, 0.0], [-100.0, gap + 6.0, 0.0]])
    bmax = np.array([[300.0, -6.0, 40.0], [300.0, gap + 56.0, 40.0]])
    hist = [np.array([[float(k - delay), 0.0, z], [float(k - delay), gap, z]]) for k in range(delay + 1)]
    prev = np.array([[np.cos(-0.01), np.sin(-0.01), 0.0], [1.0, 0.0, 0.0]])
    mask = ~np.eye(2, dtype=bool)
    out = []
    for k in range(delay, delay + steps):
        p, record = hist[k], hist[k - delay]
        peers = np.stack([record, record])
        # Each peer's last step from its two newest records (one step apart).
        drift = np.stack([record - hist[k - delay - 1], record - hist[k - delay - 1]]) if k > delay else np.full((2, 2, 3), np.nan)
        lateral = p[::-1] - p
        lateral[:, [0, 2]] = 0.0
        desired = np.array([1.0, 0.0, 0.2]) + 0.6 * lateral / np.linalg.norm(lateral, axis=1, keepdims=True)
        r = control_step_of(
            p,
            prev,
            -desired,
            np.full(2, FimStatus.OK),
            peers,
            mask,
            np.full((2, 2), delay),
            FAR_SOURCE,
            np.full(2, 50.0),
            bmin,
            bmax,
            LIM,
            np.full((2, 2), 0.5),
            peer_drift_m=drift if use_drift else None,
        )
        prev = np.asarray(r.displacement)
        hist.append(p + prev)
        if np.asarray(r.filtered).all():
            out.append(float(np.linalg.norm(hist[-1][0] - hist[-1][1])))
    return np.asarray(out)


def test_side_by_side_drones_with_late_records_do_not_close_on_each_other() -> None:
    with_drift = _corridor(True)
    record_only = _corridor(False)
    assert with_drift.size >= 5 and record_only.size >= 5  # the filter is at work
    # Kept clear of the record alone, they close while filtered (the scenario is the flaw's).
    assert (np.diff(record_only) < -0.1).any()
    # Kept clear of the dead-reckoned positions, they never close.
    assert (np.diff(with_drift) >= -1e-9).all(), np.round(with_drift, 3)
    assert with_drift.min() >= 1.8 - 1e-9

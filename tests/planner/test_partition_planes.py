"""A partition of the swarm in the worst case: two halves that cannot hear each other, every
drone pulled straight at the other half's true positions (an adversarial cost gradient), for
60 steps. Each drone keeps to its side of the bisector planes built from the last records of
the step of the cut (:func:`planner.control.lost_contact_planes`); the check is on the true
positions, independently of the planner's view: no two drones of different halves ever come
within d_U* (at the steps and on the straight segments between them). The same run where the
unheard peers are ignored (the hop rule: "not a neighbour, so far away") collides, so the test
can fail. Seeded, deterministic, under a second.
"""

from __future__ import annotations

import numpy as np
import pytest

from planner import FimStatus, Limits, control_step
from planner.control import lost_contact_planes

LIM = Limits(d_uav_m=2.0, d_source_m=50.0, z_min_m=2.0, z_max_m=25.0)
STEPS = 60
CUT = 5


def segment_distance(a0: np.ndarray, a1: np.ndarray, b0: np.ndarray, b1: np.ndarray) -> float:
    """Smallest distance between two drones moving at constant velocity from a0→a1, b0→b1 (m)."""
    d0, dv = a0 - b0, (a1 - a0) - (b1 - b0)
    t = 0.0 if dv @ dv == 0.0 else float(np.clip(-(d0 @ dv) / (dv @ dv), 0.0, 1.0))
    return float(np.linalg.norm(d0 + t * dv))


def fly(seed: int, planes_rule: bool) -> float:
    """Fly 2 + 2 drones; return the smallest true distance between drones of different halves."""
    rng = np.random.default_rng(seed)
    n = 4
    half = np.array([0, 0, 1, 1])
    # Two clusters 14-20 m apart, facing each other across x = 0.
    p = np.stack([np.array([-8.0 - 2.0 * k, 0.0, 10.0]) for k in range(2)] + [np.array([8.0 + 2.0 * k, 0.0, 10.0]) for k in range(2)])
    p = p + rng.uniform(-1.0, 1.0, p.shape) * np.array([1.0, 4.0, 2.0])
    src = np.array([0.0, 500.0, 2.0])  # far away: its keep-out never binds
    prev = np.zeros((n, 3))
    history = [p.copy()]
    cross = half[:, None] != half[None, :]
    worst = np.inf
    for k in range(STEPS):
        cut = k >= CUT
        # Views: everyone fresh before the cut; after it, the other half frozen at step CUT - 1.
        seen_step = np.where(cross & cut, CUT - 1, k)
        view = np.stack([np.stack([history[seen_step[i, j]][j] for j in range(n)]) for i in range(n)])
        own_then = np.stack([np.stack([history[seen_step[i, j]][i] for j in range(n)]) for i in range(n)])
        mask = ~np.eye(n, dtype=bool)
        age = (k - seen_step).astype(float)
        # Adversarial cost: each drone descends toward the other half's true centroid.
        target = np.stack([p[half != half[i]].mean(0) for i in range(n)])
        grad = p - target
        planes = None
        if cut and planes_rule:
            view, planes = lost_contact_planes(own_then, view, cross & ~np.eye(n, dtype=bool))
            age = np.where(cross, 0.0, age)
        elif cut:
            mask = mask & ~cross  # the hop rule: peers not heard are taken to be out of range
        r = control_step(p, prev, grad, np.full(n, int(FimStatus.OK), np.int8), view, mask, age, src,
                         np.full(n, LIM.d_source_m), np.zeros((0, 3)), np.zeros((0, 3)), LIM, rng.random((n, 2)),
                         peer_planes=planes)
        nxt = np.asarray(r.next_position)
        for i in range(n):
            for j in range(n):
                if cross[i, j] and i < j:
                    worst = min(worst, segment_distance(p[i], nxt[i], p[j], nxt[j]))
        prev = nxt - p
        p = nxt
        history.append(p.copy())
    return worst


@pytest.mark.parametrize("seed", range(6))
def test_halves_heading_at_each_other_never_come_within_d_uav(seed: int) -> None:
    assert fly(seed, planes_rule=True) >= LIM.d_uav_m - 1e-9


def test_ignoring_unheard_peers_lets_the_halves_collide() -> None:
    assert min(fly(seed, planes_rule=False) for seed in range(3)) < LIM.d_uav_m

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

from planner.control import kernel_limits
from planner import FimStatus, Limits
from planner import kernels as K
from planner.control import SOURCE, UAV, lost_contact_planes
from tests.planner.stepping import NO_BOX, control_step_of

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
        r = control_step_of(
            p,
            prev,
            grad,
            np.full(n, int(FimStatus.OK), np.int8),
            view,
            mask,
            age,
            src,
            np.full(n, LIM.d_source_m),
            np.zeros((0, 3)),
            np.zeros((0, 3)),
            LIM,
            rng.random((n, 2)),
            peer_planes=planes,
        )
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


def envelope(p, prev, need, peers, planes, strict, loose, hard, source, keepout):  # type: ignore[no-untyped-def]
    """The safety filter's envelope search alone (:func:`planner.kernels.envelope_batch`) for one
    drone whose limited step (``prev`` again) failed, without a loiter certificate: (step, margins)."""
    f = np.ascontiguousarray
    step, margins, _ = K.envelope_batch(
        f(p), f(prev), f(prev), True, f(need), np.full(4, np.inf), f(peers), f(planes), f(strict), f(loose), f(hard), f(source), keepout,
        NO_BOX, NO_BOX, kernel_limits(LIM),
    )
    return step, margins


def squeeze(plane: bool) -> tuple[float, float, float]:
    """One drone at (0, 0, 10) flying +x (it cannot stop or turn back in one step), its source
    keep-out just behind it on −y (source (0, −50, 10)) and a peer's row just ahead on +y that
    requires a step toward −y of about 5 cm: no step keeps both. Returns the chosen step's
    source distance, its signed distance past the peer's plane (y − y_plane, ≤ 0 on the drone's
    side) and its distance to the peer's point (m)."""
    p = np.array([0.0, 0.0, 10.0])
    prev = np.array([LIM.step_max_m, 0.0, 0.0])
    tb = LIM.turn_buffer_m
    source = np.array([0.0, -50.0, 10.0])
    y_peer = 5.0
    now = y_peer + (0.5 * LIM.d_uav_m if plane else 0.0)  # the row's distance now
    # A step must come about 5 cm nearer −y (a point row gains dx²/(2·5 m) ≤ 10 cm sideways).
    required = np.array([now + (0.05 if plane else 0.15)])
    planes = np.array([[0.0, -1.0, 0.0]]) if plane else np.zeros((1, 3))
    need = np.zeros(4)
    need[SOURCE] = -tb + 0.02  # hard keep-out (keep-out 50 m − 2 cm plus b): come no nearer than 2 cm
    peer = np.array([[0.0, y_peer, 10.0]])
    step, _ = envelope(p, prev, need, peer, planes, required, required, required, source, 50.0 - 0.02)
    end = p + step
    return float(np.linalg.norm(end - source)), float(end[1] - y_peer), float(np.linalg.norm(end - peer[0]))


def test_a_squeezed_drone_keeps_the_source_keep_out_and_gives_up_only_the_plane_buffer() -> None:
    """Between the source keep-out and a lost peer's plane, the safety filter keeps the source
    keep-out and the plane itself (the d_U*/2 in front of it is what it gives up)."""
    d_source, past_plane, _ = squeeze(plane=True)
    assert d_source >= 50.0 - 0.02 - 1e-9
    assert past_plane <= 0.0


def test_a_squeezed_drone_keeps_the_source_keep_out_and_a_heard_peers_record_d_uav_plus_one_step() -> None:
    """Against a heard peer's reachable ball (a point row) the squeezed drone gives up the ball
    beyond d_U* + v_max Δt of the record (the peer's own filter keeps this drone's ball) and
    keeps the source keep-out."""
    d_source, _, d_peer = squeeze(plane=False)
    assert d_source >= 50.0 - 0.02 - 1e-9
    assert d_peer >= LIM.d_uav_m + LIM.step_max_m


def test_a_squeezed_drone_inside_a_peers_reachable_ball_comes_no_nearer_its_record() -> None:
    """Inside a heard peer's reachable ball (its ``hard`` requirement is the distance now), the
    squeezed drone comes no nearer the peer's record, not even down to d_U* + v_max Δt: it gives
    the source keep-out up instead. Outside the ball, the same squeeze keeps the keep-out and
    approaches the record (the test above)."""
    tb = LIM.turn_buffer_m
    p = np.array([0.0, 0.0, 10.0])
    prev = np.array([LIM.step_max_m, 0.0, 0.0])  # flying +x: every step has dx > 0
    source = np.array([20.0, -50.0, 10.0])
    d_source = float(np.linalg.norm(p - source))
    # The keep-out is 1 cm in deficit: no step may bring the drone nearer the source, which asks
    # for dy >= 0.4 dx, toward the record at (3, 5): every such step comes nearer it.
    record = np.array([3.0, 5.0, 10.0])
    d_record = float(np.linalg.norm(p - record))
    assert d_record > LIM.d_uav_m + LIM.step_max_m  # the record clearance alone would allow it
    need = np.zeros(4)
    need[SOURCE] = -0.01 - tb
    strict = np.array([LIM.d_uav_m + 4.0 * LIM.step_max_m + 2.0 * tb])  # a record 3 steps old

    def pick(hard_required: float) -> np.ndarray:
        step, margins = envelope(p, prev, need, record[None], np.zeros((1, 3)), strict, strict, np.array([hard_required]), source, d_source + 0.01)
        assert margins[UAV] < 0.0  # the peer's strict requirement is not met: a relaxed tier
        return p + step

    inside = pick(d_record)  # inside the ball: the hard requirement is the distance now
    assert np.linalg.norm(inside - record) >= d_record - 1e-9
    assert np.linalg.norm(inside - source) < d_source  # the keep-out gave way
    outside = pick(d_record - 0.5)  # outside: the ball itself may shrink to d_U* + v_max Δt
    assert np.linalg.norm(outside - source) >= d_source - 1e-9
    assert LIM.d_uav_m + LIM.step_max_m <= np.linalg.norm(outside - record) < d_record


def test_a_squeezed_drone_inside_a_peers_reachable_ball_at_the_keep_outs_floor_gives_up_the_ball() -> None:
    """The same squeeze as above with the drone already at the keep-out's floor, d_S* + 1.5 m
    from the estimate (1 cm inside it): the floor outranks the peer's ball (the peer's own filter
    keeps this drone's ball; nothing keeps the source's), so the drone comes nearer the record
    and no nearer the estimate. Above the floor the ball is kept (the test above)."""
    tb = LIM.turn_buffer_m
    p = np.array([0.0, 0.0, 10.0])
    prev = np.array([LIM.step_max_m, 0.0, 0.0])
    floor = LIM.d_source_m + 1.5
    direction = np.array([20.0, -50.0, 0.0]) / np.linalg.norm([20.0, -50.0, 0.0])
    source = p + (floor - 0.01) * direction
    d_source = float(np.linalg.norm(p - source))
    record = np.array([3.0, 5.0, 10.0])
    d_record = float(np.linalg.norm(p - record))
    need = np.zeros(4)
    need[SOURCE] = -0.01 - tb
    strict = np.array([LIM.d_uav_m + 4.0 * LIM.step_max_m + 2.0 * tb])
    step, margins = envelope(p, prev, need, record[None], np.zeros((1, 3)), strict, strict, np.array([d_record]), source, floor)
    end = p + step
    assert margins[UAV] < 0.0
    assert np.linalg.norm(end - source) >= d_source - 1e-9  # the floor kept
    assert np.linalg.norm(end - record) < d_record  # the ball given up

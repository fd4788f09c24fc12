"""The planning FIM with the own link's predicted line of sight (planner.agent.own_los_weight).

References: a dense-sampling clearance, central finite differences of the full planning cost
C(J(p)) with J(p) = J_peers + q(p) J_LOS(p) + (1 − q(p)) J_NLOS(p), and a shadow the drone must
leave (the true line-of-sight test of planner.geometry.line_of_sight).
"""

from __future__ import annotations

import numpy as np
import pytest

from planner.agent import _planning_cost, own_los_weight
from planner.fim import cost, fisher_information
from planner.geometry import distance_to_boxes, line_of_sight, link_clearance_with_gradient
from planner.params import Channel

CHANNEL = Channel(gamma=2.0, sigma_ratio_los=1.7, sigma_ratio_nlos=3.2, sigma_bearing_rad=np.radians(10.0))
# The paper missions' buildings (missions/paper/*.yaml).
BMIN = np.array([[-40.0, 95.0, 0.0], [10.0, 70.0, 0.0], [-18.0, 12.0, 0.0]])
BMAX = np.array([[-10.0, 115.0, 30.0], [35.0, 90.0, 30.0], [-8.0, 24.0, 30.0]])


def _dense_clearance(p: np.ndarray, s: np.ndarray, n: int = 4001) -> np.ndarray:
    """Per link, the least signed distance of 4000 points of it from the buildings, each
    building extended past a face the link cannot pass (its bottom at or below both ends, its top
    at or above both)."""
    t = np.linspace(0.0, 1.0, n)[1:]
    out = np.empty(p.shape[0])
    for i in range(p.shape[0]):
        x = s[i] + t[:, None] * (p[i] - s[i])
        lo, hi = BMIN.copy(), BMAX.copy()
        lo[lo[:, 2] <= min(p[i, 2], s[i, 2]), 2] = -1e6
        hi[hi[:, 2] >= max(p[i, 2], s[i, 2]), 2] = 1e6
        out[i] = distance_to_boxes(x, lo, hi).min()
    return out


def test_clearance_matches_dense_sampling_and_sign_is_line_of_sight() -> None:
    rng = np.random.default_rng(3)
    p = rng.uniform([-80.0, -80.0, 2.0], [80.0, 160.0, 25.0], (200, 3))
    s = rng.normal([0.0, 0.0, 2.0], 3.0, (200, 3))
    c = link_clearance_with_gradient(p, s, BMIN, BMAX)[0].min(-1)  # the nearest building's
    dense = _dense_clearance(p, s)  # 4000 points: every 5 cm on a 200 m link
    # 16 samples: the sampled minimum is an upper bound, within the sample spacing's reach.
    spacing = np.linalg.norm(p - s, axis=-1) / 16
    assert np.all(c >= dense - 1e-9)
    assert np.all(c - dense <= spacing)
    los = line_of_sight(p[:, None, :], s, BMIN, BMAX)[:, 0]
    clear = np.abs(dense) > spacing  # away from the shadow edges, the sign is the LOS test
    assert np.array_equal((c > 0)[clear], los[clear])
    assert (~los).sum() > 25 and los.sum() > 25


def test_cutoff_keeps_near_links_exact() -> None:
    rng = np.random.default_rng(4)
    p = rng.uniform([-80.0, -80.0, 2.0], [80.0, 160.0, 25.0], (300, 3))
    s = rng.normal([0.0, 0.0, 2.0], 3.0, (300, 3))
    c, g = link_clearance_with_gradient(p, s, BMIN, BMAX)
    cc, gc = link_clearance_with_gradient(p, s, BMIN, BMAX, cutoff_m=10.0)
    near = c < 10.0
    np.testing.assert_array_equal(cc[near], c[near])
    np.testing.assert_array_equal(gc[near], g[near])
    assert np.all(cc[~near] >= 10.0) and np.all(cc[~near] <= c[~near] + 1e-9)
    assert 0.1 < near.mean() < 0.9


@pytest.mark.parametrize("criterion", ["A", "D"])
@pytest.mark.parametrize("own_role", [(True, False), (False, True), (True, True)])
def test_planning_gradient_matches_finite_differences(criterion: str, own_role: tuple[bool, bool]) -> None:
    """Near B3's shadow edge (0 < q < 1) the gradient of the planning cost, with its ∇q term,
    is the derivative of C(J(p)) (on the LOS side: deeper than one softness into a shadow the
    slope is held, :func:`test_deep_shadow_points_to_the_nearer_side`)."""
    p_hat = np.array([0.5, -0.3, 2.2])
    peers = np.array([[40.0, -30.0, 10.0], [-45.0, -20.0, 20.0], [5.0, -55.0, 6.0], [50.0, 20.0, 15.0]])
    peer_rng = np.array([True, False, True, True])
    peer_brg = np.array([True, True, False, True])
    own_rng, own_brg = own_role

    def full_cost(p: np.ndarray) -> float:
        q, _ = own_los_weight(p, p_hat, BMIN, BMAX)
        J_peers = fisher_information(p_hat, peers, peer_rng, peer_brg, np.ones(4, dtype=bool), CHANNEL)
        one = p[None, :]
        J_L = fisher_information(p_hat, one, [own_rng], [own_brg], [True], CHANNEL)
        J_N = fisher_information(p_hat, one, [own_rng], [own_brg], [False], CHANNEL)
        return float(cost(J_peers + q * J_L + (1.0 - q) * J_N, criterion)[0])

    checked = 0
    for p in ([-12.0, 49.0, 20.0], [-10.0, 49.0, 20.0], [-9.0, 48.0, 12.0]):
        p = np.array(p)
        q, _ = own_los_weight(p, p_hat, BMIN, BMAX)
        assert 0.001 < q < 0.999, q  # on the shadow's soft edge: the ∇q term matters
        view = np.vstack([p, peers])
        own = np.array([True, False, False, False, False])
        cg = _planning_cost(
            p_hat, p, own, view, np.r_[own_rng, peer_rng], np.r_[own_brg, peer_brg], np.r_[True, np.ones(4, dtype=bool)],
            np.asarray(own_rng), np.asarray(own_brg), CHANNEL, criterion, BMIN, BMAX,
        )
        # cg was computed with the measured flag (LOS here) bounding q; compare without it.
        qm, _ = own_los_weight(p, p_hat, BMIN, BMAX, measured_los=True)
        if qm != q:
            continue
        h = 1e-4
        fd = np.array([(full_cost(p + h * e) - full_cost(p - h * e)) / (2 * h) for e in np.eye(3)])
        np.testing.assert_allclose(cg.gradient, fd, rtol=2e-4, atol=1e-9 * np.abs(fd).max())
        assert cg.value == pytest.approx(full_cost(p), rel=1e-12)
        checked += 1
    assert checked >= 2


def test_deep_shadow_points_to_the_nearer_side() -> None:
    """Deep in B1's shadow (B1 alone; buildings stand on the ground and rise above the drones), ∇q is level
    and points to the side of B1 the drone clears with the shorter move along x, in closed form
    for a link from the source at the origin: east of B1 (x = −10 m) at both of its y faces,
    x ≥ −10 y/115 m; west (x = −40 m), x ≤ −40 y/95 m. Its size does not fade with depth: it is
    at least the slope one softness inside the shadow, φ(1)/s, times t* ≥ 95/y."""
    src = np.array([0.0, 0.0, 2.0])
    checked = 0
    for y in (130.0, 150.0, 180.0):
        for x in np.linspace(-0.33 * y, -10.0 * y / 115.0, 9)[1:-1]:
            for z in (3.0, 12.0, 24.0):
                p = np.array([x, y, z])
                c, _ = link_clearance_with_gradient(p, src, BMIN, BMAX)
                if not c[0] < -4.0:  # deep behind B1
                    continue
                q, gq = own_los_weight(p, src, BMIN[:1], BMAX[:1])
                east, west = -10.0 * y / 115.0 - x, x + 40.0 * y / 95.0
                assert gq[2] == 0.0 and gq[1] == 0.0
                assert np.sign(gq[0]) == (1.0 if east < west else -1.0), (p, east, west, gq)
                assert abs(gq[0]) >= 0.2419707 / 2.0 * 95.0 / y * 0.999, (p, gq)
                checked += 1
    assert checked >= 20


def test_measured_flag_bounds_q() -> None:
    p = np.array([[-26.0, 44.0, 12.0], [30.0, 40.0, 10.0]])  # in B3's shadow; in the open
    q, _ = own_los_weight(p, np.zeros(3), BMIN, BMAX)
    assert q[0] < 0.2 and q[1] == pytest.approx(1.0)
    qm, _ = own_los_weight(p, np.zeros(3), BMIN, BMAX, measured_los=[True, False])
    assert qm[0] == pytest.approx(0.8413, abs=1e-4)  # measured LOS: at least Φ(1)
    assert qm[1] == pytest.approx(1.0 - 0.8413, abs=1e-4)  # measured NLOS: at most 1 − Φ(1)


def _descend(p: np.ndarray, peers: np.ndarray, boxes: tuple[np.ndarray, np.ndarray], steps: int) -> np.ndarray:
    """Bearing-only drone i stepping 1 m along −∇C (held at 50 m from the source, the keep-out,
    and between 2 and 25 m up),
    with bearing-only peers, the true source as estimate and its measured LOS flag."""
    src = np.array([0.0, 0.0, 2.0])
    for _k in range(steps):
        view = np.vstack([p, peers])
        measured = bool(line_of_sight(p[None], src, BMIN, BMAX)[0])
        n = len(view)
        cg = _planning_cost(
            src, p, np.r_[True, np.zeros(n - 1, dtype=bool)], view, np.zeros(n, dtype=bool), np.ones(n, dtype=bool),
            np.r_[measured, np.ones(n - 1, dtype=bool)], np.asarray(False), np.asarray(True), CHANNEL, "A", *boxes,
        )
        p = p - cg.gradient / np.linalg.norm(cg.gradient)
        p[2] = min(max(p[2], 2.0), 25.0)  # the altitude box (the buildings are 30 m tall)
        h = p[:2] - src[:2]
        p[:2] = src[:2] + h * np.sqrt(50.0**2 - (p[2] - src[2]) ** 2) / np.linalg.norm(h)
    return p


def test_descent_leaves_the_shadow() -> None:
    """The peers leave their widest angular gap around 127°, in B3's shadow (108°-146° seen from
    the source). Taking the own link as LOS (fimnav before; here: the no-building path), the
    drone settles in the shadow; with the predicted LOS it leaves it."""
    src = np.array([0.0, 0.0, 2.0])
    az = np.radians([7.0, -53.0, -113.0, 187.0, 67.0])
    peers = np.stack([50.0 * np.cos(az), 50.0 * np.sin(az), np.full(5, 12.0)], -1)
    a0 = np.radians(124.0)
    p0 = np.array([50.0 * np.cos(a0), 50.0 * np.sin(a0), 12.0])
    assert not line_of_sight(p0[None], src, BMIN, BMAX)[0]
    old = _descend(p0, peers, (np.zeros((0, 3)), np.zeros((0, 3))), 120)
    assert not line_of_sight(old[None], src, BMIN, BMAX)[0], "the scenario does not hold a LOS planner in the shadow"
    new = _descend(p0, peers, (BMIN, BMAX), 120)
    assert line_of_sight(new[None], src, BMIN, BMAX)[0], np.degrees(np.arctan2(new[1], new[0]))

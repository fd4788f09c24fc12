"""Delayed view (paper Sec. II-B): hop counts vs scipy's shortest paths, and the memory buffer on
scripted scenarios."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse.csgraph import shortest_path
from scipy.spatial.distance import cdist

from planner import hop_counts, update_saved_steps
from planner.network import NEVER, UNREACHABLE


def reference_hops(p: np.ndarray, d_hop: float) -> np.ndarray:
    adj = (cdist(p, p) <= d_hop).astype(float)
    np.fill_diagonal(adj, 0.0)
    dist = shortest_path(adj, method="D", unweighted=True, directed=False)
    return np.where(np.isinf(dist), UNREACHABLE, dist).astype(np.int64)


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 25), d_hop=st.floats(5.0, 60.0), batch=st.integers(1, 3))
def test_hop_counts_vs_scipy_shortest_path(seed, n, d_hop, batch):
    rng = np.random.default_rng(seed)
    # Clusters far apart make disconnected graphs common.
    centres = rng.uniform(-300, 300, (batch, 3, 3))
    pos = centres[:, rng.integers(0, 3, n)] + rng.uniform(-50, 50, (batch, n, 3))
    hops = hop_counts(pos, d_hop)
    assert hops.shape == (batch, n, n)
    for b in range(batch):
        np.testing.assert_array_equal(hops[b], reference_hops(pos[b], d_hop))


def test_hop_counts_line_and_max_hops():
    pos = np.array([[10.0 * k, 0.0, 5.0] for k in range(6)] + [[1000.0, 0.0, 5.0]])
    hops = hop_counts(pos, 10.0)
    assert hops[0, 5] == 5 and hops[5, 0] == 5 and hops[2, 4] == 2
    assert (hops[6, :6] == UNREACHABLE).all() and hops[6, 6] == 0
    limited = hop_counts(pos, 10.0, max_hops=2)
    assert limited[0, 2] == 2 and limited[0, 3] == UNREACHABLE
    np.testing.assert_array_equal(np.where(hops <= 2, hops, UNREACHABLE), limited)
    # Exactly at d_hop counts as a link (|p_i - p_j| <= d_hop).
    assert hop_counts(np.array([[0.0, 0, 0], [3.0, 4.0, 0]]), 5.0)[0, 1] == 1


def test_saved_steps_scripted_line():
    """Drones on a line, one hop apart. At step k, i sees j's record ℓ = k − h + 1."""
    h_max = 2
    hops = hop_counts(np.array([[10.0 * k, 0.0, 0.0] for k in range(4)]), 10.0)
    saved = np.full((4, 4), NEVER)
    for k in range(5):
        saved = update_saved_steps(saved, hops, k, h_max)
        np.testing.assert_array_equal(np.diag(saved), [k] * 4)
        assert saved[0, 1] == k  # 1 hop: current
        assert saved[0, 2] == k - 1  # 2 hops: one step late
        assert saved[0, 3] == NEVER  # 3 hops > h_max: never received


def test_saved_steps_keep_last_when_out_of_range_and_never_go_back():
    h_max = 3
    saved = np.full((2, 2), NEVER)
    script = [
        # (step, hop count between the two drones, expected saved step of the peer)
        (0, 1, 0),
        (1, 1, 1),
        (2, UNREACHABLE, 1),  # isolated: keep the last saved record
        (3, 5, 1),  # beyond h_max: keep it
        (4, 3, 2),  # back in range with 3 hops: ℓ = 4 − 3 + 1
        (5, 3, 3),
        (6, 1, 6),
        (7, 3, 6),  # hop count grew: ℓ = 5 would be older than what is saved: keep 6
        (8, 3, 6),
        (9, 2, 8),
    ]
    for k, h, expected in script:
        hops = np.array([[0, h], [h, 0]])
        saved = update_saved_steps(saved, hops, k, h_max)
        assert saved[0, 1] == expected and saved[1, 0] == expected, (k, h, saved)
        assert saved[0, 0] == k


def test_saved_steps_batched_random(rng):
    """Batched update equals per-trial updates; saved steps never decrease and never exceed k."""
    T, N, h_max = 3, 6, 2
    saved = np.full((T, N, N), NEVER)
    for k in range(12):
        pos = rng.uniform(-40, 40, (T, N, 3))
        hops = hop_counts(pos, 30.0)
        new = update_saved_steps(saved, hops, k, h_max)
        for t in range(T):
            np.testing.assert_array_equal(new[t], update_saved_steps(saved[t], hops[t], k, h_max))
            ok = (hops[t] >= 1) & (hops[t] <= h_max)
            expected = np.where(ok, np.maximum(saved[t], k - hops[t] + 1), saved[t])
            np.fill_diagonal(expected, k)
            np.testing.assert_array_equal(new[t], expected)
        assert (new >= saved).all() and (new <= k).all()
        saved = new

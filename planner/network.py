"""Multi-hop dissemination with latency: hop counts and the delayed view (paper Sec. II-B).

Drone i hears drone j directly when their distance is at most d_hop; farther data travel over
h_ij hops of the disk graph and arrive h_ij − 1 steps late: at step k drone i sees j's record of
step ℓ = k − h_ij + 1. Beyond h_max hops, or when j is unreachable, drone i keeps the last record
of j it saved (the paper's memory buffer). A record never replaces a newer one already saved
(if the hop count grows, ℓ could go back in time; fimnav keeps the newest).

All functions are batched over leading dimensions (trials).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

IntArray = NDArray[np.int64]

#: Hop count of an unreachable pair.
UNREACHABLE: int = -1
#: Saved step of a peer never heard of.
NEVER: int = -1


def hop_counts(positions: ArrayLike, d_hop_m: float, max_hops: int | None = None, blocked: ArrayLike | None = None) -> IntArray:
    """Hop counts h_ij of the disk graph of radius d_hop (breadth-first search, batched).

    Args:
        positions: drone positions, shape (..., N, 3), m, ENU.
        d_hop_m: communication radius d_hop (m): i and j are neighbours when |p_i − p_j| ≤ d_hop.
        max_hops: stop the search after this many hops (pairs farther are UNREACHABLE);
            None searches the whole graph.
        blocked: (N, N) bool, links cut whatever the distance (a network partition); None: none.

    Returns:
        Integer array (..., N, N): 0 on the diagonal, the number of hops of the shortest path,
        or :data:`UNREACHABLE` (−1).
    """
    p = np.asarray(positions, dtype=float)
    n = p.shape[-2]
    diff = p[..., :, None, :] - p[..., None, :, :]
    near = (diff * diff).sum(-1) <= d_hop_m * d_hop_m
    if blocked is not None:
        near = near & ~np.asarray(blocked, dtype=bool)
    adj = near.astype(np.uint8)
    eye = np.eye(n, dtype=bool)
    reached = np.broadcast_to(eye, adj.shape).copy()
    hops = np.where(reached, 0, UNREACHABLE).astype(np.int64)
    limit = n - 1 if max_hops is None else min(max_hops, n - 1)
    for h in range(1, limit + 1):
        grown = (reached.astype(np.uint8) @ adj) > 0
        new = grown & ~reached
        if not new.any():
            break
        hops[new] = h
        reached |= new
    return hops


def update_saved_steps(saved_steps: ArrayLike, hops: ArrayLike, step: int, h_max: int) -> IntArray:
    """Advance the memory buffer: the step of each peer's record that drone i holds at step k.

    ``saved[..., i, j]`` is the step ℓ of the newest record of drone j saved by drone i.
    At step k, for 1 ≤ h_ij ≤ h_max, drone i receives j's record of step ℓ = k − h_ij + 1
    (eq. 2's delayed data vector); its own record (h_ii = 0) is always current (ℓ = k).
    Otherwise it keeps what it saved.

    Args:
        saved_steps: (..., N, N) int, :data:`NEVER` (−1) for nothing saved yet.
        hops: (..., N, N) from :func:`hop_counts`.
        step: the current step k (≥ 0).
        h_max: maximum number of hops h_max.

    Returns:
        The new saved steps (..., N, N).
    """
    saved = np.asarray(saved_steps, dtype=np.int64)
    h = np.asarray(hops, dtype=np.int64)
    n = h.shape[-1]
    eye = np.eye(n, dtype=bool)
    delivered = ((h >= 1) & (h <= h_max)) | eye
    ell = np.where(eye, step, step - h + 1)
    return np.where(delivered, np.maximum(saved, ell), saved)

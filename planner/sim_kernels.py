"""Compiled kernels of the in-process simulator's per-step bookkeeping (numba).

:func:`missions.study.simulator.simulate` steps M trials × N drones together; around the
planning and estimation kernels, each step checks every drone's line of sight, the hop counts
of the disk graph, the memory buffer, and gathers each drone's delayed view and the records new
to it. Each kernel here does one of these for the whole batch in one loop over (trial, drone),
filling arrays the caller allocates, instead of a dozen numpy calls on (M, N, N, 3) temporaries.

Every kernel computes exactly what the numpy function it stands in for computes (the same
floating-point operations in the same order; integers and indexing otherwise), so a run is
bit-identical with either: :func:`planner.geometry.line_of_sight` (slab test),
:func:`planner.network.hop_counts` and :func:`planner.network.update_saved_steps` (disk graph,
memory buffer), the simulator's gathers, and the pairwise term of
:func:`missions.study.simulator.safety_margins`. The tests check each against that function.

Only the simulator imports this module: a vehicle process, which measures with
:mod:`planner.observation` and :mod:`planner.geometry` but never plans, does not import numba.

Imports: numpy and numba only.
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

#: numba's decorator, typed loosely: the kernels' Python signatures are their docstrings'.
njit: Any = numba.njit


@njit(cache=True)
def line_of_sight(points, source, bmin, bmax, out):  # pragma: no cover - compiled
    """Slab test of :func:`planner.geometry.line_of_sight` for every point.

    points (n, 3) m ENU; source (3,) m ENU; bmin, bmax (B, 3) box corners; out (n,) bool,
    True where the segment point → source meets no box. NaN propagates as in numpy's
    ``minimum``/``maximum`` (a NaN slab bound leaves the link unblocked by that box).
    """
    nb = bmin.shape[0]
    for n in range(points.shape[0]):
        free = True
        for b in range(nb):
            t_lo = -math.inf
            t_hi = math.inf
            nan_lo = False
            nan_hi = False
            for a in range(3):
                o = points[n, a]
                dirn = source[a] - o
                if dirn == 0.0:
                    inside = (o >= bmin[b, a]) & (o <= bmax[b, a])
                    lo = -math.inf if inside else math.inf
                    hi = math.inf if inside else -math.inf
                else:
                    inv = 1.0 / dirn
                    t1 = (bmin[b, a] - o) * inv
                    t2 = (bmax[b, a] - o) * inv
                    if (t1 != t1) | (t2 != t2):
                        nan_lo = True
                        nan_hi = True
                        continue
                    lo = min(t1, t2)
                    hi = max(t1, t2)
                t_lo = max(t_lo, lo)
                t_hi = min(t_hi, hi)
            if nan_lo | nan_hi:
                continue  # NaN <= x is False: not blocked by this box
            if max(t_lo, 0.0) <= min(t_hi, 1.0):
                free = False
                break
        out[n] = free


@njit(cache=True)
def hop_counts(positions, d_hop_m, max_hops, blocked, use_blocked, hops):  # pragma: no cover - compiled
    """Hop counts of :func:`planner.network.hop_counts` (breadth-first search per drone).

    positions (M, N, 3) m; d_hop_m the disk radius (m); max_hops the search depth (< 0: the
    whole graph); blocked (N, N) bool links cut when ``use_blocked``; hops (M, N, N) int64 out:
    0 on the diagonal, the shortest path's hops, or −1 (unreachable within the depth).
    """
    M, N = positions.shape[0], positions.shape[1]
    d2max = d_hop_m * d_hop_m
    limit = N - 1 if max_hops < 0 else min(max_hops, N - 1)
    adj = np.empty((N, N), dtype=np.bool_)
    frontier = np.empty(N, dtype=np.int64)
    nxt = np.empty(N, dtype=np.int64)
    for m in range(M):
        for i in range(N):
            for j in range(N):
                dx = positions[m, i, 0] - positions[m, j, 0]
                dy = positions[m, i, 1] - positions[m, j, 1]
                dz = positions[m, i, 2] - positions[m, j, 2]
                near = dx * dx + dy * dy + dz * dz <= d2max
                if use_blocked:
                    near = near & (not blocked[i, j])
                adj[i, j] = near
        for i in range(N):
            for j in range(N):
                hops[m, i, j] = -1
            hops[m, i, i] = 0
            frontier[0] = i
            n_front = 1
            n_reached = 1
            for h in range(1, limit + 1):
                if n_reached == N:
                    break
                n_next = 0
                for f in range(n_front):
                    r = frontier[f]
                    for j in range(N):
                        if adj[r, j] and hops[m, i, j] < 0:
                            hops[m, i, j] = h
                            nxt[n_next] = j
                            n_next += 1
                n_reached += n_next
                if n_next == 0:
                    break
                for f in range(n_next):
                    frontier[f] = nxt[f]
                n_front = n_next


@njit(cache=True)
def update_saved_steps(saved, hops, step, h_max):  # pragma: no cover - compiled
    """In place, :func:`planner.network.update_saved_steps`: saved (M, N, N) int64 steps of the
    records held (−1: none), hops (M, N, N) int64, step k, h_max the hop limit."""
    M, N = saved.shape[0], saved.shape[1]
    for m in range(M):
        for i in range(N):
            for j in range(N):
                if i == j:
                    saved[m, i, j] = max(saved[m, i, j], step)
                else:
                    h = hops[m, i, j]
                    if (h >= 1) & (h <= h_max):
                        saved[m, i, j] = max(saved[m, i, j], step - h + 1)


@njit(cache=True)
def gather_view(positions, rec_los, saved, step, view_positions, view_los, have, ages):  # pragma: no cover - compiled
    """Every drone's delayed view: drone i's record of drone j is step ``saved[m, i, j]``.

    positions (K+1, M, N, 3) the position history; rec_los (K, M, N) bool the records' LOS;
    saved (M, N, N) int64 (−1: no record; the arrays then hold drone j's record of step 0,
    as the numpy gather with the index clipped at 0); outputs view_positions (M, N, N, 3),
    view_los, have (M, N, N) bool, ages (M, N, N) int16 (k − ℓ, −1 without a record).
    """
    M, N = saved.shape[0], saved.shape[1]
    for m in range(M):
        for i in range(N):
            for j in range(N):
                s = saved[m, i, j]
                held = s >= 0
                t = max(s, 0)
                for a in range(3):
                    view_positions[m, i, j, a] = positions[t, m, j, a]
                view_los[m, i, j] = rec_los[t, m, j]
                have[m, i, j] = held
                ages[m, i, j] = step - s if held else -1


@njit(cache=True)
def gather_new_records(
    saved, used, view_positions, view_los, rec_range, rec_az, rec_el, pos_out, range_out, az_out, el_out, los_out
):  # pragma: no cover - compiled
    """The records new to each drone (step ``saved`` > ``used``), NaN (False) elsewhere, and
    ``used`` advanced to ``saved`` in place.

    saved, used (M, N, N) int64; view_positions (M, N, N, 3), view_los (M, N, N) from
    :func:`gather_view`; rec_range, rec_az, rec_el (K, M, N) the records' values; outputs
    pos_out (M, N, N, 3), range_out, az_out, el_out (M, N, N) float, los_out (M, N, N) bool.
    """
    M, N = saved.shape[0], saved.shape[1]
    nan = np.nan
    for m in range(M):
        for i in range(N):
            for j in range(N):
                s = saved[m, i, j]
                new = s > used[m, i, j]
                used[m, i, j] = s
                if new:
                    t = max(s, 0)
                    for a in range(3):
                        pos_out[m, i, j, a] = view_positions[m, i, j, a]
                    range_out[m, i, j] = rec_range[t, m, j]
                    az_out[m, i, j] = rec_az[t, m, j]
                    el_out[m, i, j] = rec_el[t, m, j]
                    los_out[m, i, j] = view_los[m, i, j]
                else:
                    for a in range(3):
                        pos_out[m, i, j, a] = nan
                    range_out[m, i, j] = nan
                    az_out[m, i, j] = nan
                    el_out[m, i, j] = nan
                    los_out[m, i, j] = False


@njit(cache=True)
def late_record_count(late_steps):  # pragma: no cover - compiled
    """The largest number of late records (steps ≥ 0) any drone receives: late_steps (W, M, N, N)
    int64, the steps of the records first delivered after a newer one (−1 elsewhere)."""
    W, M, N = late_steps.shape[0], late_steps.shape[1], late_steps.shape[2]
    most = 0
    for m in range(M):
        for i in range(N):
            count = 0
            for w in range(W):
                for j in range(N):
                    count += late_steps[w, m, i, j] >= 0
            most = max(most, count)
    return most


@njit(cache=True)
def gather_late_records(
    late_steps, positions, rec_range, rec_az, rec_el, rec_los, pos_out, range_out, az_out, el_out, los_out
):  # pragma: no cover - compiled
    """Each drone's late records, oldest window slot first, then by sender; NaN (False) after
    them: late_steps (W, M, N, N) int64 (−1: none); positions (K+1, M, N, 3), rec_range, rec_az,
    rec_el (K, M, N), rec_los (K, M, N) bool the records; outputs pos_out (M, N, L, 3),
    range_out, az_out, el_out (M, N, L), los_out (M, N, L) bool, L ≥ :func:`late_record_count`.
    """
    W, M, N = late_steps.shape[0], late_steps.shape[1], late_steps.shape[2]
    L = range_out.shape[2]
    nan = np.nan
    for m in range(M):
        for i in range(N):
            c = 0
            for w in range(W):
                for j in range(N):
                    s = late_steps[w, m, i, j]
                    if s >= 0:
                        for a in range(3):
                            pos_out[m, i, c, a] = positions[s, m, j, a]
                        range_out[m, i, c] = rec_range[s, m, j]
                        az_out[m, i, c] = rec_az[s, m, j]
                        el_out[m, i, c] = rec_el[s, m, j]
                        los_out[m, i, c] = rec_los[s, m, j]
                        c += 1
            for r in range(c, L):
                for a in range(3):
                    pos_out[m, i, r, a] = nan
                range_out[m, i, r] = nan
                az_out[m, i, r] = nan
                el_out[m, i, r] = nan
                los_out[m, i, r] = False


@njit(cache=True)
def nearest_peer_distance(positions, out):  # pragma: no cover - compiled
    """Distance (m) from each drone to its nearest peer, +inf alone: positions (K, M, N, 3),
    out (K, M, N); sqrt(Δx² + Δy² + Δz²), the sum in that order (as numpy's)."""
    K, M, N = positions.shape[0], positions.shape[1], positions.shape[2]
    for k in range(K):
        for m in range(M):
            for i in range(N):
                best = math.inf
                for j in range(N):
                    if j != i:
                        dx = positions[k, m, i, 0] - positions[k, m, j, 0]
                        dy = positions[k, m, i, 1] - positions[k, m, j, 1]
                        dz = positions[k, m, i, 2] - positions[k, m, j, 2]
                        best = min(best, math.sqrt(dx * dx + dy * dy + dz * dz))
                out[k, m, i] = best


@njit(cache=True)
def same_views(saved, first):  # pragma: no cover - compiled
    """For each drone's view, the first drone of its trial holding the same records.

    saved (M, N, N) int64, the step of drone i's record of drone j (−1: none); first (M, N) int64
    out: the smallest i' with ``saved[m, i'] == saved[m, i]`` (i itself when none before it).
    Two such views hold the same records, so every quantity of the view (its FIM, its PEB) is
    the same: a swarm within one hop of itself has one view per trial.
    """
    M, N = saved.shape[0], saved.shape[1]
    for m in range(M):
        for i in range(N):
            first[m, i] = i
            for r in range(i):
                if first[m, r] != r:
                    continue
                same = True
                for j in range(N):
                    if saved[m, r, j] != saved[m, i, j]:
                        same = False
                        break
                if same:
                    first[m, i] = r
                    break


#: Lower bound of λ_min/λ_max (4 det J / (tr J)³) above which :func:`position_error_bounds`
#: takes J⁻¹'s trace from the cofactors: far from singular (1e-12) and ill-conditioned (1e-8)
#: alike, and well conditioned enough (cond J ≤ 1e4) that the cofactors and the LU inverse of
#: :func:`planner.fim.position_error_bound` agree to ~1e-12 relative.
WELL_CONDITIONED_BOUND: float = 1e-4


@njit(cache=True)
def position_error_bounds(J, peb, checked):  # pragma: no cover - compiled
    """PEB = sqrt(tr J⁻¹) (eq. 18, m) of the FIMs J (B, 3, 3) that are provably well conditioned.

    For symmetric positive semi-definite J, λ_max ≤ tr J and λ_mid λ_max ≤ (tr J / 2)², so
    λ_min/λ_max ≥ 4 det J / (tr J)³. Where that bound exceeds :data:`WELL_CONDITIONED_BOUND`,
    ``peb[b]`` = sqrt((sum of the principal 2×2 minors) / det J) and ``checked[b]`` False; elsewhere
    (near-singular, non-finite, not positive) ``checked[b]`` is True and ``peb[b]`` is left for
    :func:`planner.fim.position_error_bound` (its eigenvalue check decides singular views).
    """
    for b in range(J.shape[0]):
        a, bb, c = J[b, 0, 0], J[b, 0, 1], J[b, 0, 2]
        d, e, f = J[b, 1, 1], J[b, 1, 2], J[b, 2, 2]
        c00 = d * f - e * e
        c11 = a * f - c * c
        c22 = a * d - bb * bb
        det = a * c00 - bb * (bb * f - c * e) + c * (bb * e - d * c)
        tr = a + d + f
        ok = (tr > 0.0) & (det > 0.0) & math.isfinite(tr) & math.isfinite(det)
        ok = ok and 4.0 * det > WELL_CONDITIONED_BOUND * tr * tr * tr
        if ok:
            peb[b] = math.sqrt((c00 + c11 + c22) / det)
        checked[b] = not ok


__all__ = [
    "gather_late_records",
    "gather_new_records",
    "gather_view",
    "hop_counts",
    "late_record_count",
    "line_of_sight",
    "nearest_peer_distance",
    "position_error_bounds",
    "same_views",
    "update_saved_steps",
]


# The entry kernels built ahead of time, when they are (planner.aot): bound here, at import.
from planner.aot import bind as _bind  # noqa: E402

_bind("simulator", globals())

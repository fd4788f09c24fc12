r"""Compiled range memory (one batch element at a time; :mod:`planner.estimator.memory` has
the model and the public wrappers): forgetting, insertion of ranges into cells, and the exact
negative log-likelihood of every range, its gradient and Fisher information, its polishing and
the search for another basin.

The memory of one element is an array (C, :data:`~planner.estimator.layout.NM`) of cells
(Σwp, n, S1, S2, σ_r0, T, Q). For evaluation, :func:`cells_of` lists its occupied cells as
rows (centre p̄, n, S1, S2, σ_r0², lever T − S1 p̄, spread Q − n‖p̄‖²); an empty cell adds
exactly nothing to any sum, so the sums run over the occupied cells only, in cell order.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from planner.estimator.kernels.linalg import clip, eigh, nmax, solve3
from planner.estimator.layout import M_N, M_PS, M_Q, M_S0, M_S1, M_S2, M_T, P_HI, P_LO

#: Weight below which a cell counts as empty.
EMPTY = 1e-6

# Columns of the occupied cells (cells_of).
C_X, C_N, C_S1, C_S2, C_S0SQ, C_L, C_SP = 0, 3, 4, 5, 6, 7, 10
NC = 11


@njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True)
def forget(mem: np.ndarray, lam: float, out: np.ndarray) -> None:
    """``out`` = the cells of ``mem`` with every sum times λ (σ_r0 kept)."""
    for c in range(mem.shape[0]):
        for j in range(mem.shape[1]):
            out[c, j] = mem[c, j] if (j == M_S0 or lam == 1.0) else mem[c, j] * lam


@njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True)
def cells_of(mem: np.ndarray, cells: np.ndarray) -> int:
    """Fill ``cells`` (≥ C, NC) with the occupied cells of ``mem`` (C, NM), in order; returns
    their count."""
    k = 0
    for c in range(mem.shape[0]):
        n = mem[c, M_N]
        if n < EMPTY:
            continue
        s1 = mem[c, M_S1]
        cx, cy, cz = mem[c, M_PS] / n, mem[c, M_PS + 1] / n, mem[c, M_PS + 2] / n
        cells[k, C_X], cells[k, C_X + 1], cells[k, C_X + 2] = cx, cy, cz
        cells[k, C_N] = n
        cells[k, C_S1] = s1
        cells[k, C_S2] = mem[c, M_S2]
        cells[k, C_S0SQ] = mem[c, M_S0] ** 2
        cells[k, C_L] = mem[c, M_T] - s1 * cx
        cells[k, C_L + 1] = mem[c, M_T + 1] - s1 * cy
        cells[k, C_L + 2] = mem[c, M_T + 2] - s1 * cz
        cells[k, C_SP] = nmax(mem[c, M_Q] - n * (cx * cx + cy * cy + cz * cz), 0.0)
        k += 1
    return k


@njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True)
def _terms(cells: np.ndarray, c: int, x0: float, x1: float, x2: float, gamma: float) -> tuple[float, float, float, float, float, float]:
    """Cell c at x: distance d (floored at 1 mm), unit vector u, variance σ_r0² d^γ and the
    residual sum S2 − 2(S1 d − u·lever) + n d² + spread."""
    r0, r1, r2 = x0 - cells[c, C_X], x1 - cells[c, C_X + 1], x2 - cells[c, C_X + 2]
    d = nmax(math.sqrt(r0 * r0 + r1 * r1 + r2 * r2), 1e-3)
    u0, u1, u2 = r0 / d, r1 / d, r2 / d
    var = cells[c, C_S0SQ] * (d * d if gamma == 2.0 else d**gamma)
    ul = u0 * cells[c, C_L] + u1 * cells[c, C_L + 1] + u2 * cells[c, C_L + 2]
    resid2 = cells[c, C_S2] - 2.0 * (d * cells[c, C_S1] - ul) + cells[c, C_N] * d * d + cells[c, C_SP]
    return d, u0, u1, u2, var, resid2


@njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True)
def nll(cells: np.ndarray, nc: int, x0: float, x1: float, x2: float, gamma: float) -> float:
    """Σ_cells resid2/(2 var) + (nγ/2) ln d at x: the memory's negative log-likelihood."""
    total = 0.0
    for c in range(nc):
        d, _, _, _, var, resid2 = _terms(cells, c, x0, x1, x2, gamma)
        total += 0.5 * resid2 / var + 0.5 * gamma * cells[c, C_N] * math.log(d)
    return total


@njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True)
def gradient_fisher(cells: np.ndarray, nc: int, x: np.ndarray, gamma: float, full: bool, g: np.ndarray, F: np.ndarray) -> None:
    """``g`` (3,) and ``F`` (3, 3): gradient and Fisher information of the memory's cost at x,
    of the full likelihood (``full``) or of the generalised LS cost with σ_r² held at x."""
    f = np.zeros(6)  # xx, yy, zz, xy, yz, xz
    g[0] = g[1] = g[2] = 0.0
    for c in range(nc):
        d, u0, u1, u2, var, resid2 = _terms(cells, c, x[0], x[1], x[2], gamma)
        n = cells[c, C_N]
        dfd = (n * d - cells[c, C_S1]) / var
        info = n / var
        if full:
            dfd = dfd - 0.5 * gamma * resid2 / (var * d) + 0.5 * gamma * n / d
            info = info + 0.5 * n * (gamma / d) ** 2
        vd = var * d
        l0, l1, l2 = cells[c, C_L] / vd, cells[c, C_L + 1] / vd, cells[c, C_L + 2] / vd
        radial = dfd - (u0 * l0 + u1 * l1 + u2 * l2)
        g[0] += radial * u0 + l0
        g[1] += radial * u1 + l1
        g[2] += radial * u2 + l2
        w0, w1 = info * u0, info * u1
        f[0] += w0 * u0
        f[1] += w1 * u1
        f[2] += info * u2 * u2
        f[3] += w0 * u1
        f[4] += w1 * u2
        f[5] += w0 * u2
    F[0, 0], F[1, 1], F[2, 2] = f[0], f[1], f[2]
    F[0, 1] = F[1, 0] = f[3]
    F[1, 2] = F[2, 1] = f[4]
    F[0, 2] = F[2, 0] = f[5]


@njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True)
def polish(cells: np.ndarray, nc: int, x: np.ndarray, gamma: float, p: np.ndarray, iterations: int, tolerance: float) -> float:
    """Projected Fisher-scoring (Levenberg-Marquardt) minimisation of :func:`nll` from x (3,),
    in place, inside the search box of ``p``; a step is kept only if the cost does not
    increase; stops after ``iterations`` or once a projected step is shorter than
    ``tolerance`` (m). Returns the cost at x."""
    cost = nll(cells, nc, x[0], x[1], x[2], gamma)
    mu = 1e-3
    g, step, cand = np.empty(3), np.empty(3), np.empty(3)
    F, H = np.empty((3, 3)), np.empty((3, 3))
    free = np.empty(3, dtype=np.bool_)
    for _ in range(iterations):
        gradient_fisher(cells, nc, x, gamma, np.bool_(True), g, F)
        for i in range(3):
            s = 0.0 if g[i] == 0.0 else (1.0 if g[i] > 0.0 else -1.0)
            if g[i] != g[i]:
                s = g[i]
            free[i] = clip(x[i] - 1e-6 * s, p[P_LO + i], p[P_HI + i]) != x[i]
        for i in range(3):
            for j in range(3):
                H[i, j] = F[i, j] if (free[i] and free[j]) else 0.0
            if not free[i]:
                g[i] = 0.0
        tr = H[0, 0] + H[1, 1] + H[2, 2]
        for i in range(3):
            H[i, i] = H[i, i] + (mu * H[i, i] + 1e-9 * tr + 1e-12) + (0.0 if free[i] else 1.0)
        solve3(H, g, step)
        live, nan = False, False
        for i in range(3):
            cand[i] = clip(x[i] - step[i], p[P_LO + i], p[P_HI + i])
            moved = abs(cand[i] - x[i])
            nan = nan or moved != moved
            live = live or moved > tolerance
        live = live and not nan  # numpy's max over the coordinates is NaN then
        c_new = nll(cells, nc, cand[0], cand[1], cand[2], gamma)
        if np.isfinite(c_new) and c_new <= cost:
            x[0], x[1], x[2] = cand[0], cand[1], cand[2]
            cost = c_new
            mu = mu / 3.0
        else:
            mu = mu * 4.0
        if not live:
            break
    return cost


@njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True)
def best_start(cells: np.ndarray, nc: int, x: np.ndarray, cand: np.ndarray, gamma: float, p: np.ndarray, points: int, out: np.ndarray) -> None:
    """``out``: of ``cand`` and of ``points`` points on the line through x along the memory's
    least-informed direction (within ± the mean distance from x to the cells, in the search
    box), the one of lowest :func:`nll` (the first of equal ones)."""
    g, F = np.empty(3), np.empty((3, 3))
    gradient_fisher(cells, nc, x, gamma, np.bool_(False), g, F)
    w, vecs = np.empty(3), np.empty((3, 3))
    eigh(F, w, vecs)
    reach = 0.0
    for c in range(nc):
        r0, r1, r2 = x[0] - cells[c, C_X], x[1] - cells[c, C_X + 1], x[2] - cells[c, C_X + 2]
        reach += math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
    reach = reach / max(nc, 1)
    step = 2.0 / (points - 1)
    best = np.inf
    pt = np.empty(3)
    for k in range(points + 1):
        if k < points:
            t = 1.0 if k == points - 1 else k * step - 1.0
            for i in range(3):
                pt[i] = clip(x[i] + (t * reach) * vecs[i, 0], p[P_LO + i], p[P_HI + i])
        else:
            pt[0], pt[1], pt[2] = cand[0], cand[1], cand[2]
        cost = nll(cells, nc, pt[0], pt[1], pt[2], gamma)
        if k == 0 or (np.isfinite(cost) and cost < best):  # the first point if none is finite
            best = cost if np.isfinite(cost) else np.inf
            out[0], out[1], out[2] = pt[0], pt[1], pt[2]


@njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True)
def _nearest(mem: np.ndarray, cc: np.ndarray, pos: np.ndarray, m: int, sig: float) -> tuple[int, float, int]:
    """The occupied cell nearest to row m's position of σ_r0 ``sig`` and its squared distance
    ‖p̄‖² − 2p̄·p + ‖p‖² (floored at 0), (0, inf) if there is none; and the nearest occupied
    cell of any σ_r0 (0 if none). The first of equally near cells."""
    best, bd, near, nd = 0, np.inf, 0, np.inf
    px, py, pz = pos[m, 0], pos[m, 1], pos[m, 2]
    pp = px * px + py * py + pz * pz
    for c in range(mem.shape[0]):
        if mem[c, M_N] < EMPTY:
            continue
        d2 = nmax(cc[c, 3] - 2.0 * (cc[c, 0] * px + cc[c, 1] * py + cc[c, 2] * pz) + pp, 0.0)
        if d2 < nd:
            near, nd = c, d2
        if mem[c, M_S0] == sig and d2 < bd:
            best, bd = c, d2
    return best, bd, near


@njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True)
def _cells_of_rows(mem: np.ndarray, pos: np.ndarray, rng: np.ndarray, w: np.ndarray, sig: np.ndarray, rf: float, cell: np.ndarray) -> None:
    """The cell of every row with a positive weight (:func:`insert`'s rule; −1: no row), and
    σ_r0 set on the empty cells that the first row of each new group takes."""
    C, M = mem.shape[0], rng.shape[0]
    cc = np.empty((C, 4))  # centre and its squared norm
    n_empty = np.int64(0)
    for c in range(C):
        n = mem[c, M_N]
        full = n >= EMPTY
        n_empty += 0 if full else 1
        safe = n if full else 1.0
        for i in range(3):
            cc[c, i] = mem[c, M_PS + i] / safe
        cc[c, 3] = cc[c, 0] * cc[c, 0] + cc[c, 1] * cc[c, 1] + cc[c, 2] * cc[c, 2]
    fresh = np.zeros(M, dtype=np.bool_)
    fallback = np.zeros(M, dtype=np.int64)
    for m in range(M):
        cell[m] = -1
        if not w[m] > 0.0:
            continue
        best, d_same, near = _nearest(mem, cc, pos, m, sig[m])
        radius = rf * nmax(abs(mem[best, M_S1]) / mem[best, M_N], 1.0) if np.isfinite(d_same) else 0.0
        if d_same <= radius * radius:
            cell[m] = best
        else:
            fresh[m] = True
            fallback[m] = best if np.isfinite(d_same) else near
    _group(mem, pos, rng, sig, rf, fresh, fallback, n_empty, cell)


@njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True)
def _group(
    mem: np.ndarray,
    pos: np.ndarray,
    rng: np.ndarray,
    sig: np.ndarray,
    rf: float,
    fresh: np.ndarray,
    fallback: np.ndarray,
    n_empty: int,
    cell: np.ndarray,
) -> None:
    """The rows that joined no cell (``fresh``): a row within reach of an earlier such row of
    its σ_r0 shares that row's cell (the first row that reaches it, followed to the group's
    first row); the first row of each group takes an empty cell, in row order, while any is
    left; the others' rows take their ``fallback`` cell."""
    C, M = mem.shape[0], rng.shape[0]
    leader = np.zeros(M, dtype=np.int64)
    for j in range(M):
        for i in range(j + 1):
            if fresh[i] and fresh[j] and sig[i] == sig[j]:
                dx, dy, dz = pos[i, 0] - pos[j, 0], pos[i, 1] - pos[j, 1], pos[i, 2] - pos[j, 2]
                if math.sqrt(dx * dx + dy * dy + dz * dz) <= rf * nmax(abs(rng[i]), 1.0):
                    leader[j] = i
                    break
    jumped = np.empty(M, dtype=np.int64)
    for _ in range(max(1, int(math.ceil(math.log2(M))) + 1)):  # follow chains to their first row
        for j in range(M):
            jumped[j] = leader[leader[j]]
        for j in range(M):
            leader[j] = jumped[j]
    empty_ids = np.empty(C, dtype=np.int64)
    k = 0
    for c in range(C):
        if mem[c, M_N] < EMPTY:
            empty_ids[k] = c
            k += 1
    rank = 0
    took = np.full(M, -1, dtype=np.int64)  # the empty cell a group's first row takes
    for m in range(M):
        if fresh[m] and leader[m] == m:
            if rank < n_empty:
                took[m] = empty_ids[rank]
                mem[took[m], M_S0] = sig[m]
            rank += 1
    for m in range(M):
        if fresh[m]:
            cell[m] = took[leader[m]] if took[leader[m]] >= 0 else fallback[m]


@njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True)
def insert(mem: np.ndarray, pos: np.ndarray, rng: np.ndarray, w: np.ndarray, sig: np.ndarray, rf: float) -> None:
    """Add the ranges ``rng`` (M,), m, taken at ``pos`` (M, 3), m, ENU, with weights ``w`` (M,)
    (0: absent) and σ_r0 ``sig`` (M,), to the cells ``mem`` (C, NM), in place (the rule of
    :func:`planner.estimator.memory.insert`, against the cells as they were before the call).
    Each cell's sums grow by the sum of its rows' terms, in row order."""
    C, M = mem.shape[0], rng.shape[0]
    if C == 0 or M == 0:
        return
    cell = np.empty(M, dtype=np.int64)
    _cells_of_rows(mem, pos, rng, w, sig, rf, cell)
    inc = np.zeros((C, 10))  # n, S1, S2, Q, Σwp, T
    for m in range(M):
        c = cell[m]
        if c < 0:
            continue
        wv, dv = w[m], rng[m]
        px, py, pz = pos[m, 0], pos[m, 1], pos[m, 2]
        inc[c, 0] += wv
        inc[c, 1] += wv * dv
        inc[c, 2] += wv * dv * dv
        inc[c, 3] += wv * (px * px + py * py + pz * pz)
        for i in range(3):
            inc[c, 4 + i] += wv * pos[m, i]
            inc[c, 7 + i] += wv * dv * pos[m, i]
    for c in range(C):
        if inc[c, 0] != 0.0 or inc[c, 1] != 0.0:
            mem[c, M_N] += inc[c, 0]
            mem[c, M_S1] += inc[c, 1]
            mem[c, M_S2] += inc[c, 2]
            mem[c, M_Q] += inc[c, 3]
            for i in range(3):
                mem[c, M_PS + i] += inc[c, 4 + i]
                mem[c, M_T + i] += inc[c, 7 + i]


# --------------------------------------------------------------------------- batch entry points
@njit(cache=True, error_model="numpy")
def insert_batch(mem: np.ndarray, pos: np.ndarray, rng: np.ndarray, w: np.ndarray, sig: np.ndarray, rf: float) -> np.ndarray:
    """:func:`insert` for every element of a batch (E, C, NM) of memories; returns new cells."""
    out = mem.copy()
    for e in range(mem.shape[0]):
        insert(out[e], pos[e], rng[e], w[e], sig[e], rf)
    return out


@njit(cache=True, error_model="numpy")
def cells_batch(mem: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The occupied cells of every memory (E, C, NM): (E, C, NC) (empty rows: n = 0, σ_r0² = 1)
    and their counts (E,)."""
    E, C = mem.shape[0], mem.shape[1]
    cells = np.zeros((E, C, NC))
    counts = np.zeros(E, dtype=np.int64)
    for e in range(E):
        counts[e] = cells_of(mem[e], cells[e])
        cells[e, counts[e] :, C_S0SQ] = 1.0
    return cells, counts


@njit(cache=True, error_model="numpy")
def evaluate_batch(mem: np.ndarray, x: np.ndarray, gamma: float, full: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """At points x (P, 3), point k on memory k mod E of ``mem`` (E, C, NM): :func:`nll` (P,),
    :func:`gradient_fisher` (P, 3), (P, 3, 3) (``full``: of the likelihood)."""
    E, C, P = mem.shape[0], mem.shape[1], x.shape[0]
    cells = np.empty((E, C, NC))
    counts = np.empty(E, dtype=np.int64)
    for e in range(E):
        counts[e] = cells_of(mem[e], cells[e])
    cost, g, F = np.empty(P), np.empty((P, 3)), np.empty((P, 3, 3))
    for k in range(P):
        e = k % E
        cost[k] = nll(cells[e], counts[e], x[k, 0], x[k, 1], x[k, 2], gamma)
        gradient_fisher(cells[e], counts[e], x[k], gamma, full, g[k], F[k])
    return cost, g, F


@njit(cache=True, error_model="numpy")
def polish_batch(mem: np.ndarray, x: np.ndarray, gamma: float, p: np.ndarray, iterations: int, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`polish` from points x (P, 3), point k on memory k mod E; the search box in ``p``."""
    E, C, P = mem.shape[0], mem.shape[1], x.shape[0]
    cells = np.empty((C, NC))
    out, cost = x.copy(), np.empty(P)
    for k in range(P):
        nc = cells_of(mem[k % E], cells)
        cost[k] = polish(cells, nc, out[k], gamma, p, iterations, tolerance)
    return out, cost


@njit(cache=True, error_model="numpy")
def best_start_batch(mem: np.ndarray, x: np.ndarray, cand: np.ndarray, gamma: float, p: np.ndarray, points: int) -> np.ndarray:
    """:func:`best_start` for every element (E, C, NM), x and cand (E, 3)."""
    E, C = mem.shape[0], mem.shape[1]
    cells = np.empty((C, NC))
    out = np.empty((E, 3))
    for e in range(E):
        nc = cells_of(mem[e], cells)
        best_start(cells, nc, x[e], cand[e], gamma, p, points, out[e])
    return out

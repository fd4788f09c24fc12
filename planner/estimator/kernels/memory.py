r"""Compiled range memory (one batch element at a time; :mod:`planner.estimator.memory` has
the model and the public wrappers): forgetting, insertion of ranges into cells, and the exact
negative log-likelihood of every range, its gradient and Fisher information, its polishing and
the search for another basin.

The memory of one element is an array (:data:`~planner.estimator.layout.NM`, C), one row per
quantity and one column per cell (structure of arrays: every pass over the cells reads
contiguous rows). The rows ``M_PS`` .. ``M_Q`` hold the sums (Σwp, n, S1, S2, σ_r0, T, Q) that
an insertion adds to; the rows from ``M_CX`` on hold what an evaluation reads, kept up to date
for every cell an insertion or the forgetting changes (:func:`refresh`): centre p̄, σ_r0², lever
T − S1 p̄, spread Q − n‖p̄‖², ‖p̄‖², and n, S1, S2 again, all 0 for an empty cell (n < 1e-6),
so that an empty cell adds exactly nothing to any sum. Cells are taken in index order and a
cell beyond the last occupied one is empty: the passes run over the first ``used`` cells
(:func:`used_cells`).

The passes over the cells (:func:`evaluate`) compute the distances and their logarithms in
separate loops and sum with ``fastmath`` reassociation, so that the compiler vectorises them:
the sums' order depends on the machine's vector width (not on the batch).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from planner.estimator.kernels.linalg import borrowing, clip, counting, eigh, nmax, solve3_in_place
from planner.estimator.layout import (
    M_CC,
    M_CX,
    M_EN,
    M_ES1,
    M_ES2,
    M_L,
    M_N,
    M_PS,
    M_Q,
    M_S0,
    M_S0SQ,
    M_S1,
    M_S2,
    M_SP,
    M_T,
    NM,
    P_HI,
    P_LO,
)

#: Weight below which a cell counts as empty.
EMPTY = 1e-6

#: Rows of the pass scratch (:func:`evaluate`): distance floored at 1 mm, its log, raw
#: distance, variance σ_r0² d^γ, the logarithm's mantissas.
NSC = 5

_FAST = {"reassoc", "contract"}


@borrowing
def refresh(mem: np.ndarray, c: int) -> None:
    """The evaluation rows of cell c from its sums: centre Σwp/n, σ_r0², lever T − S1 p̄, spread
    max(Q − n‖p̄‖², 0), ‖p̄‖², n, S1, S2; zeros (σ_r0² kept) for an empty cell."""
    n = mem[M_N, c]
    mem[M_S0SQ, c] = mem[M_S0, c] ** 2
    if n < EMPTY:
        for r in (M_CX, M_CX + 1, M_CX + 2, M_L, M_L + 1, M_L + 2, M_SP, M_CC, M_EN, M_ES1, M_ES2):
            mem[r, c] = 0.0
        return
    s1 = mem[M_S1, c]
    cx, cy, cz = mem[M_PS, c] / n, mem[M_PS + 1, c] / n, mem[M_PS + 2, c] / n
    mem[M_CX, c], mem[M_CX + 1, c], mem[M_CX + 2, c] = cx, cy, cz
    mem[M_L, c] = mem[M_T, c] - s1 * cx
    mem[M_L + 1, c] = mem[M_T + 1, c] - s1 * cy
    mem[M_L + 2, c] = mem[M_T + 2, c] - s1 * cz
    mem[M_SP, c] = nmax(mem[M_Q, c] - n * (cx * cx + cy * cy + cz * cz), 0.0)
    mem[M_CC, c] = cx * cx + cy * cy + cz * cz
    mem[M_EN, c], mem[M_ES1, c], mem[M_ES2, c] = n, s1, mem[M_S2, c]


@borrowing
def used_cells(mem: np.ndarray) -> int:
    """1 + the index of the last occupied cell (0 if none)."""
    for c in range(mem.shape[1] - 1, -1, -1):
        if mem[M_N, c] >= EMPTY:
            return c + 1
    return 0


@borrowing
def occupied(mem: np.ndarray, nc: int) -> int:
    """The number of occupied cells among the first nc."""
    k = 0
    for c in range(nc):
        k += 1 if mem[M_N, c] >= EMPTY else 0
    return k


@borrowing
def forget(mem: np.ndarray, lam: float) -> None:
    """Every sum of every cell times λ (σ_r0 kept), in place, and the cells refreshed."""
    if lam == 1.0:
        return
    for r in range(M_PS, M_Q + 1):
        if r != M_S0:
            for c in range(mem.shape[1]):
                mem[r, c] *= lam
    for c in range(mem.shape[1]):
        refresh(mem, c)


# fdlibm's log (e_log.c): ln x = k ln2 + ln(1 + f), √2/2 ≤ 1 + f < √2, within 1 ulp.
_LN2_HI, _LN2_LO = 6.93147180369123816490e-01, 1.90821492927058770002e-10
_LG1, _LG2, _LG3, _LG4 = 6.666666666666735130e-01, 3.999999999940941908e-01, 2.857142874366239149e-01, 2.222219843214978396e-01
_LG5, _LG6, _LG7 = 1.818357216161805012e-01, 1.531383769920937332e-01, 1.479819860511658591e-01


@borrowing(fastmath=_FAST)
def _logs(sc: np.ndarray, nc: int) -> None:
    """sc[1, c] = ln sc[0, c] for c < nc (positive values; inf and NaN kept), fdlibm's
    algorithm written over arrays so that the compiler vectorises it (a call of the C
    library's log per value is the passes' largest cost otherwise); sc[4] scratch."""
    bits = sc.view(np.int64)
    for c in range(nc):
        hx = bits[0, c]
        mant = hx & 0x000FFFFFFFFFFFFF
        i = (mant + 0x00095F6400000000) & 0x0010000000000000
        bits[4, c] = mant | (i ^ 0x3FF0000000000000)  # 1 + f
        sc[1, c] = float((hx >> 52) - 1023 + (i >> 52))  # k
    for c in range(nc):
        f = sc[4, c] - 1.0
        dk = sc[1, c]
        s = f / (2.0 + f)
        z = s * s
        w = z * z
        t1 = w * (_LG2 + w * (_LG4 + w * _LG6))
        t2 = z * (_LG1 + w * (_LG3 + w * (_LG5 + w * _LG7)))
        hfsq = 0.5 * f * f
        r = dk * _LN2_HI - ((hfsq - (s * (hfsq + (t2 + t1)) + dk * _LN2_LO)) - f)
        x = sc[0, c]
        sc[1, c] = r if x < 1.7976931348623157e308 else x


@borrowing(fastmath=_FAST)
def _distances(mem: np.ndarray, nc: int, x0: float, x1: float, x2: float, gamma: float, sc: np.ndarray, logs: bool) -> None:
    """sc[0] = d = max(‖x − p̄_c‖, 1 mm), sc[2] the distance itself, sc[3] the variance
    σ_r0² d^γ, sc[1] = ln d if ``logs`` (loops the compiler vectorises)."""
    for c in range(nc):
        r0, r1, r2 = x0 - mem[M_CX, c], x1 - mem[M_CX + 1, c], x2 - mem[M_CX + 2, c]
        s = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
        sc[2, c] = s
        sc[0, c] = s if s > 1e-3 else 1e-3
    if gamma == 2.0:
        for c in range(nc):
            sc[3, c] = mem[M_S0SQ, c] * (sc[0, c] * sc[0, c])
    else:
        for c in range(nc):
            sc[3, c] = mem[M_S0SQ, c] * sc[0, c] ** gamma
    if logs:
        _logs(sc, nc)


@borrowing(fastmath=_FAST)
def _nll_sum(mem: np.ndarray, nc: int, x0: float, x1: float, x2: float, gamma: float, sc: np.ndarray) -> float:
    """Σ_cells resid2/(2 var) + (nγ/2) ln d from the distances ``sc``."""
    total = 0.0
    for c in range(nc):
        d, var = sc[0, c], sc[3, c]
        ul = ((x0 - mem[M_CX, c]) * mem[M_L, c] + (x1 - mem[M_CX + 1, c]) * mem[M_L + 1, c] + (x2 - mem[M_CX + 2, c]) * mem[M_L + 2, c]) / d
        n = mem[M_EN, c]
        resid2 = mem[M_ES2, c] - 2.0 * (d * mem[M_ES1, c] - ul) + n * d * d + mem[M_SP, c]
        total += 0.5 * resid2 / var + 0.5 * gamma * n * sc[1, c]
    return total


@borrowing(fastmath=_FAST)
def _gradient_sum(
    mem: np.ndarray, nc: int, x0: float, x1: float, x2: float, gamma: float, full: bool, sc: np.ndarray, g: np.ndarray, F: np.ndarray
) -> None:
    """``g``, ``F`` (:func:`evaluate`) from the distances ``sc``."""
    g0 = g1 = g2 = 0.0
    fxx = fyy = fzz = fxy = fyz = fxz = 0.0
    hg = 0.5 * gamma if full else 0.0
    h2 = 0.5 * gamma * gamma if full else 0.0
    for c in range(nc):
        d = sc[0, c]
        inv_d = 1.0 / d
        u0, u1, u2 = (x0 - mem[M_CX, c]) * inv_d, (x1 - mem[M_CX + 1, c]) * inv_d, (x2 - mem[M_CX + 2, c]) * inv_d
        inv_var = 1.0 / sc[3, c]
        n, s1 = mem[M_EN, c], mem[M_ES1, c]
        lx, ly, lz = mem[M_L, c], mem[M_L + 1, c], mem[M_L + 2, c]
        ul = u0 * lx + u1 * ly + u2 * lz
        resid2 = mem[M_ES2, c] - 2.0 * (d * s1 - ul) + n * d * d + mem[M_SP, c]
        dfd = (n * d - s1) * inv_var - hg * resid2 * inv_var * inv_d + hg * n * inv_d
        info = n * inv_var + h2 * n * inv_d * inv_d
        ivd = inv_var * inv_d
        l0, l1, l2 = lx * ivd, ly * ivd, lz * ivd
        radial = dfd - (u0 * l0 + u1 * l1 + u2 * l2)
        g0 += radial * u0 + l0
        g1 += radial * u1 + l1
        g2 += radial * u2 + l2
        w0, w1 = info * u0, info * u1
        fxx += w0 * u0
        fyy += w1 * u1
        fzz += info * u2 * u2
        fxy += w0 * u1
        fyz += w1 * u2
        fxz += w0 * u2
    g[0], g[1], g[2] = g0, g1, g2
    F[0, 0], F[1, 1], F[2, 2] = fxx, fyy, fzz
    F[0, 1] = F[1, 0] = fxy
    F[1, 2] = F[2, 1] = fyz
    F[0, 2] = F[2, 0] = fxz


@borrowing
def nll(mem: np.ndarray, nc: int, x0: float, x1: float, x2: float, gamma: float, sc: np.ndarray) -> float:
    """Σ_cells resid2/(2 var) + (nγ/2) ln d at x over the first nc cells: the memory's negative
    log-likelihood (the residual sum S2 − 2(S1 d − u·lever) + n d² + spread, variance σ_r0² d^γ
    at the centre, d floored at 1 mm). ``sc`` (NSC, ≥ nc) scratch."""
    _distances(mem, nc, x0, x1, x2, gamma, sc, True)
    return _nll_sum(mem, nc, x0, x1, x2, gamma, sc)


@borrowing
def evaluate(mem: np.ndarray, nc: int, x: np.ndarray, gamma: float, full: bool, sc: np.ndarray, g: np.ndarray, F: np.ndarray) -> float:
    """``g`` (3,) and ``F`` (3, 3): gradient and Fisher information of the memory's cost at x,
    of the full likelihood (``full``: returns its :func:`nll` too, computed by the same code,
    so the same value) or of the generalised LS cost with σ_r² held at x (returns 0)."""
    _distances(mem, nc, x[0], x[1], x[2], gamma, sc, full)
    _gradient_sum(mem, nc, x[0], x[1], x[2], gamma, full, sc, g, F)
    return _nll_sum(mem, nc, x[0], x[1], x[2], gamma, sc) if full else 0.0


@borrowing
def _polish_step(
    x: np.ndarray, g: np.ndarray, F: np.ndarray, mu: float, p: np.ndarray, tolerance: float, cand: np.ndarray, H: np.ndarray, step: np.ndarray
) -> bool:
    """``cand``: the damped projected Fisher-scoring step from x (coordinates on the box face
    that the gradient pushes against held); returns whether it moves by more than
    ``tolerance`` (m) (False if it is not finite). ``H`` (3, 3) and ``step`` (3,) scratch."""
    free = 0  # bit i: coordinate i free
    for i in range(3):
        s = 0.0 if g[i] == 0.0 else (1.0 if g[i] > 0.0 else -1.0)
        if g[i] != g[i]:
            s = g[i]
        if clip(x[i] - 1e-6 * s, p[P_LO + i], p[P_HI + i]) != x[i]:
            free |= 1 << i
    for i in range(3):
        for j in range(3):
            H[i, j] = F[i, j] if ((free >> i) & (free >> j) & 1) else 0.0
        step[i] = g[i] if (free >> i) & 1 else 0.0
    tr = H[0, 0] + H[1, 1] + H[2, 2]
    for i in range(3):
        H[i, i] = H[i, i] + (mu * H[i, i] + 1e-9 * tr + 1e-12) + (0.0 if (free >> i) & 1 else 1.0)
    solve3_in_place(H, step)
    live, nan = False, False
    for i in range(3):
        cand[i] = clip(x[i] - step[i], p[P_LO + i], p[P_HI + i])
        moved = abs(cand[i] - x[i])
        nan = nan or moved != moved
        live = live or moved > tolerance
    return live and not nan  # numpy's max over the coordinates is NaN then


@counting
def polish(
    mem: np.ndarray, nc: int, x: np.ndarray, gamma: float, p: np.ndarray, iterations: int, tolerance: float, sc: np.ndarray
) -> tuple[float, float]:
    """Projected Fisher-scoring (Levenberg-Marquardt) minimisation of :func:`nll` from x (3,),
    in place, inside the search box of ``p``; a step is kept only if the cost does not
    increase; stops after ``iterations`` or once a projected step is shorter than
    ``tolerance`` (m). One pass over the cells per iteration (the cost, gradient and Fisher
    information at the candidate together; a rejected step re-uses those at x). Returns the
    cost at x and the cost where it started."""
    g, F, gc, Fc, cand = np.empty(3), np.empty((3, 3)), np.empty(3), np.empty((3, 3)), np.empty(3)
    H, step = np.empty((3, 3)), np.empty(3)
    cost = evaluate(mem, nc, x, gamma, np.bool_(True), sc, g, F)
    start = cost
    mu = 1e-3
    for _ in range(iterations):
        live = _polish_step(x, g, F, mu, p, tolerance, cand, H, step)
        c_new = evaluate(mem, nc, cand, gamma, np.bool_(True), sc, gc, Fc) if live else nll(mem, nc, cand[0], cand[1], cand[2], gamma, sc)
        if np.isfinite(c_new) and c_new <= cost:
            x[0], x[1], x[2] = cand[0], cand[1], cand[2]
            cost = c_new
            mu = mu / 3.0
            for i in range(3):
                g[i] = gc[i]
                for j in range(3):
                    F[i, j] = Fc[i, j]
        else:
            mu = mu * 4.0
        if not live:
            break
    return cost, start


@counting
def best_start(
    mem: np.ndarray, nc: int, x: np.ndarray, cand: np.ndarray, gamma: float, p: np.ndarray, points: int, sc: np.ndarray, out: np.ndarray
) -> None:
    """``out``: of ``cand`` and of ``points`` points on the line through x along the memory's
    least-informed direction (within ± the mean distance from x to the occupied cells, in the
    search box), the one of lowest :func:`nll` (the first of equal ones)."""
    g, F = np.empty(3), np.empty((3, 3))
    evaluate(mem, nc, x, gamma, np.bool_(False), sc, g, F)
    w, vecs = np.empty(3), np.empty((3, 3))
    eigh(F, w, vecs)
    reach = 0.0
    for c in range(nc):
        if mem[M_N, c] >= EMPTY:
            reach += sc[2, c]
    reach = reach / max(occupied(mem, nc), 1)
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
        cost = nll(mem, nc, pt[0], pt[1], pt[2], gamma, sc)
        if k == 0 or (np.isfinite(cost) and cost < best):  # the first point if none is finite
            best = cost if np.isfinite(cost) else np.inf
            out[0], out[1], out[2] = pt[0], pt[1], pt[2]


# --------------------------------------------------------------------------- insertion
@borrowing(fastmath={"nnan", "nsz"})
def _least(key: np.ndarray, n: int) -> float:
    """min key[:n] (+inf if n = 0) of values none of which is NaN (the compiler vectorises it
    as a min reduction: exact, whatever the order)."""
    m = np.inf
    for c in range(n):
        v = key[c]
        m = v if v < m else m
    return m


@borrowing
def _nearest(mem: np.ndarray, nc: int, px: float, py: float, pz: float, sig: float, sc: np.ndarray) -> tuple[int, float, int]:
    """The occupied cell nearest to (px, py, pz) of σ_r0 ``sig`` and its squared distance
    ‖p̄‖² − 2p̄·p + ‖p‖² (floored at 0), (0, inf) if there is none; and, only where there is
    none (else the first), the nearest occupied cell of any σ_r0 (0 if none). The first of
    equally near cells. ``sc`` (≥ 2, ≥ nc) scratch: sc[0] the squared distances, inf for the
    empty cells, sc[1] the same, inf for the cells of another σ_r0 and NaN distances, in a loop
    the compiler vectorises; then their least (:func:`_least`) and the first cell that has it."""
    d2, key = sc[0], sc[1]
    pp = px * px + py * py + pz * pz
    for c in range(nc):
        v = mem[M_CC, c] - 2.0 * (mem[M_CX, c] * px + mem[M_CX + 1, c] * py + mem[M_CX + 2, c] * pz) + pp
        v = 0.0 if v < 0.0 else v  # NaN kept
        d = np.inf if mem[M_N, c] < EMPTY else v
        d2[c] = d
        key[c] = d if (mem[M_S0, c] == sig and d == d) else np.inf
    bd = _least(key, nc)
    if bd < np.inf:
        best = 0
        while key[best] != bd:
            best += 1
        return best, key[best], best
    near, nd = 0, np.inf
    for c in range(nc):
        if d2[c] < nd:
            near, nd = c, d2[c]
    return 0, np.inf, near


@borrowing
def _group(
    mem: np.ndarray, nc: int, pos: np.ndarray, rng: np.ndarray, sig: np.ndarray, rf: float, fresh: np.ndarray, cell: np.ndarray, iw: np.ndarray
) -> int:
    """The rows that joined no cell (``fresh`` ≠ 0; ``cell`` holds their fallback cell): a row
    within reach of an earlier such row of its σ_r0 shares that row's cell (the first row that
    reaches it, followed to the group's first row); the first row of each group takes an empty
    cell, in index order, while any is left (its σ_r0 set); the others' rows keep their
    fallback. ``iw`` (3, M) int scratch. Returns the new count of used cells."""
    C, M = mem.shape[1], rng.shape[0]
    leader, jumped, took = iw[0], iw[1], iw[2]
    for j in range(M):
        leader[j] = 0
        for i in range(j + 1):
            if fresh[i] != 0 and fresh[j] != 0 and sig[i] == sig[j]:
                dx, dy, dz = pos[i, 0] - pos[j, 0], pos[i, 1] - pos[j, 1], pos[i, 2] - pos[j, 2]
                if math.sqrt(dx * dx + dy * dy + dz * dz) <= rf * nmax(abs(rng[i]), 1.0):
                    leader[j] = i
                    break
    for _ in range(max(1, int(math.ceil(math.log2(M))) + 1)):  # follow chains to their first row
        for j in range(M):
            jumped[j] = leader[leader[j]]
        for j in range(M):
            leader[j] = jumped[j]
    c = 0  # the next empty cell to look at
    used = nc
    for m in range(M):
        took[m] = -1
        if fresh[m] != 0 and leader[m] == m:
            while c < C and mem[M_N, c] >= EMPTY:
                c += 1
            if c < C:
                took[m] = c
                mem[M_S0, c] = sig[m]
                used = max(used, c + 1)
                c += 1
    for m in range(M):
        if fresh[m] != 0 and took[leader[m]] >= 0:
            cell[m] = took[leader[m]]
    return used


@borrowing
def _save_empty(mem: np.ndarray, M: int, k: int, iw: np.ndarray, backup: np.ndarray, keep: bool) -> int:
    """Save (:func:`_save`) the empty cells that new groups of M rows may take: the first M
    empty cells in index order. Returns the new count k of saved cells."""
    C, c = mem.shape[1], 0
    for _ in range(M):
        while c < C and mem[M_N, c] >= EMPTY:
            c += 1
        if c >= C:
            break
        k = _save(mem, c, k, iw, backup, keep)
        c += 1
    return k


@borrowing
def insert(
    mem: np.ndarray,
    nc: int,
    pos: np.ndarray,
    rng: np.ndarray,
    w: np.ndarray,
    sig: np.ndarray,
    rf: float,
    iw: np.ndarray,
    backup: np.ndarray,
    sc: np.ndarray,
    keep: bool,
) -> int:
    """Add the ranges ``rng`` (M,), m, taken at ``pos`` (M, 3), m, ENU, with weights ``w`` (M,)
    (0: absent) and σ_r0 ``sig`` (M,), to the cells ``mem`` (NM, C) whose first ``nc`` are
    used, in place (the rule of :func:`planner.estimator.memory.insert`, against the cells as
    they were before the call). Each cell's sums grow by the sum of its rows' terms, in row
    order. ``iw`` (6, M) int scratch: iw[3] is left holding each row's cell (−1: none), iw[4, 0]
    the number k of cells changed and iw[4, 1:k+1] which, iw[5] whether each row joined no cell; ``backup`` (NM, M) their columns
    before the call if ``keep`` (else only which); ``sc`` (≥ 2, C) float scratch. Returns the new count of used cells."""
    C, M = mem.shape[1], rng.shape[0]
    iw[4, 0] = 0
    if C == 0 or M == 0:
        return nc
    cell, fresh = iw[3], iw[5]
    for m in range(M):
        cell[m] = -1
        fresh[m] = 0
        if not w[m] > 0.0:
            continue
        best, d_same, near = _nearest(mem, nc, pos[m, 0], pos[m, 1], pos[m, 2], sig[m], sc)
        radius = rf * nmax(abs(mem[M_S1, best]) / mem[M_N, best], 1.0) if np.isfinite(d_same) else 0.0
        if d_same <= radius * radius:
            cell[m] = best
        else:
            fresh[m] = 1
            cell[m] = best if np.isfinite(d_same) else near
    k = 0  # the changed cells, their columns saved before any change (σ_r0 of a taken cell too)
    used = nc
    any_fresh = False
    for m in range(M):
        any_fresh = any_fresh or fresh[m] != 0
    if any_fresh:
        k = _save_empty(mem, M, k, iw, backup, keep)
        used = _group(mem, nc, pos, rng, sig, rf, fresh, cell, iw)
    for m in range(M):
        c = cell[m]
        if c < 0 or _saved(iw, k, c):
            continue
        k = _save(mem, c, k, iw, backup, keep)
    for j in range(k):
        c = iw[4, 1 + j]
        inc_n = inc_s1 = inc_s2 = inc_q = 0.0
        inc_p0 = inc_p1 = inc_p2 = inc_t0 = inc_t1 = inc_t2 = 0.0
        hit = False
        for m in range(M):
            if cell[m] != c:
                continue
            hit = True
            wv, dv = w[m], rng[m]
            px, py, pz = pos[m, 0], pos[m, 1], pos[m, 2]
            inc_n += wv
            inc_s1 += wv * dv
            inc_s2 += wv * dv * dv
            inc_q += wv * (px * px + py * py + pz * pz)
            inc_p0 += wv * px
            inc_p1 += wv * py
            inc_p2 += wv * pz
            inc_t0 += wv * dv * px
            inc_t1 += wv * dv * py
            inc_t2 += wv * dv * pz
        if hit and (inc_n != 0.0 or inc_s1 != 0.0):
            mem[M_N, c] += inc_n
            mem[M_S1, c] += inc_s1
            mem[M_S2, c] += inc_s2
            mem[M_Q, c] += inc_q
            mem[M_PS, c] += inc_p0
            mem[M_PS + 1, c] += inc_p1
            mem[M_PS + 2, c] += inc_p2
            mem[M_T, c] += inc_t0
            mem[M_T + 1, c] += inc_t1
            mem[M_T + 2, c] += inc_t2
        refresh(mem, c)
        if mem[M_N, c] >= EMPTY:
            used = max(used, c + 1)
    return used


@borrowing
def _saved(iw: np.ndarray, k: int, c: int) -> bool:
    """Whether cell c is among the k saved ones."""
    for j in range(k):  # noqa: SIM110 - compiled: no generator
        if iw[4, 1 + j] == c:
            return True
    return False


@borrowing
def _save(mem: np.ndarray, c: int, k: int, iw: np.ndarray, backup: np.ndarray, keep: bool) -> int:
    """Cell c's index into iw[4, k + 1] and, if ``keep``, its column into ``backup`` (slot k)
    (if there is room); returns the new count."""
    if k >= backup.shape[1] or 1 + k >= iw.shape[1]:
        return k
    if keep:
        for r in range(NM):
            backup[r, k] = mem[r, c]
    iw[4, 0] = k + 1
    iw[4, 1 + k] = c
    return k + 1


@borrowing
def swap_backup(mem: np.ndarray, iw: np.ndarray, backup: np.ndarray) -> None:
    """Exchange the saved columns (:func:`insert`) with the cells': called twice, the memory
    is as it was."""
    for j in range(iw[4, 0]):
        c = iw[4, 1 + j]
        for r in range(NM):
            mem[r, c], backup[r, j] = backup[r, j], mem[r, c]


# --------------------------------------------------------------------------- batch entry points
@njit(cache=True, error_model="numpy")
def refresh_batch(mem: np.ndarray) -> None:
    """:func:`refresh` every cell of every memory (E, NM, C), in place."""
    for e in range(mem.shape[0]):
        for c in range(mem.shape[2]):
            refresh(mem[e], c)


@njit(cache=True, error_model="numpy")
def insert_batch(mem: np.ndarray, pos: np.ndarray, rng: np.ndarray, w: np.ndarray, sig: np.ndarray, rf: float) -> np.ndarray:
    """:func:`insert` for every element of a batch (E, NM, C) of memories; returns new cells."""
    out = mem.copy()
    M = rng.shape[1]
    iw = np.zeros((6, max(2 * M, 1) + 1), dtype=np.int64)
    backup = np.zeros((NM, 2 * M))
    sc = np.empty((2, mem.shape[2]))
    for e in range(mem.shape[0]):
        insert(out[e], used_cells(out[e]), pos[e], rng[e], w[e], sig[e], rf, iw, backup, sc, np.bool_(False))
    return out


@njit(cache=True, error_model="numpy")
def evaluate_batch(mem: np.ndarray, x: np.ndarray, gamma: float, full: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """At points x (P, 3), point k on memory k mod E of ``mem`` (E, NM, C): :func:`nll` (P,),
    the gradient (P, 3) and Fisher information (P, 3, 3) of :func:`evaluate` (``full``: of the
    likelihood)."""
    E, P = mem.shape[0], x.shape[0]
    sc = np.empty((NSC, mem.shape[2]))
    cost, g, F = np.empty(P), np.empty((P, 3)), np.empty((P, 3, 3))
    for k in range(P):
        m = mem[k % E]
        nc = used_cells(m)
        cost[k] = nll(m, nc, x[k, 0], x[k, 1], x[k, 2], gamma, sc)
        evaluate(m, nc, x[k], gamma, full, sc, g[k], F[k])
    return cost, g, F


@njit(cache=True, error_model="numpy")
def polish_batch(mem: np.ndarray, x: np.ndarray, gamma: float, p: np.ndarray, iterations: int, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`polish` from points x (P, 3), point k on memory k mod E; the search box in ``p``."""
    E, P = mem.shape[0], x.shape[0]
    sc = np.empty((NSC, mem.shape[2]))
    out, cost = x.copy(), np.empty(P)
    for k in range(P):
        m = mem[k % E]
        cost[k] = polish(m, used_cells(m), out[k], gamma, p, iterations, tolerance, sc)[0]
    return out, cost


@njit(cache=True, error_model="numpy")
def best_start_batch(mem: np.ndarray, x: np.ndarray, cand: np.ndarray, gamma: float, p: np.ndarray, points: int) -> np.ndarray:
    """:func:`best_start` for every element (E, NM, C), x and cand (E, 3)."""
    E = mem.shape[0]
    sc = np.empty((NSC, mem.shape[2]))
    out = np.empty((E, 3))
    for e in range(E):
        best_start(mem[e], used_cells(mem[e]), x[e], cand[e], gamma, p, points, sc, out[e])
    return out

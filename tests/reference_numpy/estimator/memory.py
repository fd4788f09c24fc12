r"""The range memory (internal): every range so far, compressed by where it was taken, for the
exact-likelihood global re-check (:func:`planner.estimator.update._recheck`).

A linearised summary (Λ, η) cannot tell two distant basins apart: each record was linearised
where the estimate was when it arrived, so a summary built in a wrong basin holds the estimate
there. The squared-range PL summary can (it is exact in θ = (p0, ‖p0‖²)), but its cost is not
the likelihood: squaring ranges of 40 % relative noise puts its minimiser further off than the
exact ML in the paper's final ranging geometry (``docs/estimator.md``). The memory keeps what
the exact likelihood needs.

Under the model d̂ ~ N(d, σ_r0² d^γ) (eq. 5), the ranges d̂_k taken from one position p with one
σ_r0 enter the negative log-likelihood only through n = Σ w_k, S1 = Σ w_k d̂_k and
S2 = Σ w_k d̂_k² (w_k the record's forgetting weight):

.. math::
    f(p_0) = \frac{S_2 - 2 d S_1 + n d^2}{2\sigma_{r0}^2 d^\gamma} + \frac{n\gamma}{2}\ln d,
    \qquad d = \lVert p_0 - p\rVert.

A cell holds n, S1, S2, Σ w p, T = Σ w d̂ p and Q = Σ w ‖p‖² of the ranges taken within
``range_memory_radius`` (a fraction of the cell's mean range) of its mean position p̄, with the
same σ_r0 (LOS or NLOS). With them the residual sum Σ w (d̂ − ‖p0 − p‖)² is kept to first
order in the offsets δ = p − p̄ (u the unit vector from p̄ to p0, d = ‖p0 − p̄‖):

.. math::
    S_2 - 2\,(d S_1 - u^T (T - S_1 \bar p)) + n d^2 + (Q - n \lVert\bar p\rVert^2),

exact for ranges taken at one position; the variance is taken at the centre (a relative error
of order γ δ/d). When every cell is taken, a range joins the nearest cell of its σ_r0 (or the
nearest cell) whatever the distance: the memory degrades gracefully and never grows.

``EstimatorConfig`` leaves the memory off (``range_memory_cells`` = 0); a mission file turns it on
with 256 cells for a static source (``estimator.range_memory_cells``). ``docs/estimator.md``
gives what it changes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Weight below which a cell counts as empty (a cell forgotten at λ = 0.97 for 450 calls).
_EMPTY = 1e-6


@dataclass(frozen=True)
class RangeMemory:
    """Cells of compressed ranges, batch shape ``...``, ``C`` cells (internal).

    Attributes:
        position_sum: Σ w p, (..., C, 3), m·(weight), ENU.
        weight: n = Σ w, (..., C); a cell with n < 1e-6 is empty.
        range_sum: S1 = Σ w d̂, (..., C), m.
        square_sum: S2 = Σ w d̂², (..., C), m².
        sigma_r0: σ_r0 of the cell's ranges (LOS or NLOS, eq. 5), (..., C), m.
        cross_sum: T = Σ w d̂ p, (..., C, 3), m².
        position_square_sum: Q = Σ w ‖p‖², (..., C), m².
    """

    position_sum: FloatArray
    weight: FloatArray
    range_sum: FloatArray
    square_sum: FloatArray
    sigma_r0: FloatArray
    cross_sum: FloatArray
    position_square_sum: FloatArray

    @property
    def cells(self) -> int:
        """Capacity C."""
        return int(self.weight.shape[-1])

    def subset(self, mask: BoolArray) -> RangeMemory:
        """The batch elements where ``mask`` (...,)."""
        return RangeMemory(*(getattr(self, f)[mask] for f in RangeMemory.__dataclass_fields__))

    def scattered(self, part: RangeMemory, mask: BoolArray) -> RangeMemory:
        """A copy with the elements ``mask`` (...,) replaced by ``part`` (their :meth:`subset`)."""
        out = []
        for f in RangeMemory.__dataclass_fields__:
            a = np.array(getattr(self, f), copy=True)
            a[mask] = getattr(part, f)
            out.append(a)
        return RangeMemory(*out)

    def forgotten(self, lam: float) -> RangeMemory:
        """Every cell's statistics times the forgetting factor λ (the cells stay where they are)."""
        if lam == 1.0:
            return self
        return RangeMemory(
            self.position_sum * lam,
            self.weight * lam,
            self.range_sum * lam,
            self.square_sum * lam,
            self.sigma_r0,
            self.cross_sum * lam,
            self.position_square_sum * lam,
        )


@dataclass(frozen=True)
class Cells:
    """The occupied cells of a memory, ready to evaluate (internal): mean positions ``centre``
    (..., C', 3), m, ENU; n, S1, S2 (0 where empty) and σ_r0² (..., C'); the first moment of
    the ranges about the centre ``lever`` = T − S1 p̄ (..., C', 3), m², and the spread
    Σ w ‖p − p̄‖² (..., C'), m²; C' the last occupied cell of any batch element, plus one."""

    centre: FloatArray
    n: FloatArray
    s1: FloatArray
    s2: FloatArray
    s0sq: FloatArray
    lever: FloatArray
    spread: FloatArray

    @staticmethod
    def of(memory: RangeMemory) -> Cells:
        """The occupied cells of ``memory``, padded with empty ones to a multiple of
        :data:`_BLOCK` cells (for :func:`_cell_sum`)."""
        full = memory.weight >= _EMPTY
        occupied = np.nonzero(np.any(full, axis=tuple(range(full.ndim - 1))))[0]
        c = int(occupied[-1]) + 1 if occupied.size else 0
        width = -(-c // _BLOCK) * _BLOCK

        def cut(a: FloatArray, fill: float, vector: bool = False) -> FloatArray:
            """``a``'s first c cells, padded with ``fill`` to ``width`` cells."""
            a = a[..., :c, :] if vector else a[..., :c]
            pad = [(0, 0)] * a.ndim
            pad[a.ndim - 2 if vector else a.ndim - 1] = (0, width - c)
            return np.pad(a, pad, constant_values=fill)

        weight = cut(memory.weight, 0.0)
        full = weight >= _EMPTY
        safe_n = np.where(full, weight, 1.0)
        n = np.where(full, weight, 0.0)
        s1 = np.where(full, cut(memory.range_sum, 0.0), 0.0)
        centre = cut(memory.position_sum, 0.0, vector=True) / safe_n[..., None]
        lever = np.where(full[..., None], cut(memory.cross_sum, 0.0, vector=True) - s1[..., None] * centre, 0.0)
        spread = np.where(full, np.maximum(cut(memory.position_square_sum, 0.0) - n * (centre * centre).sum(axis=-1), 0.0), 0.0)
        return Cells(centre, n, s1, np.where(full, cut(memory.square_sum, 0.0), 0.0), cut(memory.sigma_r0, 1.0) ** 2, lever, spread)

    def take(self, rows: NDArray[np.int64]) -> Cells:
        """The cells of the elements ``rows`` of a flattened (elements, C) set of cells."""
        return Cells(*(getattr(self, f)[rows] for f in Cells.__dataclass_fields__))

    def broadcast(self, shape: tuple[int, ...]) -> Cells:
        """The cells with a leading batch shape ``shape`` added (to evaluate several points)."""
        return Cells(*(np.broadcast_to(getattr(self, f), shape + getattr(self, f).shape) for f in Cells.__dataclass_fields__))


def empty_memory(batch_shape: tuple[int, ...], cells: int) -> RangeMemory:
    """A memory of ``cells`` empty cells per batch element."""
    z = np.zeros(batch_shape + (cells,))
    return RangeMemory(
        np.zeros(batch_shape + (cells, 3)), z, z.copy(), z.copy(), np.ones(batch_shape + (cells,)), np.zeros(batch_shape + (cells, 3)), z.copy()
    )


def insert(
    memory: RangeMemory, positions: FloatArray, ranges: FloatArray, weights: FloatArray, sigma_r0: FloatArray, radius_fraction: float
) -> RangeMemory:
    """The memory with the ranges ``ranges`` (..., M), m, taken at ``positions`` (..., M, 3), m,
    ENU, with weights ``weights`` (..., M) (0: absent) and σ_r0 ``sigma_r0`` (..., M), m, added
    each batch element independently (a batch element holds what the same rows give with batch
    shape ()).

    Against the cells as they were before the call: a row within ``radius_fraction`` × max(mean
    range, 1 m) of a cell of its σ_r0 joins the nearest such cell. The others form groups: a row
    within ``radius_fraction`` × max(range, 1 m) of an earlier row of the call (its σ_r0) shares
    that row's cell; the first row of each group takes an empty cell, in row order; once none is
    left, the group's rows join the nearest cell of their σ_r0 (else the nearest cell) as the
    cells were before the call. Vectorised: no loop over rows or batch elements.
    """
    if memory.cells == 0 or ranges.shape[-1] == 0:
        return memory
    batch = memory.weight.shape[:-1]
    C, M = memory.cells, ranges.shape[-1]
    B = int(np.prod(batch, dtype=np.int64))
    ps, n, s1, s2, s0, tt, qq = (
        np.array(getattr(memory, f), dtype=float, copy=True).reshape((B, C) + getattr(memory, f).shape[len(batch) + 1 :])
        for f in RangeMemory.__dataclass_fields__
    )
    pos = np.broadcast_to(positions, batch + (M, 3)).reshape(B, M, 3)
    rng = np.broadcast_to(ranges, batch + (M,)).reshape(B, M)
    w = np.broadcast_to(weights, batch + (M,)).reshape(B, M)
    sig = np.broadcast_to(sigma_r0, batch + (M,)).reshape(B, M)
    use = w > 0.0
    full_all = n >= _EMPTY  # (B, C)
    occupied = np.nonzero(np.any(full_all, axis=0))[0]
    c = int(occupied[-1]) + 1 if occupied.size else 1  # the occupied prefix (at least one cell)
    full = full_all[:, :c]
    centre = ps[:, :c] / np.where(full, n[:, :c], 1.0)[..., None]
    # Squared distances row to cell, ‖p̄‖² − 2 p̄·p + ‖p‖² (B, M, c), compared squared.
    dist2 = np.maximum(
        np.einsum("bci,bci->bc", centre, centre)[:, None, :]
        - 2.0 * np.matmul(pos, centre.transpose(0, 2, 1))
        + np.einsum("bmi,bmi->bm", pos, pos)[..., None],
        0.0,
    )
    radius = radius_fraction * np.maximum(np.abs(s1[:, :c]) / np.where(full, n[:, :c], 1.0), 1.0)  # (B, c)
    same = full[:, None, :] & (s0[:, None, :c] == sig[:, :, None])
    near_same = np.where(same, dist2, np.inf)
    best_same = np.argmin(near_same, axis=-1)  # (B, M)
    d_same = np.take_along_axis(near_same, best_same[..., None], axis=-1)[..., 0]
    r_same = np.take_along_axis(radius, best_same, axis=-1)
    merged = use & (d_same <= r_same * r_same)
    # The others: a row within reach of an earlier one of this call (its range as the mean
    # range) shares that row's cell; the first row of each such group takes an empty cell, in
    # row order, and once none is left the group's rows join the nearest cell of their σ_r0.
    fresh_row = use & ~merged
    ids = np.arange(M)
    gap = np.sqrt(((pos[:, :, None, :] - pos[:, None, :, :]) ** 2).sum(axis=-1))  # (B, M, M) [i, j]
    reach = radius_fraction * np.maximum(np.abs(rng), 1.0)  # (B, M)
    joins = (
        fresh_row[:, :, None]
        & fresh_row[:, None, :]
        & (sig[:, :, None] == sig[:, None, :])
        & (gap <= reach[:, :, None])
        & (ids[:, None] <= ids[None, :])
    )
    leader = np.argmax(joins, axis=1)  # (B, M): the first row that reaches row j (itself at worst)
    for _ in range(max(1, int(np.ceil(np.log2(M))) + 1)):  # follow chains to their first row
        leader = np.take_along_axis(leader, leader, axis=-1)
    first = fresh_row & (leader == ids)
    rank = np.cumsum(first, axis=-1) - 1  # (B, M)
    empty = ~full_all
    n_empty = empty.sum(axis=-1)  # (B,)
    empty_ids = np.argsort(~empty, axis=-1, kind="stable")  # empty cells first, in order
    takes_empty = first & (rank < n_empty[:, None])
    empty_cell = np.take_along_axis(empty_ids, np.clip(rank, 0, C - 1), axis=-1)
    in_new = fresh_row & np.take_along_axis(takes_empty, leader, axis=-1)
    new_cell = np.take_along_axis(empty_cell, leader, axis=-1)
    nearest_any = np.argmin(np.where(full[:, None, :], dist2, np.inf), axis=-1)
    fallback = np.where(np.isfinite(d_same), best_same, nearest_any)
    cell = np.where(merged, best_same, np.where(in_new, new_cell, fallback))
    bi, mi = np.nonzero(use)
    flat = bi * C + cell[bi, mi]  # the cell of each row, in the flattened (B·C) cells
    wv, dv, pv = w[bi, mi], rng[bi, mi], pos[bi, mi]

    def add(values: FloatArray) -> FloatArray:
        return np.asarray(np.bincount(flat, weights=values, minlength=B * C), dtype=float).reshape(B, C)

    n += add(wv)
    s1 += add(wv * dv)
    s2 += add(wv * dv * dv)
    qq += add(wv * np.einsum("ri,ri->r", pv, pv))
    for i in range(3):
        ps[..., i] += add(wv * pv[:, i])
        tt[..., i] += add(wv * dv * pv[:, i])
    tb, tm = np.nonzero(takes_empty)
    s0[tb, cell[tb, tm]] = sig[tb, tm]
    return RangeMemory(
        ps.reshape(batch + (C, 3)),
        n.reshape(batch + (C,)),
        s1.reshape(batch + (C,)),
        s2.reshape(batch + (C,)),
        s0.reshape(batch + (C,)),
        tt.reshape(batch + (C, 3)),
        qq.reshape(batch + (C,)),
    )


#: Where each entry of a symmetric 3 × 3 matrix is in (xx, yy, zz, xy, yz, xz).
_SYM = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2]])

#: Cells summed together before the running sum of :func:`_cell_sum`.
_BLOCK = 8


def _cell_sum(a: FloatArray, axis: int) -> FloatArray:
    """Sum of ``a`` over its cell axis (a multiple of :data:`_BLOCK` long): within blocks of
    :data:`_BLOCK` cells, then block after block (a cumulative sum's last entry). A batch
    element's sum then does not depend on how many empty cells its batch pads it with
    (``Cells.of`` keeps the batch's occupied cells): numpy's pairwise ``sum`` groups the terms
    by the axis' length, so a trial would change in the last bits with the batch it runs in."""
    axis = axis % a.ndim
    c = a.shape[axis]
    if c == 0:
        return np.zeros(a.shape[:axis] + a.shape[axis + 1 :])
    blocks = a.reshape(a.shape[:axis] + (c // _BLOCK, _BLOCK) + a.shape[axis + 1 :]).sum(axis=axis + 1)
    return np.take(np.cumsum(blocks, axis=axis), -1, axis=axis)


def _terms(cells: Cells, x: FloatArray, gamma: float) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Per cell at x (..., 3): distance d = ‖x − p̄‖ (..., C), unit vector u (..., C, 3),
    variance σ_r0² d^γ and the residual sum Σ w (d̂ − ‖x − p‖)² (..., C), to first order in the
    records' offsets p − p̄ from the centre: S2 − 2(S1 d − u·lever) + nd² + spread."""
    r = x[..., None, :] - cells.centre
    d = np.maximum(np.sqrt(np.einsum("...ci,...ci->...c", r, r)), 1e-3)
    u = r / d[..., None]
    var = cells.s0sq * (d * d if gamma == 2.0 else d**gamma)
    resid2 = cells.s2 - 2.0 * (d * cells.s1 - np.einsum("...ci,...ci->...c", u, cells.lever)) + cells.n * d * d + cells.spread
    return d, u, var, resid2


def _nll(cells: Cells, x: FloatArray, gamma: float) -> FloatArray:
    d, _, var, resid2 = _terms(cells, x, gamma)
    return _cell_sum(0.5 * resid2 / var + 0.5 * gamma * cells.n * np.log(d), axis=-1)


def nll(memory: RangeMemory, x: FloatArray, gamma: float) -> FloatArray:
    """Negative log-likelihood of every range in the memory at source positions x (..., 3), m,
    ENU, up to a constant (eq. 5): Σ_cells Σ w (d̂ − ‖x − p‖)²/(2σ_r0² d^γ) + (nγ/2) ln d, d the
    distance to the cell's centre, the residuals to first order in the offsets from it
    (exact for ranges taken at one position), (...,)."""
    return _nll(Cells.of(memory), x, gamma)


def _gradient_fisher(cells: Cells, x: FloatArray, gamma: float, full_likelihood: bool) -> tuple[FloatArray, FloatArray]:
    d, u, var, resid2 = _terms(cells, x, gamma)
    dfd = (cells.n * d - cells.s1) / var
    info = cells.n / var
    if full_likelihood:
        dfd = dfd - 0.5 * gamma * resid2 / (var * d) + 0.5 * gamma * cells.n / d
        info = info + 0.5 * cells.n * (gamma / d) ** 2
    # The lever term u·lever turns with u: ∂u/∂x = (I − uuᵀ)/d.
    lev = cells.lever / (var * d)[..., None]
    # Σ_c (lev_c − (u_c·lev_c) u_c), without forming the per-cell tangential vectors.
    radial = dfd - np.einsum("...ci,...ci->...c", u, lev)
    g = _cell_sum(radial[..., None] * u + lev, axis=-2)
    # F = Σ_c info_c u_c u_cᵀ, from its six distinct entries.
    wu = info[..., None] * u
    prods = np.empty(u.shape[:-1] + (6,))
    np.multiply(wu, u, out=prods[..., :3])
    np.multiply(wu[..., :2], u[..., 1:], out=prods[..., 3:5])
    np.multiply(wu[..., 0], u[..., 2], out=prods[..., 5])
    f6 = _cell_sum(prods, axis=-2)
    F = f6[..., _SYM]
    return g, F


def gradient_fisher(memory: RangeMemory, x: FloatArray, gamma: float, full_likelihood: bool) -> tuple[FloatArray, FloatArray]:
    """Gradient (..., 3), m⁻¹, and Fisher information (..., 3, 3), m⁻², of the memory's cost at
    x (..., 3), m, ENU. ``full_likelihood``: of :func:`nll` (with ½ ln σ_r², Fisher
    n(1/σ_r² + γ²/(2d²)) uuᵀ); else of the generalised LS cost Σ w (d̂ − ‖x − p‖)²/(2σ_r²) with
    σ_r² held at x (Fisher n/σ_r² uuᵀ), the form of the refinement's prior in GLS mode."""
    return _gradient_fisher(Cells.of(memory), x, gamma, full_likelihood)


def polish(
    memory: RangeMemory, x: FloatArray, gamma: float, clip: Callable[[FloatArray], FloatArray], iterations: int = 15, tolerance_m: float = 1e-3
) -> tuple[FloatArray, FloatArray]:
    """Fisher-scoring (Levenberg-Marquardt) minimisation of :func:`nll` from x (..., 3), m,
    ENU, projected by ``clip`` (into the search box), each step kept only if the cost does not
    increase; at most ``iterations``; a point stops once its projected step is shorter than ``tolerance_m``.
    ``memory`` may have fewer batch axes than x (its cells broadcast over the leading ones).
    Returns the point and its cost (...,)."""
    cells = Cells.of(memory)
    shape = x.shape[:-1]
    nb = memory.weight.ndim - 1  # the memory's batch axes, the trailing ones of x's
    elems = int(np.prod(memory.weight.shape[:-1], dtype=np.int64))
    # The cells flattened to (elements, C); point p of the flattened x uses element p mod elems.
    flat = Cells(*(np.reshape(getattr(cells, f), (elems,) + getattr(cells, f).shape[nb:]) for f in Cells.__dataclass_fields__))
    x = np.array(x, dtype=float).reshape(-1, 3)
    elem = np.arange(x.shape[0]) % elems
    cost = np.empty(x.shape[0])
    for ch in _chunks(np.arange(x.shape[0])):
        cost[ch] = _nll(flat.take(elem[ch]), x[ch], gamma)
    mu = np.full(cost.shape, 1e-3)
    live = np.ones(cost.shape, dtype=bool)
    eye = np.eye(3)
    for _ in range(iterations):
        idx = np.nonzero(live)[0]
        if idx.size == 0:
            break
        # In chunks of points, so that the (points, C) arrays stay in the cache.
        for ch in _chunks(idx):
            sub = flat.take(elem[ch])
            xi, mi = x[ch], mu[ch]
            g, F = _gradient_fisher(sub, xi, gamma, True)
            # Projected Newton: a coordinate held at the box by the descent direction is fixed
            # (its row and column of the system dropped), so that a point on the box's face
            # slides along it instead of zigzagging into it.
            free = clip(xi - 1e-6 * np.sign(g)) != xi
            both = free[..., :, None] & free[..., None, :]
            F = np.where(both, F, 0.0)
            g = np.where(free, g, 0.0)
            diag = np.einsum("...ii->...i", F)
            H = (
                F
                + (mi[..., None] * diag + 1e-9 * diag.sum(axis=-1, keepdims=True) + 1e-12)[..., None] * eye
                + np.where(free, 0.0, 1.0)[..., None] * eye
            )
            step = -np.linalg.solve(H, g[..., None])[..., 0]
            cand = clip(xi + step)
            c_new = _nll(sub, cand, gamma)
            ok = np.isfinite(c_new) & (c_new <= cost[ch])
            x[ch] = np.where(ok[..., None], cand, xi)
            cost[ch] = np.where(ok, c_new, cost[ch])
            mu[ch] = np.where(ok, mi / 3.0, mi * 4.0)
            # A point is done once its step (projected into the box), taken or not, is
            # shorter than the tolerance.
            live[ch] = np.abs(cand - xi).max(axis=-1) > tolerance_m
    return x.reshape(shape + (3,)), cost.reshape(shape)


#: Points per chunk of the memory's evaluations (their (points, C) arrays stay in the cache).
_CHUNK = 128


def _chunks(idx: NDArray[np.int64]) -> list[NDArray[np.int64]]:
    """``idx`` in consecutive pieces of at most :data:`_CHUNK`."""
    return [idx[k : k + _CHUNK] for k in range(0, idx.size, _CHUNK)]


def best_start(
    memory: RangeMemory, x: FloatArray, cand: FloatArray, gamma: float, clip: Callable[[FloatArray], FloatArray], points: int = 16
) -> FloatArray:
    """Where to look for another basin (..., 3), m, ENU: of the candidate ``cand`` and of
    ``points`` points on the line through x along the memory's least-informed direction (within
    ± the mean distance from x to the cells, projected by ``clip``), the one of lowest
    :func:`nll`. Ranges pin the distances, not the direction of least information (e.g. the
    height of a source below a swarm), so the other basin lies along it."""
    cells = Cells.of(memory)
    _, F = _gradient_fisher(cells, x, gamma, False)
    _, vecs = np.linalg.eigh(F)
    v = vecs[..., :, 0]  # (..., 3) smallest eigenvalue
    occupied = cells.n > 0.0
    dist = np.sqrt(((x[..., None, :] - cells.centre) ** 2).sum(axis=-1))
    reach = _cell_sum(np.where(occupied, dist, 0.0), axis=-1) / np.maximum(occupied.sum(axis=-1), 1)
    t = np.linspace(-1.0, 1.0, points)
    pts = clip(x[..., None, :] + (t[:, None] * reach[..., None, None]) * v[..., None, :])  # (..., P, 3)
    pts = np.concatenate((pts, cand[..., None, :]), axis=-2)
    costs = _nll(cells.broadcast((pts.shape[-2],)), np.moveaxis(pts, -2, 0), gamma)  # (P, ...)
    costs = np.where(np.isfinite(costs), costs, np.inf)
    best = np.argmin(costs, axis=0)
    return np.take_along_axis(pts, best[..., None, None], axis=-2)[..., 0, :]


def has_ranges(memory: RangeMemory) -> BoolArray:
    """Where the memory holds any range, (...,)."""
    return np.any(memory.weight >= _EMPTY, axis=-1)

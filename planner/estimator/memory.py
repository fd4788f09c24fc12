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

The arithmetic is compiled (:mod:`planner.estimator.kernels.memory`, one batch element at a
time); the functions below are its batched entry points, for the estimator's state and tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from planner.estimator.layout import M_CX, M_EN, M_ES1, M_ES2, M_L, M_N, M_PS, M_Q, M_S0, M_S0SQ, M_S1, M_S2, M_SP, M_T, NM, NP, P_HI, P_LO

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

    def packed(self) -> FloatArray:
        """The cells as one array (E, NM, C) (:mod:`planner.estimator.layout`), E the
        flattened batch."""
        return pack_memory(self)

    @staticmethod
    def of_packed(mem: FloatArray, batch_shape: tuple[int, ...]) -> RangeMemory:
        """The memory whose cells are ``mem`` (E, NM, C), as views, with batch shape
        ``batch_shape``."""
        m = np.moveaxis(mem.reshape(tuple(batch_shape) + mem.shape[-2:]), -1, -2)  # (..., C, NM)
        return RangeMemory(m[..., M_PS : M_PS + 3], m[..., M_N], m[..., M_S1], m[..., M_S2], m[..., M_S0], m[..., M_T : M_T + 3], m[..., M_Q])


def pack_memory(memory: RangeMemory) -> FloatArray:
    """The cells of ``memory`` as one array (E, NM, C), the evaluation rows computed."""
    from planner.estimator.kernels import memory as km

    E, C = int(np.prod(memory.weight.shape[:-1], dtype=np.int64)), memory.cells
    out = np.zeros((E, NM, C))
    out[:, M_PS : M_PS + 3] = np.moveaxis(np.reshape(memory.position_sum, (E, C, 3)), -1, -2)
    out[:, M_T : M_T + 3] = np.moveaxis(np.reshape(memory.cross_sum, (E, C, 3)), -1, -2)
    for row, f in (
        (M_N, memory.weight),
        (M_S1, memory.range_sum),
        (M_S2, memory.square_sum),
        (M_S0, memory.sigma_r0),
        (M_Q, memory.position_square_sum),
    ):
        out[:, row] = np.reshape(f, (E, C))
    km.refresh_batch(out)
    return out


@dataclass(frozen=True)
class Cells:
    """The occupied cells of a memory, ready to evaluate (for inspection and tests): mean
    positions ``centre`` (..., C', 3), m, ENU; n, S1, S2 and σ_r0² (..., C'); the first moment
    of the ranges about the centre ``lever`` = T − S1 p̄ (..., C', 3), m², and the spread
    Σ w ‖p − p̄‖² (..., C'), m²; each element's occupied cells first, in order, then empty ones
    (n = 0, σ_r0² = 1) up to C' = the most occupied element's count."""

    centre: FloatArray
    n: FloatArray
    s1: FloatArray
    s2: FloatArray
    s0sq: FloatArray
    lever: FloatArray
    spread: FloatArray

    @staticmethod
    def of(memory: RangeMemory) -> Cells:
        """The occupied cells of ``memory`` (the evaluation rows of its packed form,
        :mod:`planner.estimator.kernels.memory`)."""
        batch = memory.weight.shape[:-1]
        mem = pack_memory(memory)  # (E, NM, C)
        E = mem.shape[0]
        occ = mem[:, M_N] >= _EMPTY
        width = int(occ.sum(axis=-1).max(initial=0))
        rows = (M_CX, M_CX + 1, M_CX + 2, M_EN, M_ES1, M_ES2, M_S0SQ, M_L, M_L + 1, M_L + 2, M_SP)
        out = np.zeros((E, width, len(rows)))
        out[..., 6] = 1.0
        for e in range(E):
            cols = np.flatnonzero(occ[e])
            out[e, : len(cols)] = mem[e][list(rows)][:, cols].T
        c = out.reshape(batch + (width, len(rows)))
        return Cells(c[..., 0:3], c[..., 3], c[..., 4], c[..., 5], c[..., 6], c[..., 7:10], c[..., 10])


def empty_memory(batch_shape: tuple[int, ...], cells: int) -> RangeMemory:
    """A memory of ``cells`` empty cells per batch element."""
    mem = np.zeros((int(np.prod(batch_shape, dtype=np.int64)), NM, cells))
    mem[:, M_S0] = 1.0
    return RangeMemory.of_packed(mem, tuple(batch_shape))


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
    cells were before the call. Each cell's sums grow by the sum of its rows' terms.
    """
    from planner.estimator.kernels import memory as km

    if memory.cells == 0 or np.shape(ranges)[-1] == 0:
        return memory
    batch = memory.weight.shape[:-1]
    M = np.shape(ranges)[-1]

    def rows(a: FloatArray, tail: tuple[int, ...]) -> FloatArray:
        return np.ascontiguousarray(np.broadcast_to(np.asarray(a, dtype=float), batch + (M,) + tail).reshape((-1, M) + tail))

    mem = km.insert_batch(pack_memory(memory), rows(positions, (3,)), rows(ranges, ()), rows(weights, ()), rows(sigma_r0, ()), float(radius_fraction))
    return RangeMemory.of_packed(mem, batch)


def _points(memory: RangeMemory, x: FloatArray) -> tuple[FloatArray, FloatArray, tuple[int, ...]]:
    """The packed cells (E, C, NM), the points x flattened (P, 3) with point k on element k mod E
    (the memory's batch axes broadcast against x's trailing ones), and the points' batch shape."""
    x = np.asarray(x, dtype=float)
    shape = np.broadcast_shapes(x.shape[:-1], memory.weight.shape[:-1])
    pts = np.ascontiguousarray(np.broadcast_to(x, shape + (3,)).reshape(-1, 3))
    return pack_memory(memory), pts, shape


def nll(memory: RangeMemory, x: FloatArray, gamma: float) -> FloatArray:
    """Negative log-likelihood of every range in the memory at source positions x (..., 3), m,
    ENU, up to a constant (eq. 5): Σ_cells Σ w (d̂ − ‖x − p‖)²/(2σ_r0² d^γ) + (nγ/2) ln d, d the
    distance to the cell's centre, the residuals to first order in the offsets from it
    (exact for ranges taken at one position), (...,)."""
    from planner.estimator.kernels import memory as km

    mem, pts, shape = _points(memory, x)
    return km.evaluate_batch(mem, pts, float(gamma), True)[0].reshape(shape)


def gradient_fisher(memory: RangeMemory, x: FloatArray, gamma: float, full_likelihood: bool) -> tuple[FloatArray, FloatArray]:
    """Gradient (..., 3), m⁻¹, and Fisher information (..., 3, 3), m⁻², of the memory's cost at
    x (..., 3), m, ENU. ``full_likelihood``: of :func:`nll` (with ½ ln σ_r², Fisher
    n(1/σ_r² + γ²/(2d²)) uuᵀ); else of the generalised LS cost Σ w (d̂ − ‖x − p‖)²/(2σ_r²) with
    σ_r² held at x (Fisher n/σ_r² uuᵀ), the form of the refinement's prior in GLS mode."""
    from planner.estimator.kernels import memory as km

    mem, pts, shape = _points(memory, x)
    _, g, F = km.evaluate_batch(mem, pts, float(gamma), bool(full_likelihood))
    return g.reshape(shape + (3,)), F.reshape(shape + (3, 3))


def _box(bounds_min: FloatArray, bounds_max: FloatArray) -> FloatArray:
    """The kernels' parameter vector carrying only the search box."""
    p = np.zeros(NP)
    p[P_LO : P_LO + 3] = bounds_min
    p[P_HI : P_HI + 3] = bounds_max
    return p


def polish(
    memory: RangeMemory,
    x: FloatArray,
    gamma: float,
    bounds: tuple[FloatArray, FloatArray],
    iterations: int = 15,
    tolerance_m: float = 1e-3,
) -> tuple[FloatArray, FloatArray]:
    """Fisher-scoring (Levenberg-Marquardt) minimisation of :func:`nll` from x (..., 3), m,
    ENU, projected into the search box ``bounds`` = (min, max) (3,), m, each step kept only if
    the cost does not increase; at most ``iterations``; a point stops once its projected step
    is shorter than ``tolerance_m``. ``memory`` may have fewer batch axes than x (its cells
    broadcast over the leading ones). Returns the point and its cost (...,)."""
    from planner.estimator.kernels import memory as km

    mem, pts, shape = _points(memory, x)
    out, cost = km.polish_batch(mem, pts, float(gamma), _box(*bounds), int(iterations), float(tolerance_m))
    return out.reshape(shape + (3,)), cost.reshape(shape)


def best_start(
    memory: RangeMemory, x: FloatArray, cand: FloatArray, gamma: float, bounds: tuple[FloatArray, FloatArray], points: int = 16
) -> FloatArray:
    """Where to look for another basin (..., 3), m, ENU: of the candidate ``cand`` and of
    ``points`` points on the line through x along the memory's least-informed direction (within
    ± the mean distance from x to the cells, projected into the box ``bounds``), the one of
    lowest :func:`nll`. Ranges pin the distances, not the direction of least information (e.g.
    the height of a source below a swarm), so the other basin lies along it."""
    from planner.estimator.kernels import memory as km

    batch = memory.weight.shape[:-1]
    xs = np.ascontiguousarray(np.broadcast_to(np.asarray(x, dtype=float), batch + (3,)).reshape(-1, 3))
    cs = np.ascontiguousarray(np.broadcast_to(np.asarray(cand, dtype=float), batch + (3,)).reshape(-1, 3))
    return km.best_start_batch(pack_memory(memory), xs, cs, float(gamma), _box(*bounds), int(points)).reshape(batch + (3,))


def has_ranges(memory: RangeMemory) -> BoolArray:
    """Where the memory holds any range, (...,)."""
    return np.any(memory.weight >= _EMPTY, axis=-1)

"""Compiled kernels of the planning step (numba): the geometry of the buildings, the Fisher
information and its costs, one drone's control step with its safety filter, and the planning
policy around them (predicted line of sight, keep-outs, loiter, peer constraints, the carried
state). Each kernel loops over a batch of drones itself (trials × drones in the simulator, one
drone in a planner node).

The public functions, their documentation and the equations they implement are in
:mod:`planner.geometry`, :mod:`planner.fim`, :mod:`planner.control` and :mod:`planner.agent`;
the tests check every kernel against an independent reference (closed forms, finite
differences, dense sampling, the former numpy expressions evaluated in the test).

One module: numba keys the cache of a compiled function on its own source file only, so the
functions a cached kernel links in live in the same file (an edit anywhere here recompiles).
Entry kernels (called from Python) are ``@njit(cache=True)``; the functions they call are
``@inner`` (``no_cpython_wrapper=True, _nrt=False``: compiled into their callers, no Python entry
point of their own, and without numba's reference counting: they allocate nothing and return
no array, so their array arguments are borrowed from the entry kernel that owns them, without
the atomic increment and decrement of every array argument at every call that otherwise took
about 40 % of the planning step's time; ``tests/simulator/test_reference_counts.py`` checks
that a simulation leaves no array of the compiled code alive). Written for numba's compile time as well as for speed: short functions with few
branches (``&`` rather than ``and``, ``min``/``max`` rather than conditional expressions),
since numba's compile time grows faster than linearly with the branches of a function.
The functions the batch step calls once per drone (:func:`plan_cost`, :func:`plan_one` and,
under it, :func:`advance_state`, :func:`keepout_policy`, :func:`peer_rows`, :func:`control_one`
with :func:`constraints`, :func:`requirements`, :func:`_orthogonalise` and
:func:`safety_filter`) are compiled into the loop over the drones, :func:`plan_drones`
(``inline="always"``), itself ``@inner``: a call passes every array of its tuples as separate
words, and passing the scene, the state and the workspace again for each drone was about a
fifth of the step. Those called per candidate step of the filter stay calls (inlining them
gained nothing measurable). Inlined into the entry kernel instead, which counts references, the
bodies would count theirs: slower.

Imports: numpy and numba only.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray


def contiguous(a: ArrayLike, dtype: type = np.float64) -> NDArray[Any]:
    """``a`` as a C-contiguous, writeable ``dtype`` array (a copy only where it is not one): the
    one array type an entry kernel is compiled for. A read-only array (a broadcast view, say) is
    another numba type, and would compile the entry a second time."""
    arr: NDArray[Any] = np.ascontiguousarray(a, dtype=dtype)
    return arr if arr.flags.writeable else arr.copy()


def one_drone(a: ArrayLike, dtype: type = np.float64) -> NDArray[Any]:
    """One drone's array as a batch of one (a view where ``a`` is already a C-contiguous,
    writeable array of ``dtype``): the entry kernels' form without the broadcasting of :func:`as_batch`."""
    if type(a) is np.ndarray and a.dtype == dtype and a.flags.c_contiguous and a.flags.writeable:
        return a[None]
    return contiguous(a, dtype)[None]


#: numba's decorator, typed loosely: the kernels' Python signatures are their docstrings'. With
#: numpy's error model: a division by zero gives ±inf or NaN instead of raising (IEEE arithmetic,
#: as everywhere else); every division here is guarded or by a nonzero quantity, so the results
#: are those of Python's model, without its zero test before each division.
njit: Any = functools.partial(numba.njit, error_model="numpy")
#: The decorator of the functions the entry kernels call: compiled into their callers, without
#: numba's reference counting (the module's documentation).
inner: Any = functools.partial(numba.njit, error_model="numpy", no_cpython_wrapper=True, _nrt=False)


def as_batch(a: ArrayLike, shape: tuple[int, ...], dtype: type, tail: int) -> NDArray[Any]:
    """``a`` broadcast to ``shape`` as a C-contiguous, writeable ``dtype`` array (:func:`contiguous`)
    with the leading dimensions (all but the last ``tail``) flattened into one batch axis: the form
    the entry kernels take."""
    cut = len(shape) - tail
    if type(a) is np.ndarray and a.shape == shape and a.dtype == dtype and a.flags.c_contiguous and a.flags.writeable:
        # Already the kernels' form (the planning step's inputs, every step): no conversion.
        return a[None] if cut == 0 else (a if cut == 1 else a.reshape((math.prod(shape[:cut]),) + shape[cut:]))
    arr: NDArray[Any] = np.asarray(a, dtype=dtype)
    if arr.shape != shape:
        arr = np.broadcast_to(arr, shape)
    if not (arr.flags.c_contiguous and arr.flags.writeable):
        arr = contiguous(arr, dtype)
    if cut == 0:
        return arr[None]  # one drone: a batch of one
    return arr.reshape((math.prod(shape[:cut]),) + shape[cut:])


# =========================================================================== geometry
#: How far (m) a box is extended past a face a link cannot pass (:func:`link_clearance`).
NO_EXIT_M: float = 1.0e4


@inner
def box_signed_distance(x, y, z, bmin, bmax, b):
    """Signed distance (m) of the point (x, y, z) to box b: the distance to its surface outside,
    minus the distance to its nearest face inside."""
    ox = x - min(max(x, bmin[b, 0]), bmax[b, 0])
    oy = y - min(max(y, bmin[b, 1]), bmax[b, 1])
    oz = z - min(max(z, bmin[b, 2]), bmax[b, 2])
    outside = math.sqrt(ox * ox + oy * oy + oz * oz)
    if outside > 0.0:
        return outside
    depth = min(min(min(x - bmin[b, 0], bmax[b, 0] - x), min(y - bmin[b, 1], bmax[b, 1] - y)), min(z - bmin[b, 2], bmax[b, 2] - z))
    return -max(depth, 0.0)


@inner
def distance_to_boxes(x, y, z, bmin, bmax):
    """Signed distance (m) of the point (x, y, z) to the nearest box; +inf without boxes (eq. 17)."""
    best = np.inf
    for b in range(bmin.shape[0]):
        d = box_signed_distance(x, y, z, bmin, bmax, b)
        if d < best:
            best = d
    return best


@inner
def distance_to_boxes_with_gradient(x, y, z, bmin, bmax, grad):
    """Signed distance (m) to the nearest box, its unit gradient written to ``grad`` (3,): from the
    nearest surface point outside, the outward normal of the nearest face inside; +inf and
    zeros without boxes. The nearest box is the first of the smallest distance."""
    grad[0] = 0.0
    grad[1] = 0.0
    grad[2] = 0.0
    nb = bmin.shape[0]
    if nb == 0:
        return np.inf
    best = np.inf
    k = 0
    for b in range(nb):
        d = box_signed_distance(x, y, z, bmin, bmax, b)
        if d < best:
            best = d
            k = b
    if best > 0.0:
        grad[0] = (x - min(max(x, bmin[k, 0]), bmax[k, 0])) / best
        grad[1] = (y - min(max(y, bmin[k, 1]), bmax[k, 1])) / best
        grad[2] = (z - min(max(z, bmin[k, 2]), bmax[k, 2])) / best
        return best
    # Inside (or on) box k: the outward normal of its nearest face.
    below0, above0 = x - bmin[k, 0], bmax[k, 0] - x
    below1, above1 = y - bmin[k, 1], bmax[k, 1] - y
    below2, above2 = z - bmin[k, 2], bmax[k, 2] - z
    g0, g1, g2 = min(below0, above0), min(below1, above1), min(below2, above2)
    axis = 0
    gap = g0
    if g1 < gap:
        axis, gap = 1, g1
    if g2 < gap:
        axis = 2
    if axis == 0:
        lower = below0 < above0
    elif axis == 1:
        lower = below1 < above1
    else:
        lower = below2 < above2
    grad[axis] = -1.0 if lower else 1.0
    return best


@inner
def _crossing_exit(p, s, lo, hi, out):
    """Unit direction ``out`` (3,) in which the drone p moves a link s → p that crosses the box
    [lo, hi] out of it: per face, the displacement along its normal that takes the part of the
    segment inside the box past it (max over the segment's entry and exit parameters); the
    face with the smallest displacement (docs/control.md)."""
    t_lo_max = -np.inf
    t_hi_min = np.inf
    for a in range(3):
        d = p[a] - s[a]
        if d == 0.0:
            inside = s[a] >= lo[a] and s[a] <= hi[a]
            t_lo = -np.inf if inside else np.inf
            t_hi = np.inf if inside else -np.inf
        else:
            t1 = (lo[a] - s[a]) / d
            t2 = (hi[a] - s[a]) / d
            t_lo = min(t1, t2)
            t_hi = max(t1, t2)
        t_lo_max = max(t_lo_max, t_lo)
        t_hi_min = min(t_hi_min, t_hi)
    t_in = min(max(t_lo_max, 1e-6), 1.0)
    t_out = min(max(t_hi_min, t_in), 1.0)
    best = np.inf
    k = 0
    for face in range(6):
        a = face % 3
        d = p[a] - s[a]
        x_in = s[a] + t_in * d
        x_out = s[a] + t_out * d
        up = max((hi[a] - x_in) / t_in, (hi[a] - x_out) / t_out)
        down = max((x_in - lo[a]) / t_in, (x_out - lo[a]) / t_out)
        move = up if face < 3 else down
        if move < best:
            best = move
            k = face
    out[0] = 0.0
    out[1] = 0.0
    out[2] = 0.0
    out[k % 3] = 1.0 if k < 3 else -1.0


@inner
def link_clearance(p, s, bmin, bmax, b, samples, cutoff_m, grad, work):
    """Clearance c (m) of the link s → p from box b and its gradient w.r.t. p, written to ``grad``
    (3,) (:func:`planner.geometry.link_clearance_with_gradient`): the smallest signed distance
    to the box of the points s + t (p − s), t = (m + 1)/``samples``; ∇c = t* ∇d at the sampled
    minimiser. A box's bottom at or below both ends of the link (top at or above both) is
    extended past it by :data:`NO_EXIT_M` for this link; a link crossing the box gets the
    direction of :func:`_crossing_exit`. A link whose bounding box is ``cutoff_m`` or farther
    from the box (``cutoff_m`` > 0) is not sampled: c is that distance and ∇c = 0. ``work``:
    scratch (6,)."""
    grad[0] = 0.0
    grad[1] = 0.0
    grad[2] = 0.0
    if cutoff_m > 0.0:
        c2 = 0.0
        for a in range(3):
            hi_ps = max(p[a], s[a])
            lo_ps = min(p[a], s[a])
            gap = max(max(bmin[b, a] - hi_ps, lo_ps - bmax[b, a]), 0.0)
            c2 += gap * gap
        c = math.sqrt(c2)
        if not c < cutoff_m:
            return c
    lo = work[0:3]
    hi = work[3:6]
    lo[0], lo[1], lo[2] = bmin[b, 0], bmin[b, 1], bmin[b, 2]
    hi[0], hi[1], hi[2] = bmax[b, 0], bmax[b, 1], bmax[b, 2]
    z_lo, z_hi = min(p[2], s[2]), max(p[2], s[2])
    if lo[2] <= z_lo:
        lo[2] = z_lo - NO_EXIT_M
    if hi[2] >= z_hi:
        hi[2] = z_hi + NO_EXIT_M
    best = np.inf
    t_best = 0.0
    e0b = e1b = e2b = 0.0
    s0b = s1b = s2b = 1.0
    out_b = 0.0
    for m in range(samples):
        t = (m + 1.0) / samples
        x0 = s[0] + t * (p[0] - s[0])
        x1 = s[1] + t * (p[1] - s[1])
        x2 = s[2] + t * (p[2] - s[2])
        l0, h0 = lo[0] - x0, x0 - hi[0]
        l1, h1 = lo[1] - x1, x1 - hi[1]
        l2, h2 = lo[2] - x2, x2 - hi[2]
        e0, e1, e2 = max(l0, h0), max(l1, h1), max(l2, h2)
        p0, p1, p2 = max(e0, 0.0), max(e1, 0.0), max(e2, 0.0)
        out = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
        sdf = out + min(max(max(e0, e1), e2), 0.0)
        if sdf < best:
            best = sdf
            t_best = t
            e0b, e1b, e2b = e0, e1, e2
            s0b = -1.0 if l0 >= h0 else 1.0
            s1b = -1.0 if l1 >= h1 else 1.0
            s2b = -1.0 if l2 >= h2 else 1.0
            out_b = out
    if out_b <= 0.0:
        _crossing_exit(p, s, lo, hi, grad)
    else:
        grad[0] = s0b * (max(e0b, 0.0) / out_b)
        grad[1] = s1b * (max(e1b, 0.0) / out_b)
        grad[2] = s2b * (max(e2b, 0.0) / out_b)
    grad[0] *= t_best
    grad[1] *= t_best
    grad[2] *= t_best
    return best


@njit(cache=True)
def distances_batch(points, bmin, bmax, with_gradient):
    """Signed distances (n,) of points (n, 3) to the nearest box and, if ``with_gradient``,
    their unit gradients (n, 3) (zeros otherwise)."""
    n = points.shape[0]
    d = np.empty(n)
    g = np.zeros((n, 3))
    for i in range(n):
        if with_gradient:
            d[i] = distance_to_boxes_with_gradient(points[i, 0], points[i, 1], points[i, 2], bmin, bmax, g[i])
        else:
            d[i] = distance_to_boxes(points[i, 0], points[i, 1], points[i, 2], bmin, bmax)
    return d, g


@njit(cache=True)
def link_clearance_batch(p, s, bmin, bmax, samples, cutoff_m):
    """Clearances (n, B) and gradients (n, B, 3) of the links s → p (n, 3) from every box."""
    n, nb = p.shape[0], bmin.shape[0]
    c = np.empty((n, nb))
    g = np.empty((n, nb, 3))
    work = np.empty(6)
    for i in range(n):
        for b in range(nb):
            c[i, b] = link_clearance(p[i], s[i], bmin, bmax, b, samples, cutoff_m, g[i, b], work)
    return c, g


# =========================================================================== Fisher information
#: Horizontal distance floor (m), as :data:`planner.geometry.RHO_FLOOR_M`.
RHO_FLOOR_M: float = 1e-9
#: Reciprocal condition numbers of :func:`planner.fim.invert_fim`.
SINGULAR_RCOND: float = 1e-12
ILL_CONDITIONED_RCOND: float = 1e-8
#: Status codes of :class:`planner.fim.FimStatus`.
OK, ILL, SINGULAR = 0, 1, 2
#: :func:`well_conditioned`'s threshold on its lower bound 4 det J/(tr J)³ of the reciprocal
#: condition number: a hundred times :data:`ILL_CONDITIONED_RCOND`, so that the bound, with its
#: rounding, decides only where the eigenvalues would give status OK by far.
SURELY_OK_RCOND: float = 100.0 * ILL_CONDITIONED_RCOND
#: Relative size (of (tr J)^k, k the minor's order) below which a computed leading minor is not
#: trusted to be positive: its rounding error is a few ε (tr J)^k.
MINOR_TOL: float = 1e-13
#: Indices of the channel array.
CH_GAMMA, CH_S2_LOS, CH_S2_NLOS, CH_SB2 = 0, 1, 2, 3


def channel_array(gamma: float, sigma_r0_los: float, sigma_r0_nlos: float, sigma_bearing_rad: float) -> np.ndarray:
    """The channel array ``ch`` of the kernels: (γ, σ_r0,LOS², σ_r0,NLOS², σ_b²)."""
    return np.array([gamma, sigma_r0_los**2, sigma_r0_nlos**2, sigma_bearing_rad**2])


@inner
def _rotate(app, aqq, apq, arp, arq, late):
    """One Jacobi rotation of a symmetric 3×3 a zeroing a[p, q] (r the third index), on its
    entries a[p, p], a[q, q], a[p, q], a[r, p], a[r, q]; after the first sweeps (``late``) an
    a[p, q] negligible beside both a[p, p] and a[q, q] is set to zero instead (relative accuracy
    of the small eigenvalues). Returns the five entries after it and what it did: 0 nothing
    (a[p, q] = 0), 1 a[p, q] set to zero, 2 a rotation (a[q, p] = 0, a[p, r] = a[r, p], a[q, r] = a[r, q])."""
    if apq == 0.0:
        return app, aqq, apq, arp, arq, 0
    g = 100.0 * abs(apq)
    if late and abs(app) + g == abs(app) and abs(aqq) + g == abs(aqq):
        return app, aqq, 0.0, arp, arq, 1
    h = aqq - app
    if abs(h) + g == abs(h):
        t = apq / h
    else:
        theta = 0.5 * h / apq
        t = 1.0 / (abs(theta) + math.sqrt(1.0 + theta * theta))
        if theta < 0.0:
            t = -t
    c = 1.0 / math.sqrt(1.0 + t * t)
    s = t * c
    tau = s / (1.0 + c)
    return app - t * apq, aqq + t * apq, 0.0, arp - s * (arq + arp * tau), arq + s * (arp - arq * tau), 2


@inner
def eigvalsh3(J):
    """Eigenvalues (ascending, three floats) of the symmetric 3×3 ``J`` by cyclic Jacobi
    rotations (the nine entries held as scalars; each rotation reads and writes the entries a
    rotation of the full matrix would, so a J that is not exactly symmetric gives the same)."""
    a00, a01, a02 = J[0, 0], J[0, 1], J[0, 2]
    a10, a11, a12 = J[1, 0], J[1, 1], J[1, 2]
    a20, a21, a22 = J[2, 0], J[2, 1], J[2, 2]
    for sweep in range(60):
        if a01 == 0.0 and a02 == 0.0 and a12 == 0.0:
            break
        late = sweep > 3
        # (p, q, r) = (0, 1, 2)
        a00, a11, a01, a20, a21, done = _rotate(a00, a11, a01, a20, a21, late)
        if done > 0:
            a10 = 0.0
        if done == 2:
            a02, a12 = a20, a21
        # (0, 2, 1)
        a00, a22, a02, a10, a12, done = _rotate(a00, a22, a02, a10, a12, late)
        if done > 0:
            a20 = 0.0
        if done == 2:
            a01, a21 = a10, a12
        # (1, 2, 0)
        a11, a22, a12, a01, a02, done = _rotate(a11, a22, a12, a01, a02, late)
        if done > 0:
            a21 = 0.0
        if done == 2:
            a10, a20 = a01, a02
    e0, e1, e2 = a00, a11, a22
    if e0 > e1:
        e0, e1 = e1, e0
    if e1 > e2:
        e1, e2 = e2, e1
    if e0 > e1:
        e0, e1 = e1, e0
    return e0, e1, e2


@inner
def inverse3(J, out, lu):
    """``out`` = J⁻¹ of a 3×3 matrix by an LU factorisation with partial pivoting (as LAPACK's
    gesv: error ~ cond(J) ε); ``lu``: scratch (3, 3)."""
    p0, p1, p2 = 0, 1, 2
    for i in range(3):
        for k in range(3):
            lu[i, k] = J[i, k]
    for k in range(2):
        best = k
        for i in range(k + 1, 3):
            best = i if abs(lu[i, k]) > abs(lu[best, k]) else best
        if best != k:
            for c in range(3):
                lu[k, c], lu[best, c] = lu[best, c], lu[k, c]
            if k == 0:
                p0, p1, p2 = (p1, p0, p2) if best == 1 else (p2, p1, p0)
            else:
                p1, p2 = p2, p1
        for i in range(k + 1, 3):
            lu[i, k] = lu[i, k] / lu[k, k]
            for c in range(k + 1, 3):
                lu[i, c] -= lu[i, k] * lu[k, c]
    for col in range(3):
        # Solve L U x = e_col permuted: b_i = 1 where the row came from ``col``.
        y0 = 1.0 * (p0 == col)
        y1 = 1.0 * (p1 == col) - lu[1, 0] * y0
        y2 = 1.0 * (p2 == col) - lu[2, 0] * y0 - lu[2, 1] * y1
        x2 = y2 / lu[2, 2]
        x1 = (y1 - lu[1, 2] * x2) / lu[1, 1]
        out[0, col] = (y0 - lu[0, 1] * x1 - lu[0, 2] * x2) / lu[0, 0]
        out[1, col] = x1
        out[2, col] = x2


@inner
def well_conditioned(J):
    """Whether the symmetric 3×3 ``J`` is surely positive definite with λ_min/λ_max above
    :data:`SURELY_OK_RCOND`, from its trace, leading minors and determinant alone (no
    eigenvalues): positive minors (Sylvester's criterion, each above its rounding) make J
    positive definite, and then λ_max ≤ tr J and λ_mid λ_max ≤ (tr J/2)², so λ_min/λ_max ≥
    4 det J/(tr J)³. False says nothing (the eigenvalues decide)."""
    tr = J[0, 0] + J[1, 1] + J[2, 2]
    if not (tr > 0.0 and J[0, 0] > 0.0):
        return False
    t2 = tr * tr
    t3 = t2 * tr
    m2 = J[0, 0] * J[1, 1] - J[0, 1] * J[1, 0]
    det = (
        J[0, 0] * (J[1, 1] * J[2, 2] - J[1, 2] * J[2, 1])
        - J[0, 1] * (J[1, 0] * J[2, 2] - J[1, 2] * J[2, 0])
        + J[0, 2] * (J[1, 0] * J[2, 1] - J[1, 1] * J[2, 0])
    )
    return m2 > MINOR_TOL * t2 and det > MINOR_TOL * t3 and 4.0 * det > SURELY_OK_RCOND * t3


@inner
def invert(J, inv, work, need_logdet):
    """Health, inverse and ln det of a symmetric 3×3 FIM (:func:`planner.fim.invert_fim`): the
    status code (λ_min ≤ 1e-12 λ_max, λ_max ≤ 0 or a non-finite entry: singular, ``inv`` zeros,
    ln det −inf; λ_min ≤ 1e-8 λ_max: ill-conditioned) and ln det J = Σ ln λ. ``inv``: (3, 3)
    out. Without ``need_logdet`` (the A criterion reads only the inverse and the status), a J
    that is :func:`well_conditioned` skips the eigenvalues: status OK, the same inverse, ln det
    NaN."""
    finite = True
    for i in range(3):
        for j in range(3):
            if not math.isfinite(J[i, j]):
                finite = False
    if not finite:
        for i in range(3):
            for j in range(3):
                inv[i, j] = 0.0
        return SINGULAR, -np.inf
    if not need_logdet and well_conditioned(J):
        inverse3(J, inv, work)
        return OK, np.nan
    e0, e1, e2 = eigvalsh3(J)
    rcond = e0 / e2 if e2 > 0.0 else 0.0
    if not e2 > 0.0 or rcond <= SINGULAR_RCOND:
        for i in range(3):
            for j in range(3):
                inv[i, j] = 0.0
        return SINGULAR, -np.inf
    inverse3(J, inv, work)
    status = ILL if rcond <= ILL_CONDITIONED_RCOND else OK
    return status, math.log(e0) + math.log(e1) + math.log(e2)


@inner
def invert_for_cost(J, inv, work, criterion_d):
    """:func:`invert` for the planning cost (:func:`criterion_derivative`): a J that is
    :func:`well_conditioned` skips the eigenvalues for either criterion (status OK, the same
    inverse); its ln det J, which only the D criterion reads, is then that of the inverse's LU
    factorisation, Σ ln |u_ii| (in ``work``), equal to Σ ln λ up to rounding (a few ε
    relative; the cost's value only, which no step reads: the gradient and the status are
    those of :func:`invert`). Elsewhere :func:`invert` itself."""
    if well_conditioned(J):
        inverse3(J, inv, work)
        if not criterion_d:
            return OK, np.nan
        return OK, math.log(abs(work[0, 0])) + math.log(abs(work[1, 1])) + math.log(abs(work[2, 2]))
    return invert(J, inv, work, criterion_d)


@inner
def add_fim_terms(src, positions, ranging, bearing, los_w, ch, J):
    """J += the range and bearing terms (eqs. 10-12) of the drones at ``positions`` (N, 3) seen
    from the source ``src`` (3,): ``ranging``, ``bearing`` (N,) bool (κ_j, β_j, and the view
    holds the record), ``los_w`` (N,) the LOS flag or weight q in [0, 1]; ``J`` (3, 3), m⁻²."""
    gamma, s2l, s2n, sb2 = ch[CH_GAMMA], ch[CH_S2_LOS], ch[CH_S2_NLOS], ch[CH_SB2]
    j00 = j01 = j02 = j11 = j12 = j22 = 0.0
    for j in range(positions.shape[0]):
        if not (ranging[j] or bearing[j]):
            continue
        rx = src[0] - positions[j, 0]
        ry = src[1] - positions[j, 1]
        rz = src[2] - positions[j, 2]
        rho2 = max(rx * rx + ry * ry, RHO_FLOOR_M * RHO_FLOOR_M)
        d2 = rho2 + rz * rz
        d = math.sqrt(d2)
        q = los_w[j]
        if ranging[j]:
            inv_s0sq = q / s2l + (1.0 - q) / s2n
            w = math.sqrt((d ** (-gamma) * inv_s0sq + gamma * gamma / (2.0 * d2)) / d2)
            ux, uy, uz = rx * w, ry * w, rz * w
            j00 += ux * ux
            j01 += ux * uy
            j02 += ux * uz
            j11 += uy * uy
            j12 += uy * uz
            j22 += uz * uz
        if bearing[j] and q != 0.0:
            wb = q / (sb2 * rho2)
            w = math.sqrt(wb / rho2)
            bx, by = -ry * w, rx * w
            j00 += bx * bx
            j01 += bx * by
            j11 += by * by
            w = math.sqrt(wb / (d2 * d2))
            vx, vy, vz = -rx * rz * w, -ry * rz * w, rho2 * w
            j00 += vx * vx
            j01 += vx * vy
            j02 += vx * vz
            j11 += vy * vy
            j12 += vy * vz
            j22 += vz * vz
    J[0, 0] += j00
    J[0, 1] += j01
    J[0, 2] += j02
    J[1, 0] += j01
    J[1, 1] += j11
    J[1, 2] += j12
    J[2, 0] += j02
    J[2, 1] += j12
    J[2, 2] += j22


@inner
def criterion_derivative(J, criterion_d, M, work):
    """The cost C of eq. 6 at ``J`` and M = ∂C/∂J to ``M`` (3, 3): C = tr J⁻¹, M = −J⁻² (A);
    C = −ln det J, M = −J⁻¹ (``criterion_d``). Returns (C, status); singular: (+inf, 2), M = 0.
    ``work``: scratch (2, 3, 3)."""
    inv = work[0]
    status, logdet = invert_for_cost(J, inv, work[1], criterion_d)
    for i in range(3):
        for k in range(3):
            mik = -(inv[i, 0] * inv[0, k] + inv[i, 1] * inv[1, k] + inv[i, 2] * inv[2, k])
            M[i, k] = -inv[i, k] if criterion_d else mik
    if status == SINGULAR:
        return np.inf, status
    return (-logdet if criterion_d else inv[0, 0] + inv[1, 1] + inv[2, 2]), status


@inner
def own_gradient(J, src, p, ranging, bearing, q, grad_q, use_grad_q, ch, criterion_d, grad, M, work):
    """Cost C of eq. 6 at ``J`` (``criterion_d``: −ln det J, else tr J⁻¹) and its gradient
    w.r.t. the drone's own position ``p`` (eq. 14), written to ``grad`` (3,): −∂ tr(M J_own)/∂r
    of the own range and bearing terms (r = src − p, M = ∂C/∂J, written to ``M`` (3, 3)) plus,
    if ``use_grad_q``, tr(M (J_own,LOS − J_own,NLOS)) ∇q (q the own LOS weight, ``grad_q``
    (3,), 1/m). Returns (C, status); a singular J gives (+inf, 2) and a zero gradient.
    ``work``: scratch (2, 3, 3)."""
    grad[0] = 0.0
    grad[1] = 0.0
    grad[2] = 0.0
    value, status = criterion_derivative(J, criterion_d, M, work)
    if status == SINGULAR:
        return value, status
    gamma, s2l, s2n, sb2 = ch[CH_GAMMA], ch[CH_S2_LOS], ch[CH_S2_NLOS], ch[CH_SB2]
    rx, ry, rz = src[0] - p[0], src[1] - p[1], src[2] - p[2]
    rho2 = max(rx * rx + ry * ry, RHO_FLOOR_M * RHO_FLOOR_M)
    d2 = rho2 + rz * rz
    d = math.sqrt(d2)
    gx = gy = gz = 0.0
    tr = 0.0
    if ranging:
        # J_r = h(d) r rᵀ: ∂ tr(M J_r)/∂r = (h'/d)(rᵀMr) r + 2h M r.
        mrx = rx * M[0, 0] + ry * M[1, 0] + rz * M[2, 0]
        mry = rx * M[0, 1] + ry * M[1, 1] + rz * M[2, 1]
        mrz = rx * M[0, 2] + ry * M[1, 2] + rz * M[2, 2]
        q_r = rx * mrx + ry * mry + rz * mrz
        inv_s0sq = q / s2l + (1.0 - q) / s2n
        h = d ** (-gamma) * inv_s0sq / d2 + gamma * gamma / (2.0 * d2 * d2)
        dh = (-gamma - 2.0) * d ** (-gamma - 3.0) * inv_s0sq - 2.0 * gamma * gamma / (d2 * d2 * d)
        c = dh / d * q_r
        gx = c * rx + 2.0 * h * mrx
        gy = c * ry + 2.0 * h * mry
        gz = c * rz + 2.0 * h * mrz
        tr = d ** (-gamma) * (1.0 / s2l - 1.0 / s2n) / d2 * q_r
    if bearing and (q != 0.0 or use_grad_q):
        # Azimuth w b bᵀ, b = (−r_y, r_x, 0), w = 1/(σ_b² ρ⁴); elevation c² v vᵀ/σ_b²,
        # v = (−r_x r_z, −r_y r_z, ρ²), c = 1/(d² ρ).
        bx, by = -ry, rx
        mbx = bx * M[0, 0] + by * M[1, 0]
        mby = bx * M[0, 1] + by * M[1, 1]
        q_b = bx * mbx + by * mby
        w_az = 1.0 / (sb2 * rho2 * rho2)
        k_az = 4.0 * w_az * q_b / rho2
        az_x = 2.0 * w_az * mby - k_az * rx
        az_y = 2.0 * w_az * -mbx - k_az * ry
        vx, vy, vz = -rx * rz, -ry * rz, rho2
        mvx = vx * M[0, 0] + vy * M[1, 0] + vz * M[2, 0]
        mvy = vx * M[0, 1] + vy * M[1, 1] + vz * M[2, 1]
        mvz = vx * M[0, 2] + vy * M[1, 2] + vz * M[2, 2]
        q_v = vx * mvx + vy * mvy + vz * mvz
        c2 = 1.0 / (d2 * d2 * rho2)
        m2 = -2.0 * c2
        el_x = (2.0 * c2 * (-rz * mvx + 2.0 * rx * mvz) + q_v * (m2 * (2.0 * rx / d2 + rx / rho2))) / sb2
        el_y = (2.0 * c2 * (-rz * mvy + 2.0 * ry * mvz) + q_v * (m2 * (2.0 * ry / d2 + ry / rho2))) / sb2
        el_z = (2.0 * c2 * (-rx * mvx - ry * mvy) + q_v * (m2 * (2.0 * rz / d2 + 0.0 / rho2))) / sb2
        gx += q * (az_x + el_x)
        gy += q * (az_y + el_y)
        gz += q * (0.0 + el_z)
        tr += w_az * q_b + c2 * q_v / sb2
    grad[0] = -gx
    grad[1] = -gy
    grad[2] = -gz
    if use_grad_q:
        grad[0] += tr * grad_q[0]
        grad[1] += tr * grad_q[1]
        grad[2] += tr * grad_q[2]
    return value, status


@njit(cache=True)
def fim_batch(src, positions, ranging, bearing, los_w, ch, J):
    """J (B, 3, 3) of B views, to ``J`` (zeros in): sources (B, 3), positions (B, N, 3), masks and
    LOS weights (B, N)."""
    for b in range(positions.shape[0]):
        add_fim_terms(src[b], positions[b], ranging[b], bearing[b], los_w[b], ch, J[b])


@njit(cache=True)
def cost_gradient_batch(J, src, p, ranging, bearing, q, grad_q, use_grad_q, ch, criterion_d, out):
    """:func:`own_gradient` of B drones: J (B, 3, 3), src, p (B, 3), ranging, bearing (B,) bool,
    q (B,), grad_q (B, 3). To ``out`` (B, 14): C, ∇C (3), the status code, M (9, row-major)."""
    work = np.empty((2, 3, 3))
    M = np.empty((3, 3))
    for b in range(J.shape[0]):
        value, status = own_gradient(J[b], src[b], p[b], ranging[b], bearing[b], q[b], grad_q[b], use_grad_q, ch, criterion_d, out[b, 1:4], M, work)
        out[b, 0], out[b, 4] = value, status
        for i in range(3):
            for k in range(3):
                out[b, 5 + 3 * i + k] = M[i, k]


@njit(cache=True)
def invert_batch(J, inv, out):
    """:func:`invert` of B FIMs (B, 3, 3): J⁻¹ to ``inv`` (B, 3, 3), (ln det J, status code) to
    ``out`` (B, 2)."""
    work = np.empty((3, 3))
    for b in range(J.shape[0]):
        status, logdet = invert(J[b], inv[b], work, True)
        out[b, 0], out[b, 1] = logdet, status


# =========================================================================== control step
UAV, SOURCE, OBSTACLE, ALTITUDE = 0, 1, 2, 3
#: Indices of the limits array (:func:`limits_array`).
L_DUAV, L_DSRC, L_DOBS, L_SMIN, L_SMAX, L_HMAX, L_TMAX, L_ZMIN, L_ZMAX, L_SAFE, L_TB = range(11)
L_LOITER_K, L_LOITER_REACH, L_SRC_MARGIN, L_SRC_MARGIN_EXACT, L_ALT_MARGIN, L_ALT_MARGIN_EXACT = range(11, 17)
L_SIZE = 17
#: From index L_TABLE: cos and sin of v φ_max for the loiter path's steps v = 1..K (:func:`loiter_vertices`).
L_TABLE = L_SIZE
#: Relative cut-off of the constraint normals' pseudo-inverse (eq. 14's (NᵀN)⁻¹).
PINV_RCOND: float = 1e-6
#: A projected gradient shorter than this fraction of the gradient is zero.
PG_REL_TOL: float = 1e-9
#: Candidate steps of the kinematic envelope: 9 headings × 5 tilts × 2 speeds, and the loiter's
#: first step to either side.
N_HEADINGS, N_TILTS = 9, 5
N_CANDIDATES = N_HEADINGS * N_TILTS * 2 + 2
#: Peers beyond which the filter scores only those that can be nearest after one step.
PRUNE_PEERS = 32
# Rows of the per-peer workspace (N-vectors): distance now (plane rows: to the plane), the
# constraint value less its margin, the strict, loose and hard requirements, the record
# clearance's, the plane flag (1.0: a lost peer's plane), the base requirement and the margin now.
W_DIST, W_GT, W_STRICT, W_LOOSE, W_HARD, W_REC, W_PLANE, W_BASE, W_NOW = range(9)
N_PEER_ROWS = 9
# Rows of the small vectors: the correction of eq. 14, the obstacle normal, a constraint normal,
# the active constraint values, the margins now and their needs (filter and certificate), a
# score, the selected values and columns.
V_CORR, V_NO, V_NRM, V_G, V_NOW, V_NEED, V_NOW_C, V_NEED_C, V_SCORE, V_SEL, V_COL = range(11)
N_VECTORS = 11
# Rows of the candidates' scores: −closeness, strict peer slack, the buffers (min of the peer and
# source slack), peer, source and obstacle slack, the exact and physical margins.
S_NEGCLOSE, S_STRICT_UAV, S_BUFFERS, S_SLACK_UAV, S_SLACK_SRC, S_SLACK_OBS, S_EXACT, S_EXACT_PHYS, S_PHYS_OBS = range(9)
N_SCORES = 9
# Rows of the candidates' pass masks: the tiers, the certificate, dead reckoning, scratch.
O_STRICT, O_SLACK, O_T3, O_T4, O_T5, O_T6, O_T7, O_T8, O_CERT, O_STRICT_CERT, O_RECK, O_EVERY, O_STRICT_RECK, O_BOTH, O_T5F, O_T5G = range(16)
N_MASKS = 16


def limits_array(values: tuple[float, ...], safe: bool, derived: tuple[float, ...]) -> np.ndarray:
    """The limits array ``lim`` of the kernels from ``values`` = (d_U*, d_S*, d_O*, v_min Δt,
    v_max Δt, φ_max, θ_max, z_min, z_max) (m, rad), the activation rule, and ``derived`` = (turn
    buffer b, loiter steps K, loiter reach, source activation margin about an estimate and about
    an exact source, altitude activation margin about an estimate and about an exact source), m."""
    return np.array(tuple(values) + (1.0 if safe else 0.0,) + tuple(derived), dtype=np.float64)


# --------------------------------------------------------------------------- small helpers
@inner
def spherical(x, y, z):
    """(length, heading Ψ from east, tilt Θ) of a step (eq. 1), m and rad."""
    return math.sqrt(x * x + y * y + z * z), math.atan2(y, x), math.atan2(z, math.hypot(x, y))


@inner
def cartesian(s, psi, theta):
    """The step of length s, heading Ψ and tilt Θ (eq. 1): s (cos Ψ cos Θ, sin Ψ cos Θ, sin Θ)."""
    sc = s * math.cos(theta)
    return sc * math.cos(psi), sc * math.sin(psi), s * math.sin(theta)


@inner
def tilt_buffer(tilt, lim):
    """Height (m) still climbed after a step of tilt Θ before the tilt can reach 0:
    v_max Δt Σ_{k=1..3} max(0, sin(Θ − k θ_max))."""
    tmax = lim[L_TMAX]
    total = _rising(tilt - 1.0 * tmax) + _rising(tilt - 2.0 * tmax)
    return lim[L_SMAX] * (total + _rising(tilt - 3.0 * tmax))


@inner
def _rising(x):
    """max(0, sin x), without evaluating sin where it is known to be ≤ 0: on [−3, 0] ⊂ [−π, 0]
    (sin x ≤ 0 there, and the libm sin keeps the sign: |sin x| ≥ min(|x|, sin 3) is far above its
    error), so max(0, sin x) = 0 exactly; NaN and every other x take the sine."""
    if (x <= 0.0) & (x >= -3.0):
        return 0.0
    return max(0.0, math.sin(x))


@inner
def altitude_margin(z, tilt, lim):
    """Margin (m) of a height z to the altitude box after a step of tilt Θ (:func:`tilt_buffer`)."""
    return min(lim[L_ZMAX] - z - tilt_buffer(tilt, lim), z - lim[L_ZMIN] - tilt_buffer(-tilt, lim))


@inner
def peer_distance(x, y, z, peers, planes, flags, j, d_uav):
    """Distance (m) of (x, y, z) to peer row j: Euclidean to a point row; (x − m)·n + d_U*/2 to a
    plane row (``flags[j]`` > 0: point m, unit normal n = ``planes[j]``;
    :func:`planner.control.peer_distance`)."""
    dx, dy, dz = x - peers[j, 0], y - peers[j, 1], z - peers[j, 2]
    if flags[j] > 0.0:
        return dx * planes[j, 0] + dy * planes[j, 1] + dz * planes[j, 2] + 0.5 * d_uav
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@inner
def peer_margin(x, y, z, peers, planes, flags, required, idx, n_idx, d_uav):
    """Smallest peer margin (m) of (x, y, z) over the peer rows ``idx[:n_idx]``: min_j d_j − required_j (+inf: none)."""
    best = np.inf
    for k in range(n_idx):
        j = idx[k]
        best = min(best, peer_distance(x, y, z, peers, planes, flags, j, d_uav) - required[j])
    return best


@inner
def score(x, y, z, tilt, peers, planes, flags, required, idx, n_idx, source, source_required, obstacle_required, bmin, bmax, lim, out):
    """Clearance margins (m) of the end position (x, y, z) of a step of tilt Θ, per family, to
    ``out`` (4,): nearest peer (``required`` per peer row), source, nearest obstacle, altitude
    box (with the height still climbed while the tilt swings back, :func:`tilt_buffer`)."""
    out[UAV] = peer_margin(x, y, z, peers, planes, flags, required, idx, n_idx, lim[L_DUAV])
    dx, dy, dz = x - source[0], y - source[1], z - source[2]
    out[SOURCE] = math.sqrt(dx * dx + dy * dy + dz * dz) - source_required
    out[OBSTACLE] = distance_to_boxes(x, y, z, bmin, bmax) - obstacle_required
    out[ALTITUDE] = altitude_margin(z, tilt, lim)


# --------------------------------------------------------------------------- eqs. 15-17 and 14
@inner
def _select3(sel, col, v, c):
    """Keep the three smallest values in ``sel`` (3,) with their columns in ``col``; a tie keeps
    the earlier column first (a stable sort's first three)."""
    if v < sel[2]:
        if v < sel[1]:
            sel[2], col[2] = sel[1], col[1]
            if v < sel[0]:
                sel[1], col[1] = sel[0], col[0]
                sel[0], col[0] = v, c
            else:
                sel[1], col[1] = v, c
        else:
            sel[2], col[2] = v, c


@inner(inline="always")
def constraints(p, peers, mask, age, planes, source, keepout, bmin, bmax, lim, source_exact, wn, vec, active):
    """Constraint values g = d − d* of eqs. 15-17 less their activation margins (safe rule: one
    step of both parties' motion and the turn-away buffers, docs/control.md): every peer (to
    ``wn[W_GT]``, with the distances to ``wn[W_DIST]`` and the plane flags to ``wn[W_PLANE]``),
    the source keep-out, the nearest obstacle (its normal to ``vec[V_NO]``) and, with the safe
    rule, the altitude box's faces; the three smallest to ``vec[V_SEL]``, ``vec[V_COL]``; the
    active families to ``active`` (4,). Returns the source and obstacle values g_s, g_o, m."""
    N = peers.shape[0]
    safe = lim[L_SAFE] > 0.5
    d_uav, smax, tb = lim[L_DUAV], lim[L_SMAX], lim[L_TB]
    sel, col = vec[V_SEL], vec[V_COL]
    for k in range(3):
        sel[k] = np.inf
        col[k] = -1.0
    any_uav = False
    for j in range(N):
        wn[W_PLANE, j] = 1.0 * ((planes[j, 0] != 0.0) | (planes[j, 1] != 0.0) | (planes[j, 2] != 0.0))
        wn[W_DIST, j] = peer_distance(p[0], p[1], p[2], peers, planes, wn[W_PLANE], j, d_uav)
        g = wn[W_DIST, j] - d_uav if mask[j] else np.inf
        if safe:
            g = g - (smax * (2.0 + age[j]) + 2.0 * tb)
        wn[W_GT, j] = g
        any_uav = any_uav | (g < 0.0)
        _select3(sel, col, g, float(j))
    dx, dy, dz = p[0] - source[0], p[1] - source[1], p[2] - source[2]
    g_s = math.sqrt(dx * dx + dy * dy + dz * dz) - keepout
    g_o = distance_to_boxes_with_gradient(p[0], p[1], p[2], bmin, bmax, vec[V_NO]) - lim[L_DOBS]
    gt_s, gt_o = g_s, g_o
    if safe:
        gt_s = g_s - (lim[L_SRC_MARGIN_EXACT] if source_exact else lim[L_SRC_MARGIN])
        gt_o = g_o - lim[L_SRC_MARGIN]
    _select3(sel, col, gt_s, float(N))
    _select3(sel, col, gt_o, float(N + 1))
    active[UAV], active[SOURCE], active[OBSTACLE], active[ALTITUDE] = any_uav, gt_s < 0.0, gt_o < 0.0, False
    if safe:
        alt_m = lim[L_ALT_MARGIN_EXACT] if source_exact else lim[L_ALT_MARGIN]
        top, bottom = lim[L_ZMAX] - p[2] - alt_m, p[2] - lim[L_ZMIN] - alt_m
        _select3(sel, col, top, float(N + 2))
        _select3(sel, col, bottom, float(N + 3))
        active[ALTITUDE] = (top < 0.0) | (bottom < 0.0)
    return g_s, g_o


@inner
def _normal(c, p, peers, planes, wn, source, vec):
    """Unit normal w.r.t. p of constraint column ``c`` (peers, source, obstacle, altitude top,
    altitude bottom) to ``vec[V_NRM]``."""
    N = peers.shape[0]
    out = vec[V_NRM]
    if c < N:
        dj = max(wn[W_DIST, c], 0.0)
        dj = dj + 1.0 * (dj == 0.0)
        for a in range(3):
            out[a] = planes[c, a] if wn[W_PLANE, c] > 0.0 else (p[a] - peers[c, a]) / dj
    elif c == N:
        dx, dy, dz = p[0] - source[0], p[1] - source[1], p[2] - source[2]
        ds = math.sqrt(dx * dx + dy * dy + dz * dz)
        ds = ds + 1.0 * (ds == 0.0)
        out[0], out[1], out[2] = dx / ds, dy / ds, dz / ds
    elif c == N + 1:
        out[0], out[1], out[2] = vec[V_NO, 0], vec[V_NO, 1], vec[V_NO, 2]
    else:
        out[0], out[1], out[2] = 0.0, 0.0, 2.0 * (c == N + 3) - 1.0


@inner(inline="always")
def _orthogonalise(U, V, m):
    """One-sided Jacobi SVD of the 3 × m matrix ``U`` (in place; ``V`` (3, 3) the accumulated
    rotations): afterwards U's columns are orthogonal and A = U Vᵀ."""
    for i in range(3):
        for k in range(3):
            V[i, k] = 1.0 * (i == k)
    for _ in range(30):
        rotated = False
        for i in range(m):
            for k in range(i + 1, m):
                a = U[0, i] * U[0, i] + U[1, i] * U[1, i] + U[2, i] * U[2, i]
                b = U[0, k] * U[0, k] + U[1, k] * U[1, k] + U[2, k] * U[2, k]
                g = U[0, i] * U[0, k] + U[1, i] * U[1, k] + U[2, i] * U[2, k]
                if abs(g) <= 1e-17 * math.sqrt(a * b):
                    continue
                rotated = True
                zeta = (b - a) / (2.0 * g)
                t = math.copysign(1.0, zeta) / (abs(zeta) + math.sqrt(1.0 + zeta * zeta))
                c = 1.0 / math.sqrt(1.0 + t * t)
                s = c * t
                for r in range(3):
                    U[r, i], U[r, k] = c * U[r, i] - s * U[r, k], s * U[r, i] + c * U[r, k]
                    V[r, i], V[r, k] = c * V[r, i] - s * V[r, k], s * V[r, i] + c * V[r, k]
        if not rotated:
            break


@inner
def projection(A, g, m, P, corr, V):
    """Eq. 14's projection onto the m active constraints of unit normals A[:, :m] (3 × m) and
    values g[:m]: P = I − N (NᵀN)⁻¹ Nᵀ to ``P`` (3, 3) and the correction −N (NᵀN)⁻¹ g to
    ``corr`` (3,), m, with a pseudo-inverse (singular values up to 1e-6 of the largest count as
    zero, so nearly parallel normals keep P well conditioned). ``A`` is overwritten."""
    _orthogonalise(A, V, m)
    top = 0.0
    for i in range(m):
        top = max(top, math.sqrt(A[0, i] * A[0, i] + A[1, i] * A[1, i] + A[2, i] * A[2, i]))
    for i in range(3):
        corr[i] = 0.0
        for k in range(3):
            P[i, k] = 1.0 * (i == k)
    for i in range(m):
        sig = math.sqrt(A[0, i] * A[0, i] + A[1, i] * A[1, i] + A[2, i] * A[2, i])
        if not sig > PINV_RCOND * top:
            continue
        vg = 0.0
        for r in range(m):
            vg += V[r, i] * g[r]
        for r in range(3):
            ur = A[r, i] / sig
            for k in range(3):
                P[r, k] -= ur * (A[k, i] / sig)
            corr[r] -= ur * (vg / sig)


@inner
def active_projection(p, peers, planes, wn, source, vec, m33):
    """P (``m33[2]``) and the correction (``vec[V_CORR]``) of eq. 14 over the active ones among
    the three most violated constraints (:func:`constraints`); returns whether any is active."""
    A, V, P = m33[0], m33[1], m33[2]
    m = np.int64(0)
    for k in range(3):
        if vec[V_SEL, k] < 0.0:
            _normal(int(vec[V_COL, k]), p, peers, planes, wn, source, vec)
            for a in range(3):
                A[a, m] = vec[V_NRM, a]
            vec[V_G, m] = vec[V_SEL, k]
            m += 1
    if m > 0:
        projection(A, vec[V_G], m, P, vec[V_CORR], V)
        return True
    for i in range(3):
        vec[V_CORR, i] = 0.0
        for k in range(3):
            P[i, k] = 1.0 * (i == k)
    return False


@inner
def _mul(P, x, y, z):
    """P (x, y, z) for a 3 × 3 P."""
    return P[0, 0] * x + P[0, 1] * y + P[0, 2] * z, P[1, 0] * x + P[1, 1] * y + P[1, 2] * z, P[2, 0] * x + P[2, 1] * y + P[2, 2] * z


@inner
def descent(grad, P, projected, xi, lim):
    """The gradient step −ξ P∇C of eq. 14, m (P applied where ``projected``): ξ given (``xi``, m
    per unit gradient), or (``xi`` NaN) normalised to v_max Δt; a projected gradient up to 1e-9
    of the gradient is zero."""
    gx, gy, gz = grad[0], grad[1], grad[2]
    px, py, pz = gx, gy, gz
    if projected:
        px, py, pz = _mul(P, gx, gy, gz)
    pg = math.sqrt(px * px + py * py + pz * pz)
    keep = 1.0 * (pg > PG_REL_TOL * math.sqrt(gx * gx + gy * gy + gz * gz))
    px, py, pz, pg = px * keep, py * keep, pz * keep, pg * keep
    if math.isnan(xi):
        k = pg + 1.0 * (pg == 0.0)
        smax = lim[L_SMAX]
        return -smax * px / k, -smax * py / k, -smax * pz / k
    return -xi * px, -xi * py, -xi * pz


@inner
def limited_step(grad, status, prev, uni, projected, P, corr, xi, pert, lim, u):
    """Steps 2-3 of one drone's step: the descent of eq. 14 (or, with a singular J, the paper's
    fallback: the last heading and tilt perturbed uniformly by ±``pert`` rad, a random heading
    before the first step), plus the correction, under the kinematic limits of eq. 2 (length in
    [v_min, v_max] Δt, heading and tilt changes within φ_max, θ_max of ``prev``); the step to
    ``u`` (3,), m. Returns (singular, the step's tilt Θ, whether there was a previous step)."""
    smin, smax, hmax, tmax = lim[L_SMIN], lim[L_SMAX], lim[L_HMAX], lim[L_TMAX]
    prev_s, prev_psi, prev_theta = spherical(prev[0], prev[1], prev[2])
    has_prev = prev_s > 0.0
    singular = status == SINGULAR
    if singular:
        psi_r = prev_psi + (2.0 * uni[0] - 1.0) * pert if has_prev else 2.0 * math.pi * uni[0]
        th_r = min(max(prev_theta + (2.0 * uni[1] - 1.0) * pert, -0.5 * math.pi), 0.5 * math.pi) if has_prev else 0.0
        ux, uy, uz = cartesian(smax, psi_r, th_r)
        if projected:
            ux, uy, uz = _mul(P, ux, uy, uz)
    else:
        ux, uy, uz = descent(grad, P, projected, xi, lim)
    s, psi, theta = spherical(ux + corr[0], uy + corr[1], uz + corr[2])
    if s < 1e-12:
        psi, theta = prev_psi, prev_theta
    s = min(max(s, smin), smax)
    if has_prev:
        psi = prev_psi + min(max((psi - prev_psi + math.pi) % (2.0 * math.pi) - math.pi, -hmax), hmax)
        theta = min(max(theta, prev_theta - tmax), prev_theta + tmax)
    u[0], u[1], u[2] = cartesian(s, psi, theta)
    return singular, theta, has_prev


# --------------------------------------------------------------------------- the safety filter's requirements
@inner(inline="always")
def requirements(peers, mask, age, drift, g_s, g_o, p_z, lim, wn, reck, vec):
    """The safety filter's requirements (docs/control.md, "Safety filter").

    Per peer j of age a_j: the reachable ball of its record, d_U* + (a_j + 1) v_max Δt + 2b at the
    end of the step; a margin already in deficit may not shrink (strict: against the ball of now;
    loose: against the end-of-step ball; hard: without the turn-away buffers 2b), the bisector
    planes of a partition together (each may come back to the worst of them). To ``wn``'s
    W_STRICT, W_LOOSE, W_HARD rows; the dead-reckoned positions of the peers whose reachable ball
    the drone is inside, now and at the end of the step, to ``reck`` (2, N, 3) (NaN: none); the
    margins now and what a step must keep, per family, to ``vec[V_NOW]``, ``vec[V_NEED]``, and
    those of the loiter certificate (the reachable balls, the keep-out, d_O* + v_min Δt/2, the
    altitude box) to ``vec[V_NOW_C]``, ``vec[V_NEED_C]``."""
    N = peers.shape[0]
    d_uav, smin, smax, tb = lim[L_DUAV], lim[L_SMIN], lim[L_SMAX], lim[L_TB]
    plane_now = np.inf
    for j in range(N):
        req = d_uav + (age[j] + 1.0) * smax + 2.0 * tb if mask[j] else -np.inf
        g = wn[W_DIST, j] - d_uav if mask[j] else np.inf
        wn[W_BASE, j] = req
        wn[W_NOW, j] = g - (req - d_uav)
        if wn[W_PLANE, j] > 0.0:
            plane_now = min(plane_now, wn[W_NOW, j])
    now, need = vec[V_NOW], vec[V_NEED]
    now[UAV] = np.inf
    for j in range(N):
        point = wn[W_PLANE, j] == 0.0
        eff = wn[W_NOW, j] if point else min(wn[W_NOW, j], plane_now)
        need_j = min(eff + smax * point, 0.0)
        now[UAV] = min(now[UAV], wn[W_NOW, j] - need_j)
        wn[W_STRICT, j] = wn[W_BASE, j] + need_j
        wn[W_LOOSE, j] = wn[W_BASE, j] + min(eff, 0.0)
        wn[W_HARD, j] = wn[W_BASE, j] - 2.0 * tb + min(eff + 2.0 * tb, 0.0)
        inside = point & mask[j] & (eff + 2.0 * tb < 0.0)
        inside = inside & math.isfinite(drift[j, 0]) & math.isfinite(drift[j, 1]) & math.isfinite(drift[j, 2])
        for a in range(3):
            reck[0, j, a] = peers[j, a] + age[j] * drift[j, a] if inside else np.nan
            reck[1, j, a] = reck[0, j, a] + drift[j, a]
    obstacle_required = lim[L_DOBS] + 0.5 * smax + tb
    now[SOURCE] = g_s - tb
    now[OBSTACLE] = g_o - (obstacle_required - lim[L_DOBS])
    now[ALTITUDE] = min(lim[L_ZMAX] - p_z, p_z - lim[L_ZMIN])
    now_c, need_c = vec[V_NOW_C], vec[V_NEED_C]
    now_c[UAV] = np.inf
    for j in range(N):
        now_c[UAV] = min(now_c[UAV], wn[W_DIST, j] - wn[W_HARD, j])
    now_c[SOURCE] = g_s
    now_c[OBSTACLE] = g_o - 0.5 * smin
    now_c[ALTITUDE] = now[ALTITUDE]
    for f in range(4):
        need[f] = min(now[f], 0.0)
        need_c[f] = min(now_c[f], 0.0)
    need[UAV] = 0.0


@inner
def kept_peers(wn, idx, lim, prune):
    """The peer rows the filter scores, to ``idx``; returns their number. All, or (``prune``) only
    those whose clearance now is within 2 (v_max Δt + the loiter's reach) of the smallest, per
    requirement variant: the others can never be the nearest after one step (exact)."""
    N = wn.shape[1]
    if not prune:
        for j in range(N):
            idx[j] = j
        return N
    span = 2.0 * (lim[L_SMAX] + lim[L_LOITER_REACH]) + 1e-6
    m_s = m_l = m_h = np.inf
    for j in range(N):
        m_s = min(m_s, wn[W_DIST, j] - wn[W_STRICT, j])
        m_l = min(m_l, wn[W_DIST, j] - wn[W_LOOSE, j])
        m_h = min(m_h, wn[W_DIST, j] - wn[W_HARD, j])
    n = 0
    for j in range(N):
        keep = (wn[W_DIST, j] - wn[W_STRICT, j] <= m_s + span) | (wn[W_DIST, j] - wn[W_LOOSE, j] <= m_l + span)
        if keep | (wn[W_DIST, j] - wn[W_HARD, j] <= m_h + span):
            idx[n] = j
            n += 1
    return n


# --------------------------------------------------------------------------- the loiter certificate
@inner
def loiter_heading(sx, sy, sz):
    """cos Ψ, sin Ψ and the tilt Θ of the step (sx, sy, sz) that a loiter path follows (Ψ = 0 for a
    vertical step)."""
    rho = math.hypot(sx, sy)
    cp, sp = (sx / rho, sy / rho) if rho > 0.0 else (1.0, 0.0)
    return cp, sp, math.atan2(sz, rho)


@inner
def loiter_side(ex, ey, ez, cp, sp, theta, side, lim, out):
    """One loiter path (``side`` 0: left, 1: right) of :func:`loiter_vertices` to ``out[side]``."""
    K = int(lim[L_LOITER_K])
    smin, tmax = lim[L_SMIN], lim[L_TMAX]
    sgn = 1.0 if theta > 0.0 else (-1.0 if theta < 0.0 else 0.0)
    turn = 1.0 - 2.0 * side
    out[side, 0, 0], out[side, 0, 1], out[side, 0, 2] = ex, ey, ez
    cx = cy = cz = 0.0
    for v in range(1, K + 1):
        ca, sa = lim[L_TABLE + 2 * v - 2], turn * lim[L_TABLE + 2 * v - 1]
        th_v = sgn * max(abs(theta) - v * tmax, 0.0) if tmax > 0.0 else theta
        ct, st = (math.cos(th_v), math.sin(th_v)) if th_v != 0.0 else (1.0, 0.0)
        sc = smin * ct
        cx, cy, cz = cx + sc * (cp * ca - sp * sa), cy + sc * (sp * ca + cp * sa), cz + smin * st
        out[side, v, 0], out[side, v, 1], out[side, v, 2] = ex + cx, ey + cy, ez + cz


@inner
def loiter_vertices(ex, ey, ez, sx, sy, sz, lim, out):
    """The loiter paths (:func:`planner.control.loiter_path`) from the end (ex, ey, ez) of the step
    (sx, sy, sz) to ``out`` (2, K + 1, 3): per side (left, right) the end itself, then K steps of
    v_min Δt at the step's heading Ψ ± v φ_max (cos and sin of v φ_max from the limits' table),
    the tilt Θ returning to level at θ_max per step."""
    cp, sp, theta = loiter_heading(sx, sy, sz)
    for side in range(2):
        loiter_side(ex, ey, ez, cp, sp, theta, side, lim, out)


@inner
def certified(ex, ey, ez, sx, sy, sz, peers, planes, wn, idx, n_idx, source, source_required, obstacle_required, need, bmin, bmax, lim, cw):
    """Whether a loiter path (:func:`loiter_vertices`) from the end position (ex, ey, ez) after the
    step (sx, sy, sz) keeps every clearance of the loiter certificate (the peers' reachable balls
    ``wn[W_HARD]``, the keep-out ``source_required``, ``obstacle_required`` from the obstacles,
    the altitude box) at least by ``need`` (4,), to the left or to the right. A peer, the source,
    a building or the altitude box whose margin at the end exceeds its need by the loiter's reach
    is not scored along the path (every clearance is 1-Lipschitz: exact). ``cw``: scratch (peer
    rows (N,), boxes (B,), vertices (2, K + 1, 3))."""
    if int(lim[L_LOITER_K]) == 0:
        return True
    on_peers, on_boxes, verts = cw
    reach = lim[L_LOITER_REACH] + 1e-9
    d_uav, hard, flags = lim[L_DUAV], wn[W_HARD], wn[W_PLANE]
    n_on = 0
    for k in range(n_idx):
        j = idx[k]
        if peer_distance(ex, ey, ez, peers, planes, flags, j, d_uav) - hard[j] - reach < need[UAV]:
            on_peers[n_on] = j
            n_on += 1
    b_on = 0
    for b in range(bmin.shape[0]):
        if box_signed_distance(ex, ey, ez, bmin, bmax, b) - obstacle_required - reach < need[OBSTACLE]:
            on_boxes[b_on] = b
            b_on += 1
    dx, dy, dz = ex - source[0], ey - source[1], ez - source[2]
    src_on = math.sqrt(dx * dx + dy * dy + dz * dz) - source_required - reach < need[SOURCE]
    alt_on = min(lim[L_ZMAX] - ez, ez - lim[L_ZMIN]) - reach < need[ALTITUDE]
    if (n_on == 0) & (b_on == 0) & (not src_on) & (not alt_on):
        return True
    cp, sp, theta = loiter_heading(sx, sy, sz)
    for side in range(2):
        loiter_side(ex, ey, ez, cp, sp, theta, side, lim, verts)  # the right path only where the left fails
        ok = True
        for v in range(verts.shape[1]):
            x, y, z = verts[side, v, 0], verts[side, v, 1], verts[side, v, 2]
            for k in range(n_on):
                j = on_peers[k]
                ok = ok & (peer_distance(x, y, z, peers, planes, flags, j, d_uav) - hard[j] >= need[UAV])
            for k in range(b_on):
                ok = ok & (box_signed_distance(x, y, z, bmin, bmax, on_boxes[k]) - obstacle_required >= need[OBSTACLE])
            dx, dy, dz = x - source[0], y - source[1], z - source[2]
            ok = ok & ((not src_on) | (math.sqrt(dx * dx + dy * dy + dz * dz) - source_required >= need[SOURCE]))
            ok = ok & ((not alt_on) | (min(lim[L_ZMAX] - z, z - lim[L_ZMIN]) >= need[ALTITUDE]))
            if not ok:
                break
        if ok:
            return True
    return False


# --------------------------------------------------------------------------- the envelope search
@inner
def envelope_candidates(prev, has_prev, lim, cand, th):
    """The kinematic envelope's candidate steps to ``cand`` (C, 3), m, and their tilts to ``th``
    (C,), rad: 9 headings × 5 tilts across the allowed turn from the previous step ``prev`` (a
    full circle of headings, tilts within ±θ_max of level, before the first step) × {v_min,
    v_max} Δt (index (heading · 5 + tilt) · 2 + speed), then the loiter path's first step to
    either side (:func:`planner.control.loiter_path`)."""
    _, prev_psi, prev_theta = spherical(prev[0], prev[1], prev[2])
    hmax, tmax = lim[L_HMAX], lim[L_TMAX]
    c = 0
    for h in range(N_HEADINGS):
        fh = -1.0 + 0.25 * h
        psi = prev_psi + fh * hmax if has_prev else math.pi * (fh + 1.0)
        for t in range(N_TILTS):
            ft = -1.0 + 0.5 * t
            theta = min(max(prev_theta + ft * tmax, -0.5 * math.pi), 0.5 * math.pi) if has_prev else ft * tmax
            for sp in range(2):
                cand[c, 0], cand[c, 1], cand[c, 2] = cartesian(lim[L_SMIN + sp], psi, theta)
                th[c] = theta
                c += 1
    sgn = 1.0 if prev_theta > 0.0 else (-1.0 if prev_theta < 0.0 else 0.0)
    level = sgn * max(abs(prev_theta) - tmax, 0.0)
    for side in range(2):
        cand[c, 0], cand[c, 1], cand[c, 2] = cartesian(lim[L_SMIN], prev_psi + (1.0 - 2.0 * side) * hmax, level)
        th[c] = level
        c += 1


@inner
def peer_margins(x, y, z, peers, planes, wn, idx, n_idx, d_uav):
    """The smallest peer margins (m) of (x, y, z) over the peer rows ``idx[:n_idx]`` against the
    strict, loose, hard and record-clearance requirements (rows of ``wn``), each distance once."""
    m_s = m_l = m_h = m_r = np.inf
    flags = wn[W_PLANE]
    for k in range(n_idx):
        j = idx[k]
        d = peer_distance(x, y, z, peers, planes, flags, j, d_uav)
        m_s, m_l = min(m_s, d - wn[W_STRICT, j]), min(m_l, d - wn[W_LOOSE, j])
        m_h, m_r = min(m_h, d - wn[W_HARD, j]), min(m_r, d - wn[W_REC, j])
    return m_s, m_l, m_h, m_r


@inner
def envelope_scores(p, u, need, peers, planes, wn, idx, n_idx, source, keepout, bmin, bmax, lim, cand, th, mc, wc, okc):
    """Per candidate step c of ``cand``: its margins per family (the peers' against the loose
    requirements, ``mc[0, c]``), its slack over ``need`` (``mc[1, c]``), the scores the tiers
    maximise (rows ``S_*`` of ``wc``) and which tiers it passes (rows ``O_*`` of ``okc``; the dead
    reckoning comes after, docs/control.md). The record clearance's requirements are in
    ``wn[W_REC]`` (:func:`record_requirements`)."""
    smax, tb = lim[L_SMAX], lim[L_TB]
    source_required = keepout + tb
    obstacle_required = lim[L_DOBS] + 0.5 * smax + tb
    # The keep-out's floor (tiers 5 and 5'): d_S* + its fixed inflation, never more than the
    # keep-out itself; a drone already inside it may not come nearer.
    floor_r = min(keepout_floor(lim), keepout)
    dx, dy, dz = p[0] - source[0], p[1] - source[1], p[2] - source[2]
    floor_need = min(math.sqrt(dx * dx + dy * dy + dz * dz) - floor_r, 0.0)
    margins, slack = mc[0], mc[1]
    for c in range(cand.shape[0]):
        x, y, z = p[0] + cand[c, 0], p[1] + cand[c, 1], p[2] + cand[c, 2]
        m_s, m_l, m_h, m_r = peer_margins(x, y, z, peers, planes, wn, idx, n_idx, lim[L_DUAV])
        dx, dy, dz = x - source[0], y - source[1], z - source[2]
        dist = math.sqrt(dx * dx + dy * dy + dz * dz)
        src_floor = dist - floor_r >= floor_need
        margins[c, SOURCE] = dist - source_required
        margins[c, OBSTACLE] = distance_to_boxes(x, y, z, bmin, bmax) - obstacle_required
        margins[c, ALTITUDE] = altitude_margin(z, th[c], lim)
        margins[c, UAV] = m_s
        ok = True
        for f in range(4):
            ok = ok & (margins[c, f] - need[f] >= 0.0)
        okc[O_STRICT, c] = ok
        wc[S_STRICT_UAV, c] = m_s - need[UAV]
        margins[c, UAV] = m_l
        ok = True
        for f in range(4):
            slack[c, f] = margins[c, f] - need[f]
            ok = ok & (slack[c, f] >= 0.0)
        okc[O_SLACK, c] = ok
        uav_hard = m_h >= 0.0
        src_hard = margins[c, SOURCE] + tb >= min(need[SOURCE] + tb, 0.0)
        phys_obstacle = slack[c, OBSTACLE] + 0.5 * smax + tb
        exact = min(slack[c, OBSTACLE], slack[c, ALTITUDE])
        wc[S_EXACT_PHYS, c] = min(min(phys_obstacle, 0.5 * smax + tb), min(lim[L_ZMAX] - z, z - lim[L_ZMIN]) - min(need[ALTITUDE], 0.0))
        dx, dy, dz = cand[c, 0] - u[0], cand[c, 1] - u[1], cand[c, 2] - u[2]
        wc[S_NEGCLOSE, c] = -(dx * dx + dy * dy + dz * dz)
        wc[S_BUFFERS, c] = min(slack[c, UAV], slack[c, SOURCE])
        wc[S_SLACK_UAV, c], wc[S_SLACK_SRC, c], wc[S_SLACK_OBS, c], wc[S_EXACT, c] = slack[c, UAV], slack[c, SOURCE], slack[c, OBSTACLE], exact
        okc[O_T3, c] = (exact >= 0.0) & uav_hard & src_hard
        okc[O_T4, c] = (exact >= 0.0) & src_hard & (m_r >= 0.0)
        okc[O_T5F, c] = (exact >= 0.0) & uav_hard & src_floor
        okc[O_T5G, c] = (exact >= 0.0) & src_floor
        okc[O_T5, c] = (exact >= 0.0) & uav_hard
        okc[O_T6, c] = exact >= 0.0
        okc[O_T7, c] = (phys_obstacle >= 0.0) & (slack[c, ALTITUDE] >= 0.0)
        okc[O_T8, c] = wc[S_EXACT_PHYS, c] >= 0.0
        okc[O_EVERY, c] = True
        okc[O_CERT, c] = False


@inner
def record_requirements(p, peers, planes, wn, idx, n_idx, lim):
    """The record clearance's requirements to ``wn[W_REC]`` (tier 4 of the envelope search): every
    peer's clearance as if its record were of now, d_U* + v_max Δt from a heard peer's record, the
    own side of a lost peer's plane; a drone already nearer (or inside the peer's reachable ball,
    ``wn[W_HARD]``) may not come nearer (docs/control.md, the tier that gives up the peers' balls)."""
    d_uav, smax = lim[L_DUAV], lim[L_SMAX]
    for k in range(n_idx):
        j = idx[k]
        now = peer_distance(p[0], p[1], p[2], peers, planes, wn[W_PLANE], j, d_uav)
        plane = wn[W_PLANE, j] > 0.0
        required = 0.5 * d_uav if plane else d_uav + smax
        inside = (now - wn[W_HARD, j] <= 1e-9) & (not plane)
        required = now if inside else min(required, now)
        wn[W_REC, j] = required if math.isfinite(wn[W_HARD, j]) else -np.inf


@inner
def dead_reckoning_kept(p, cand, reck, idx, n_idx, lim, ok):
    """``ok`` (C,): the candidates that do not bring the drone nearer the dead-reckoned position
    of a peer whose reachable ball it is inside (``reck``: now and at the end of the step):
    |p + u − r_j'| ≥ min(|p − r_j|, d_U* + 2 v_max Δt + 2b)
    (docs/control.md, "Where a peer is likely to be"). Returns False (``ok`` untouched) where no peer
    has one."""
    floor_max = lim[L_DUAV] + 2.0 * lim[L_SMAX] + 2.0 * lim[L_TB]
    known = False
    for c in range(cand.shape[0]):
        ok[c] = True
    for k in range(n_idx):
        j = idx[k]
        if not (math.isfinite(reck[0, j, 0]) & math.isfinite(reck[0, j, 1]) & math.isfinite(reck[0, j, 2])):
            continue
        known = True
        dx, dy, dz = p[0] - reck[0, j, 0], p[1] - reck[0, j, 1], p[2] - reck[0, j, 2]
        floor = min(math.sqrt(dx * dx + dy * dy + dz * dz), floor_max)
        for c in range(cand.shape[0]):
            ex = p[0] + cand[c, 0] - reck[1, j, 0]
            ey = p[1] + cand[c, 1] - reck[1, j, 1]
            ez = p[2] + cand[c, 2] - reck[1, j, 2]
            ok[c] = ok[c] & (math.sqrt(ex * ex + ey * ey + ez * ez) >= floor)
    return known


@inner
def _top_first(eligible, scores, order):
    """The eligible candidates to ``order``, the five of best score first (ties in order of index,
    as a stable sort), the rest after; returns their number."""
    n = 0
    for c in range(eligible.shape[0]):
        if eligible[c]:
            order[n] = c
            n += 1
    for a in range(min(5, n)):
        best = a
        for b in range(a + 1, n):
            better = (scores[order[b]] > scores[order[best]]) | ((scores[order[b]] == scores[order[best]]) & (order[b] < order[best]))
            best = b if better else best
        order[a], order[best] = order[best], order[a]
    return n


@inner
def certified_lazily(p, cand, eligible, scores, marks, order, cert):
    """Check the eligible candidates of one lazy tier for a loiter certificate, best score first,
    in chunks of 1, 4 and the rest, until a chunk holds a certified one; mark those in ``marks``
    (C,). Returns whether one was found (the picks of tiers 0 and 0' need no more). ``cert``:
    the certificate's clearances (the arguments of :func:`certified` after the step)."""
    n = _top_first(eligible, scores, order)
    for lo, hi in ((0, 1), (1, 5), (5, cand.shape[0])):
        found = False
        for a in range(lo, min(hi, n)):
            c = order[a]
            if certified(p[0] + cand[c, 0], p[1] + cand[c, 1], p[2] + cand[c, 2], cand[c, 0], cand[c, 1], cand[c, 2], *cert):
                marks[c] = True
                found = True
        if found:
            return True
    return False


@inner
def _argmax_where(ok, scores):
    """numpy's argmax of where(ok, scores, −inf): the first index of the largest value."""
    pick = 0
    best = scores[0] if ok[0] else -np.inf
    for c in range(1, ok.shape[0]):
        v = scores[c] if ok[c] else -np.inf
        pick = c if v > best else pick
        best = max(best, v)
    return pick


@inner
def envelope_pick(okc, wc, has_reck):
    """The envelope search's pick: the first tier (most demanding first) that some candidate
    passes, its best score; each tier first among the candidates that keep clear of the peers'
    dead-reckoned positions (``has_reck``); else the largest physical margin."""
    tiers = (
        (O_STRICT_CERT, S_NEGCLOSE),  # 0. every clearance with its buffers, and a loiter certificate
        (O_CERT, S_BUFFERS),  # 0'. a loiter certificate, the buffers given up
        (O_STRICT, S_NEGCLOSE),  # 1. every clearance with its buffers, the peers' balls of now
        (O_SLACK, S_STRICT_UAV),  # 2. the peers' requirements loose
        (O_T3, S_BUFFERS),  # 3. the peers' and the source's turn-away buffers relaxed
        (O_T4, S_SLACK_UAV),  # 4. the peers' balls beyond d_U* + v_max Δt of their records given up
        (O_T5F, S_SLACK_SRC),  # 5. the source keep-out relaxed to its floor, the peers' balls kept
        (O_T5G, S_SLACK_UAV),  # 5'. the peers' balls given up, the keep-out's floor kept
        (O_T5, S_SLACK_SRC),  # 5''. the source keep-out relaxed, the peers' balls kept
        (O_T6, S_BUFFERS),  # 6. the peers relaxed too
        (O_T7, S_SLACK_OBS),  # 7. the obstacle buffers relaxed
        (O_T8, S_EXACT),  # 8. every buffer relaxed
    )
    both = okc[O_BOTH]
    for ok_row, score_row in tiers:
        ok = okc[ok_row]
        if has_reck:
            any_both = False
            for c in range(ok.shape[0]):
                both[c] = ok[c] & okc[O_RECK, c]
                any_both = any_both | both[c]
            if any_both:
                return _argmax_where(both, wc[score_row])
        for c in range(ok.shape[0]):
            if ok[c]:
                return _argmax_where(ok, wc[score_row])
    return _argmax_where(okc[O_EVERY], wc[S_EXACT_PHYS])


@inner
def envelope_search(p, u, prev, has_prev, need, peers, planes, wn, reck, idx, n_idx, source, keepout, cert, env):
    """The best step of the kinematic envelope for a drone at ``p`` whose limited step ``u`` failed
    the safety filter (docs/control.md, "Safety filter"); the step to
    ``u``. Returns (infeasible: no candidate keeps every clearance with the loose peer
    requirements, the pick: its margins (4,) with the peers' against them are ``env[2][0, pick]``)."""
    cand, th, mc, wc, okc, order = env
    bmin, bmax, lim = cert[9], cert[10], cert[11]
    C = cand.shape[0]
    envelope_candidates(prev, has_prev, lim, cand, th)
    record_requirements(p, peers, planes, wn, idx, n_idx, lim)
    envelope_scores(p, u, need, peers, planes, wn, idx, n_idx, source, keepout, bmin, bmax, lim, cand, th, mc, wc, okc)
    infeasible = True
    for c in range(C):
        infeasible = infeasible & (not okc[O_SLACK, c])
    has_reck = dead_reckoning_kept(p, cand, reck, idx, n_idx, lim, okc[O_RECK])
    slack = mc[1]
    for c in range(C):
        okc[O_RECK, c] = okc[O_RECK, c] & (slack[c, SOURCE] >= 0.0) & (slack[c, OBSTACLE] >= 0.0) & (slack[c, ALTITUDE] >= 0.0)
        okc[O_STRICT_RECK, c] = okc[O_STRICT, c] & okc[O_RECK, c]
    # Loiter certificates, as far as the picks of tiers 0 and 0' need them.
    lazy = ((O_STRICT_RECK, S_NEGCLOSE), (O_STRICT, S_NEGCLOSE), (O_RECK, S_BUFFERS), (O_EVERY, S_BUFFERS))
    for t in range(4):
        ok_row, score_row = lazy[t]
        if (has_reck | (t % 2 == 1)) and certified_lazily(p, cand, okc[ok_row], wc[score_row], okc[O_CERT], order, cert):
            break
    for c in range(C):
        okc[O_STRICT_CERT, c] = okc[O_STRICT, c] & okc[O_CERT, c]
    pick = envelope_pick(okc, wc, has_reck)
    u[0], u[1], u[2] = cand[pick, 0], cand[pick, 1], cand[pick, 2]
    return infeasible, pick


# --------------------------------------------------------------------------- one drone's step
@inner(inline="always")
def safety_filter(p, prev, has_prev, theta, peers, mask, age, planes, drift, source, keepout, g_s, g_o, bmin, bmax, lim, u, active, ws):
    """Step 4 of :func:`control_one` (safe rule): check the limited step ``u`` (3,), m, of tilt Θ
    against the required clearances (:func:`requirements`) and the loiter certificate
    (:func:`certified`); where it fails, replace it with the envelope search's pick
    (:func:`envelope_search`). Every clearance is 1-Lipschitz and |u| ≤ v_max Δt: only a drone
    within v_max Δt of one (a loiter's reach for the certificate) has its step scored; the
    altitude box with the tilt allowance is checked for all. Returns (filtered, infeasible)."""
    wn, reck, idx, _, vec, cw, env = ws
    smax, tb = lim[L_SMAX], lim[L_TB]
    requirements(peers, mask, age, drift, g_s, g_o, p[2], lim, wn, reck, vec)
    now, need, now_c, need_c = vec[V_NOW], vec[V_NEED], vec[V_NOW_C], vec[V_NEED_C]
    alt = altitude_margin(p[2] + u[2], theta, lim)
    bad = alt < need[ALTITUDE]
    near = (now[UAV] - smax < need[UAV]) | (now[SOURCE] - smax < need[SOURCE]) | (now[OBSTACLE] - smax < need[OBSTACLE])
    reach = smax + lim[L_LOITER_REACH]
    near_c = (now_c[UAV] - reach < need_c[UAV]) | (now_c[SOURCE] - reach < need_c[SOURCE])
    near_c = near_c | (now_c[OBSTACLE] - reach < need_c[OBSTACLE]) | (now_c[ALTITUDE] - reach < need_c[ALTITUDE])
    n_idx = kept_peers(wn, idx, lim, (peers.shape[0] > PRUNE_PEERS) & (near | bad | near_c))
    ex, ey, ez = p[0] + u[0], p[1] + u[1], p[2] + u[2]
    obstacle_required = lim[L_DOBS] + 0.5 * smax + tb
    if near:
        sc = vec[V_SCORE]
        score(ex, ey, ez, theta, peers, planes, wn[W_PLANE], wn[W_STRICT], idx, n_idx, source, keepout + tb, obstacle_required, bmin, bmax, lim, sc)
        bad = bad | (sc[0] < need[0]) | (sc[1] < need[1]) | (sc[2] < need[2]) | (sc[3] < need[3])
    cert = (peers, planes, wn, idx, n_idx, source, keepout, lim[L_DOBS] + 0.5 * lim[L_SMIN], need_c, bmin, bmax, lim, cw)
    if near_c & (not bad):
        bad = not certified(ex, ey, ez, u[0], u[1], u[2], *cert)
    active[ALTITUDE] = active[ALTITUDE] | (alt < 0.0)
    if not bad:
        return False, False
    infeasible, pick = envelope_search(p, u, prev, has_prev, need, peers, planes, wn, reck, idx, n_idx, source, keepout, cert, env)
    margins = env[2][0, pick]
    for f in range(4):
        active[f] = active[f] | (margins[f] < 0.0)
    return True, infeasible


@inner(inline="always")
def control_one(p, prev, grad, status, peers, mask, age, planes, drift, source, keepout, uni, bmin, bmax, lim, xi, pert, source_exact, u, active, ws):
    """One drone's control step (eqs. 14-17 and 2, and the safety filter with the safe rule):
    the step to ``u`` (3,), m, the active constraint families to ``active`` (4,); returns
    (singular, filtered, infeasible) (:func:`planner.control.control_step`). ``ws``: the
    workspace of :func:`workspace`."""
    wn, m33, vec = ws[0], ws[3], ws[4]
    g_s, g_o = constraints(p, peers, mask, age, planes, source, keepout, bmin, bmax, lim, source_exact, wn, vec, active)
    projected = active_projection(p, peers, planes, wn, source, vec, m33)
    singular, theta, has_prev = limited_step(grad, status, prev, uni, projected, m33[2], vec[V_CORR], xi, pert, lim, u)
    if lim[L_SAFE] > 0.5:
        filtered, infeasible = safety_filter(
            p, prev, has_prev, theta, peers, mask, age, planes, drift, source, keepout, g_s, g_o, bmin, bmax, lim, u, active, ws
        )
        return singular, filtered, infeasible
    # The paper's rule clamps the altitude to its box.
    z_next = p[2] + u[2]
    clamped = min(max(z_next, lim[L_ZMIN]), lim[L_ZMAX])
    active[ALTITUDE] = clamped != z_next
    u[2] = clamped - p[2]
    return singular, False, False


@njit(no_cpython_wrapper=True, _nrt=True)
def workspace(N, K, nb):
    """The scratch arrays of :func:`control_one` for N peer rows, loiter paths of K steps and nb
    buildings."""
    C = N_CANDIDATES
    env = (
        np.empty((C, 3)),
        np.empty(C),
        np.empty((2, C, 4)),
        np.empty((N_SCORES, C)),
        np.zeros((N_MASKS, C), dtype=np.bool_),
        np.empty(C, dtype=np.int64),
    )
    return (
        np.empty((N_PEER_ROWS, N)),
        np.empty((2, N, 3)),
        np.empty(N, dtype=np.int64),
        np.empty((3, 3, 3)),
        np.empty((N_VECTORS, 4)),
        (np.empty(N, dtype=np.int64), np.empty(nb, dtype=np.int64), np.empty((2, K + 1, 3))),
        env,
    )


@njit(cache=True)
def control_batch(p, prev, grad, status, peers, mask, age, planes, drift, source, keepout, uni, bmin, bmax, lim, xi, pert, source_exact, u, flags):
    """:func:`control_one` of B drones (a leading axis B: p, prev, grad (B, 3), status (B,) int8,
    peers (B, N, 3), mask (B, N) bool, age (B, N), planes, drift (B, N, 3), source (B, 3),
    keepout (B,), uni (B, 2)): the steps to ``u`` (B, 3), to ``flags`` (B, 7) the active
    families (4), singular, filtered, infeasible."""
    ws = workspace(peers.shape[1], int(lim[L_LOITER_K]), bmin.shape[0])
    for b in range(peers.shape[0]):
        flags[b, 4], flags[b, 5], flags[b, 6] = control_one(
            p[b],
            prev[b],
            grad[b],
            np.int64(status[b]),
            peers[b],
            mask[b],
            age[b],
            planes[b],
            drift[b],
            source[b],
            keepout[b],
            uni[b],
            bmin,
            bmax,
            lim,
            xi,
            pert,
            source_exact,
            u[b],
            flags[b, 0:4],
            ws,
        )


# =========================================================================== planning policy
#: Standard deviations of the source estimate added to d_S* (:func:`source_keepout`).
SOURCE_SIGMA_FACTOR: float = 3.0
#: Standard deviations added to d_S* about a converged estimate, as long as they come to at most
#: :data:`SOURCE_TAIL_MAX_M`.
SOURCE_TAIL_SIGMA_FACTOR: float = 4.0
#: Largest inflation (m) of the converged estimate's :data:`SOURCE_TAIL_SIGMA_FACTOR` σ.
SOURCE_TAIL_MAX_M: float = 4.0
#: Smallest inflation (m) of d_S* about the estimate, however small its σ.
SOURCE_INFLATION_MIN_M: float = 1.5
#: Standard deviations of the own ranges' lower bound (:func:`own_lower_bound`).
OWN_RANGE_SIGMA_FACTOR: float = 2.0
#: Standard deviations by which the own ranges must put the source nearer than the estimate for
#: the estimate to count as contradicted (:func:`own_contradicts`).
OWN_RANGE_CONTRADICTION_SIGMAS: float = 2.5
#: The contradiction's hysteresis for a drone that loitered at its last step.
OWN_RANGE_RELEASE_SIGMAS: float = 1.0
#: A loitering drone resumes its cost once its ranges' lower bound reaches this many times
#: d_S* + a (:func:`must_loiter`).
OWN_RANGE_CLEAR_FACTOR: float = 1.5
#: Softness s (m) of the predicted line of sight Φ(c/s) of a drone's own link (:func:`own_los`).
LOS_SOFTNESS_M: float = 2.0
#: Depth (in softnesses) into a shadow below which the slope of the predicted LOS is held.
LOS_SLOPE_FLOOR_SOFTNESSES: float = 1.0
#: Links farther than this many softnesses from a building count as clear of it.
LOS_CUTOFF_SOFTNESSES: float = 5.0
#: Points sampled along a link (:func:`link_clearance`).
LINK_SAMPLES: int = 16
#: Bounds the drone's own measured LOS flag puts on q: ≥ Φ(1) in a measured LOS, ≤ 1 − Φ(1) in NLOS.
MEASURED_LOS_MIN: float = 0.8413447460685429
#: The longest gap (steps) between two records of a peer that still gives its last step.
DRIFT_MAX_GAP_STEPS: int = 4
#: Status code of a FIM the control step treats as fine (:class:`planner.fim.FimStatus`).
STATUS_OK = 0


@inner
def normal_cdf(a):
    """Φ(a), the standard normal CDF (cephes' ndtr: 0.5 + 0.5 erf(a/√2) near 0, erfc in the tails)."""
    x = a * 0.7071067811865476
    z = abs(x)
    if z < 0.7071067811865476:
        return 0.5 + 0.5 * math.erf(x)
    y = 0.5 * math.erfc(z)
    return 1.0 - y if x > 0.0 else y


@inner
def own_los(p, s, measured, use_measured, bmin, bmax, grad, work):
    """Predicted line of sight q = Π_b Φ(c_b/s) of the link s → p (c_b its clearance from building
    b, :func:`link_clearance`, s = :data:`LOS_SOFTNESS_M`) and its gradient w.r.t. p to ``grad``
    (3,), 1/m: q̄ Σ_b (φ(v_b)/Φ(v_b)) ∇c_b / s, v_b = max(c_b/s, −1), q̄ = Π_b Φ(v_b); bounded by the
    drone's own measured LOS flag where ``use_measured`` (:func:`planner.agent.own_los_weight`).
    ``work``: scratch (9,)."""
    soft = LOS_SOFTNESS_M
    q = 1.0
    qbar = 1.0
    sx = sy = sz = 0.0
    gc = work[6:9]
    for b in range(bmin.shape[0]):
        c = link_clearance(p, s, bmin, bmax, b, np.int64(LINK_SAMPLES), LOS_CUTOFF_SOFTNESSES * soft, gc, work)
        u = max(c / soft, -30.0)
        phi_u = normal_cdf(u)
        q = q * phi_u
        v = max(u, -LOS_SLOPE_FLOOR_SOFTNESSES)
        phi_v = phi_u if v == u else normal_cdf(v)
        qbar = qbar * phi_v
        mills = math.exp(-0.5 * v * v) / (math.sqrt(2.0 * math.pi) * phi_v)
        sx, sy, sz = sx + mills * gc[0], sy + mills * gc[1], sz + mills * gc[2]
    grad[0], grad[1], grad[2] = qbar * sx / soft, qbar * sy / soft, qbar * sz / soft
    if use_measured:
        q = max(q, MEASURED_LOS_MIN) if measured else min(q, 1.0 - MEASURED_LOS_MIN)
    return q


@inner
def source_keepout(sigma, lim):
    """Keep-out radius (m) about an estimate of largest standard deviation σ (m):
    d_S* + min(max(3σ, min(4σ, 4 m), 1.5 m), d_S*) (:func:`planner.agent.source_keepout_m`)."""
    d_s = lim[L_DSRC]
    tail = min(SOURCE_TAIL_SIGMA_FACTOR * sigma, SOURCE_TAIL_MAX_M)
    inflation = max(max(SOURCE_SIGMA_FACTOR * sigma, tail), min(SOURCE_INFLATION_MIN_M, d_s))
    return d_s + min(inflation, d_s)


@inner
def followable(p, centre, r, sigma, last_centre, last_r, lim):
    """The keep-out radius (m) a drone at ``p`` plans with (:func:`planner.agent.followable_keepout_m`):
    about an estimate too uncertain to cover the source (3σ ≥ d_S*) its boundary advances on the
    drone by at most b per step from the last step's (``last_centre``, ``last_r``; NaN: none)."""
    d_s = lim[L_DSRC]
    if not ((SOURCE_SIGMA_FACTOR * sigma >= d_s) & math.isfinite(r) & math.isfinite(last_r)):
        return r
    ax, ay, az = p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]
    bx, by, bz = p[0] - last_centre[0], p[1] - last_centre[1], p[2] - last_centre[2]
    moved = math.sqrt(ax * ax + ay * ay + az * az) - math.sqrt(bx * bx + by * by + bz * bz)
    return min(r, max(last_r + moved + lim[L_TB], keepout_floor(lim)))


@inner
def keepout_floor(lim):
    """The smallest keep-out radius (m) about an estimate: d_S* + min(1.5 m, d_S*), the keep-out's
    fixed inflation (:data:`SOURCE_INFLATION_MIN_M`)."""
    return lim[L_DSRC] + min(SOURCE_INFLATION_MIN_M, lim[L_DSRC])


@inner
def own_range_stats(ranges, los, ch):
    """(d̄, Σw) of a drone's own last ranges (NaN: none) and their LOS flags: the weighted mean with
    w = 1/σ_r0² of each range's LOS or NLOS σ_r0 (eq. 5), NaN and 0 without ranges
    (:func:`planner.agent.own_ranges`)."""
    sw = 0.0
    swr = 0.0
    for w in range(ranges.shape[0]):
        have = math.isfinite(ranges[w])
        w0 = (1.0 / (ch[CH_S2_LOS] if los[w] else ch[CH_S2_NLOS])) * have
        sw += w0
        swr += w0 * (ranges[w] if have else 0.0)
    return (swr / sw if sw > 0.0 else np.nan), sw


@inner
def own_relative_sd(weight, gamma, d):
    """r(d) = 1/√(Σw d^(2−γ)), the relative standard deviation of the own ranges' mean about a
    distance d (m); +inf without ranges (:meth:`planner.agent.OwnRanges.relative_sd`)."""
    if not weight > 0.0:
        return np.inf
    d = max(d, 1e-9)
    info = weight * d ** (2.0 - gamma)
    return 1.0 / math.sqrt(info if info > 0.0 else 1.0)


@inner
def own_lower_bound(mean, weight, gamma, k):
    """d̄ / (1 + k r(d̄)), the own ranges' lower confidence bound on the distance (m); +inf without
    ranges (:meth:`planner.agent.OwnRanges.lower_bound_m`)."""
    if not weight > 0.0:
        return np.inf
    return mean / (1.0 + k * own_relative_sd(weight, gamma, mean))


@inner
def own_contradicts(mean, weight, gamma, d, k):
    """The own ranges put the source nearer than the distance d (m) to the estimate by more than k
    standard deviations: (d̄/d − 1)/r(d) < −k (:meth:`planner.agent.OwnRanges.contradicts`)."""
    if not weight > 0.0:
        return False
    z = (mean / max(d, 1e-9) - 1.0) / own_relative_sd(weight, gamma, d)
    return z < -k


@inner
def must_loiter(sigma, observable, d_est, mean, weight, gamma, loitering, lim):
    """Whether the drone loiters instead of descending its cost (:func:`planner.agent.must_loiter`):
    its estimate gives no direction to trust (not observable, 3σ ≥ d_S*, or contradicted by its
    own ranges, with the hysteresis of a drone ``loitering`` at its last step) and its ranges'
    lower bound is below d_S* + a (a loitering drone: below :data:`OWN_RANGE_CLEAR_FACTOR` times that)."""
    # The cheap test first (without ranges the lower bound is +inf: no loiter); the rest only
    # where it passes (pure functions: the same answer as evaluating all of it).
    near = lim[L_DSRC] + lim[L_SRC_MARGIN]
    lower = own_lower_bound(mean, weight, gamma, OWN_RANGE_SIGMA_FACTOR)
    if not ((lower < near) | (loitering & (lower < OWN_RANGE_CLEAR_FACTOR * near))):
        return False
    k = OWN_RANGE_RELEASE_SIGMAS if loitering else OWN_RANGE_CONTRADICTION_SIGMAS
    return (not observable) or (SOURCE_SIGMA_FACTOR * sigma >= lim[L_DSRC]) or own_contradicts(mean, weight, gamma, d_est, k)


@inner
def estimate_sigma(information):
    """Largest standard deviation (m) of an estimate with Fisher information (3, 3): 1/√λ_min,
    +inf where λ_min ≤ 0 (:func:`planner.agent.estimate_sigma_m`)."""
    lmin = eigvalsh3(information)[0]
    return 1.0 / math.sqrt(max(lmin, 1e-300)) if lmin > 0.0 else np.inf


@inner
def loiter_gradient(prev, out):
    """The gradient a loitering drone descends, to ``out`` (3,): minus the horizontal unit vector
    90° to the left of its last step (east where it has none; :func:`planner.agent.loiter_gradient`)."""
    lx, ly = -prev[1], prev[0]
    n = math.sqrt(lx * lx + ly * ly + 0.0 * 0.0)
    if n > 1e-12:
        out[0], out[1], out[2] = -(lx / n), -(ly / n), -(0.0 / n)
    else:
        out[0], out[1], out[2] = -1.0, -0.0, -0.0


# --------------------------------------------------------------------------- the carried state
# Arrays of a drone's carried state (:class:`planner.step.DroneState`), in this order.
(
    ST_PREV,
    ST_RANGE,
    ST_RANGE_LOS,
    ST_LOITER,
    ST_KEEPOUT_CENTRE,
    ST_KEEPOUT,
    ST_DRIFT_POS,
    ST_DRIFT_SAVED,
    ST_DRIFT,
    ST_OWN_THEN,
    ST_TRACK,
    ST_TRACK_STEPS,
) = range(12)


@inner(inline="always")
def advance_state(b, k, p, own_range, own_los, view_pos, valid, saved, old, new):
    """Drone b's carried state after the records of step k: its own range (NaN: none) and LOS flag
    enter its window (oldest first), its position ``p`` its track (slot k mod T), and each peer's
    newest record updates the peer's drift (its mean step between its two newest records, NaN
    unless they are at most :data:`DRIFT_MAX_GAP_STEPS` apart) and the drone's own position at
    that record's step (from the track; ``p`` where the track no longer holds it). Writes
    ``new[...][b]`` from ``old[...][b]``, the track's arrays excepted: ``new``'s track holds
    ``old``'s already (:func:`plan_batch` copies them for the whole batch at once)."""
    W = old[ST_RANGE].shape[1]
    for w in range(W - 1):
        new[ST_RANGE][b, w] = old[ST_RANGE][b, w + 1]
        new[ST_RANGE_LOS][b, w] = old[ST_RANGE_LOS][b, w + 1]
    new[ST_RANGE][b, W - 1] = own_range
    new[ST_RANGE_LOS][b, W - 1] = own_los
    T = old[ST_TRACK].shape[1]
    new[ST_TRACK_STEPS][b, k % T] = k
    for a in range(3):
        new[ST_TRACK][b, k % T, a] = p[a]
    for j in range(view_pos.shape[0]):
        last = old[ST_DRIFT_SAVED][b, j]
        s = saved[j] if valid[j] else -1
        fresh = valid[j] & (s > last)
        usable = fresh & (last >= 0) & (s - last <= DRIFT_MAX_GAP_STEPS)
        slot = max(s, 0) % T
        tracked = new[ST_TRACK_STEPS][b, slot] == s
        new[ST_DRIFT_SAVED][b, j] = s if fresh else last
        for a in range(3):
            step = (view_pos[j, a] - old[ST_DRIFT_POS][b, j, a]) / max(s - last, 1)
            new[ST_DRIFT][b, j, a] = step if usable else (np.nan if fresh else old[ST_DRIFT][b, j, a])
            new[ST_DRIFT_POS][b, j, a] = view_pos[j, a] if fresh else old[ST_DRIFT_POS][b, j, a]
            then = new[ST_TRACK][b, slot, a] if tracked else p[a]
            new[ST_OWN_THEN][b, j, a] = then if fresh else old[ST_OWN_THEN][b, j, a]


@inner
def bisector_plane(a, b, lost, point, normal):
    """The plane two drones that lost contact keep apart by (:func:`planner.control.lost_contact_planes`):
    to ``point`` the midpoint of a (this drone then) and b (the peer's last record), to ``normal``
    the unit normal (a − b)/|a − b|, where ``lost`` and a ≠ b; else b and zeros."""
    dx, dy, dz = a[0] - b[0], a[1] - b[1], a[2] - b[2]
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    plane = lost & (norm > 0.0)
    n = norm if norm > 0.0 else 1.0
    for k in range(3):
        normal[k] = (a[k] - b[k]) / n if plane else 0.0
        point[k] = 0.5 * (a[k] + b[k]) if plane else b[k]


@inner(inline="always")
def peer_rows(i, k, view_pos, valid, saved, hops, lost, own_then, start, has_start, hop_rule, rows, mask, ages, planes):
    """The peer rows of drone i's anti-collision constraint (:func:`planner.agent.plan`): the peers
    heard directly (``hop_rule``: h_ij = 1; else every known peer), each at its record with the
    record's age; a lost-contact peer (``lost``, a partition) as the bisector plane between the
    drone's position at that peer's last record (``own_then``) and the record, at least d_U*/2 to
    the drone's side (age 0); a peer never heard of at its start position, aged k steps (where
    ``has_start``). To ``rows`` (N, 3), ``mask`` (N,), ``ages`` (N,), ``planes`` (N, 3) (unit
    normals; zeros for point rows)."""
    for j in range(view_pos.shape[0]):
        other = j != i
        relevant = (hops[j] == 1) | (not hop_rule)
        ages[j] = k - saved[j] if valid[j] else 0.0
        lost_j = lost[j] & valid[j] & other
        bisector_plane(own_then[j], view_pos[j], lost_j, rows[j], planes[j])
        relevant = relevant | lost_j
        ages[j] = 0.0 if lost_j else ages[j]
        unheard = has_start & (not valid[j]) & other & relevant
        for a in range(3):
            rows[j, a] = start[j, a] if unheard else rows[j, a]
        ages[j] = float(k) if unheard else ages[j]
        mask[j] = (valid[j] & other & relevant) | unheard


@inner(inline="always")
def keepout_policy(p, p_hat, information, observable, status, ranges, range_los, last_centre, last_keepout, loitering, lim, ch):
    """The FIM status the control step sees, the source keep-out radius (m) and whether the drone
    loiters (docs/control.md, "Own-range loiter"): an unobservable estimate
    counts as singular and has no keep-out (−inf); an observable one has :func:`source_keepout` of
    its largest σ, limited by :func:`followable` against the last step's keep-out; where the own
    ranges (``ranges``, ``range_los``: the window) say so (:func:`must_loiter`) the drone loiters
    (status OK) and keeps no keep-out where it is inside it and its ranges contradict the
    estimate."""
    sigma = estimate_sigma(information)
    keepout = source_keepout(sigma, lim) if observable else -np.inf
    keepout = followable(p, p_hat, keepout, sigma, last_centre, last_keepout, lim)
    mean, weight = own_range_stats(ranges, range_los, ch)
    dx, dy, dz = p[0] - p_hat[0], p[1] - p_hat[1], p[2] - p_hat[2]
    d_est = math.sqrt(dx * dx + dy * dy + dz * dz)
    gamma = ch[CH_GAMMA]
    loiter = must_loiter(sigma, observable, d_est, mean, weight, gamma, loitering, lim)
    drop = loiter and (d_est < keepout) and own_contradicts(mean, weight, gamma, d_est, OWN_RANGE_CONTRADICTION_SIGMAS)
    keepout = -np.inf if drop else keepout
    status = status if observable else SINGULAR
    return np.int64(STATUS_OK if loiter else status), keepout, loiter


@inner(inline="always")
def plan_one(b, scene, cost, old, new, config, out, ws):
    """Drone b's planning step after its cost (:func:`planner.agent.plan`): the carried state's
    update (:func:`advance_state`), the keep-out and loiter policy (:func:`keepout_policy`; with
    an oracle source: its plain d_S*), the peer rows (:func:`peer_rows`) and the control step
    (:func:`control_one`); the step, flags, keep-out and loiter to ``out``, the new state to ``new``."""
    own_index, p, own_range, own_los, view_pos, valid, saved, hops, lost, p_hat, information, observable, uni = scene
    grad, status = cost
    k, start, has_start, hop_rule, oracle, source_exact, bmin, bmax, lim, ch, xi, pert = config
    u, flags, extra = out
    rows, mask, ages, planes, g, cws = ws
    advance_state(b, k, p[b], own_range[b], own_los[b], view_pos[b], valid[b], saved[b], old, new)
    st, keepout, loiter = np.int64(status[b]), lim[L_DSRC], False
    if not oracle:
        st, keepout, loiter = keepout_policy(
            p[b],
            p_hat[b],
            information[b],
            observable[b],
            status[b],
            new[ST_RANGE][b],
            new[ST_RANGE_LOS][b],
            old[ST_KEEPOUT_CENTRE][b],
            old[ST_KEEPOUT][b],
            old[ST_LOITER][b],
            lim,
            ch,
        )
    if loiter:
        loiter_gradient(old[ST_PREV][b], g)
    else:
        g[0], g[1], g[2] = grad[b, 0], grad[b, 1], grad[b, 2]
    peer_rows(
        own_index[b], k, view_pos[b], valid[b], saved[b], hops[b], lost[b], new[ST_OWN_THEN][b], start, has_start, hop_rule, rows, mask, ages, planes
    )
    flags[b, 4], flags[b, 5], flags[b, 6] = control_one(
        p[b],
        old[ST_PREV][b],
        g,
        st,
        rows,
        mask,
        ages,
        planes,
        new[ST_DRIFT][b],
        p_hat[b],
        keepout,
        uni[b],
        bmin,
        bmax,
        lim,
        xi,
        pert,
        source_exact,
        u[b],
        flags[b, 0:4],
        cws,
    )
    extra[b, 0], flags[b, 7] = keepout, loiter
    for a in range(3):
        new[ST_PREV][b, a] = u[b, a]
        new[ST_KEEPOUT_CENTRE][b, a] = p_hat[b, a]
    new[ST_LOITER][b] = loiter
    new[ST_KEEPOUT][b] = keepout


# --------------------------------------------------------------------------- entries of the public helpers
@njit(cache=True)
def own_los_batch(p, s, measured, use_measured, bmin, bmax):
    """:func:`own_los` of n links s → p (n, 3), measured flags (n,): (q (n,), ∇q (n, 3))."""
    n = p.shape[0]
    q = np.empty(n)
    g = np.empty((n, 3))
    work = np.empty(9)
    for i in range(n):
        q[i] = own_los(p[i], s[i], measured[i], use_measured, bmin, bmax, g[i], work)
    return q, g


@njit(cache=True)
def policy_batch(sigma, observable, d_est, mean, weight, loitering, gamma, lim):
    """Per element (n,): the keep-out of σ (:func:`source_keepout`), whether the drone loiters
    (:func:`must_loiter`) and whether its ranges contradict the estimate at d_est with the
    loiter's hysteresis (:func:`own_contradicts` by 1 σ while ``loitering``, else 2.5 σ)."""
    n = sigma.shape[0]
    out = np.empty((3, n))
    for i in range(n):
        k = OWN_RANGE_RELEASE_SIGMAS if loitering[i] else OWN_RANGE_CONTRADICTION_SIGMAS
        out[0, i] = source_keepout(sigma[i], lim)
        out[1, i] = must_loiter(sigma[i], observable[i], d_est[i], mean[i], weight[i], gamma, loitering[i], lim)
        out[2, i] = own_contradicts(mean[i], weight[i], gamma, d_est[i], k)
    return out


@njit(cache=True)
def own_range_batch(mean, weight, gamma, d, k):
    """Per element (n,) of own-range statistics (d̄, Σw): the relative standard deviation at d
    (:func:`own_relative_sd`), the lower bound with k σ (:func:`own_lower_bound`), and whether
    they contradict an estimate at d by k σ (:func:`own_contradicts`)."""
    n = mean.shape[0]
    out = np.empty((3, n))
    for i in range(n):
        out[0, i] = own_relative_sd(weight[i], gamma, d[i])
        out[1, i] = own_lower_bound(mean[i], weight[i], gamma, k[i])
        out[2, i] = own_contradicts(mean[i], weight[i], gamma, d[i], k[i])
    return out


@njit(cache=True)
def own_ranges_batch(ranges, los, ch):
    """:func:`own_range_stats` of n windows (n, W): (d̄ (n,), Σw (n,))."""
    n = ranges.shape[0]
    mean = np.empty(n)
    weight = np.empty(n)
    for i in range(n):
        mean[i], weight[i] = own_range_stats(ranges[i], los[i], ch)
    return mean, weight


@njit(cache=True)
def followable_batch(p, centre, r, sigma, last_centre, last_r, lim):
    """:func:`followable` of n drones (positions and centres (n, 3), radii and σ (n,))."""
    out = np.empty(r.shape[0])
    for i in range(r.shape[0]):
        out[i] = followable(p[i], centre[i], r[i], sigma[i], last_centre[i], last_r[i], lim)
    return out


@njit(cache=True)
def small_batch(information, prev):
    """Per element: the largest standard deviation of an estimate (:func:`estimate_sigma`) of
    information (n, 3, 3), and the loiter gradient (:func:`loiter_gradient`) of last steps (m, 3)."""
    sigma = np.empty(information.shape[0])
    for i in range(information.shape[0]):
        sigma[i] = estimate_sigma(information[i])
    g = np.empty((prev.shape[0], 3))
    for i in range(prev.shape[0]):
        loiter_gradient(prev[i], g[i])
    return sigma, g


@njit(cache=True)
def peer_distance_batch(x, peers, planes, d_uav):
    """Peer distances (n, N) of positions x (n, 3) to peer rows (n, N, 3) with plane normals
    (n, N, 3; zeros for point rows) (:func:`peer_distance`)."""
    n, N = peers.shape[0], peers.shape[1]
    dist = np.empty((n, N))
    for i in range(n):
        flags = np.empty(N)
        for j in range(N):
            flags[j] = 1.0 * ((planes[i, j, 0] != 0.0) | (planes[i, j, 1] != 0.0) | (planes[i, j, 2] != 0.0))
            dist[i, j] = peer_distance(x[i, 0], x[i, 1], x[i, 2], peers[i], planes[i], flags, j, d_uav)
    return dist


@njit(cache=True)
def planes_batch(a, b, lost):
    """:func:`bisector_plane` of m pairs (a, b (m, 3), lost (m,)): (points (m, 3), normals (m, 3))."""
    m = a.shape[0]
    points = np.empty((m, 3))
    normals = np.empty((m, 3))
    for i in range(m):
        bisector_plane(a[i], b[i], lost[i], points[i], normals[i])
    return points, normals


@njit(cache=True)
def loiter_batch(end, step, lim):
    """The loiter paths' vertices (n, 2, K, 3) from ends (n, 3) after steps (n, 3)
    (:func:`loiter_vertices`, to the left then to the right, without the end itself)."""
    n, K = end.shape[0], int(lim[L_LOITER_K])
    verts = np.empty((2, K + 1, 3))
    out = np.empty((n, 2, K, 3))
    for i in range(n):
        loiter_vertices(end[i, 0], end[i, 1], end[i, 2], step[i, 0], step[i, 1], step[i, 2], lim, verts)
        out[i] = verts[:, 1:, :]
    return out


@njit(cache=True)
def candidates_batch(prev, has_prev, lim):
    """:func:`envelope_candidates` of n previous steps (n, 3): (steps (n, C, 3), tilts (n, C))."""
    n = prev.shape[0]
    cand = np.empty((n, N_CANDIDATES, 3))
    th = np.empty((n, N_CANDIDATES))
    for i in range(n):
        envelope_candidates(prev[i], has_prev[i], lim, cand[i], th[i])
    return cand, th


@njit(cache=True)
def envelope_batch(p, u, prev, has_prev, need, need_c, peers, planes, strict, loose, hard, source, keepout, bmin, bmax, lim):
    """The envelope search (:func:`envelope_search`) of one drone at ``p`` whose step ``u`` failed,
    with given peer requirements (strict, loose, hard (N,), m), margins it must keep ``need``
    (4,) and loiter-certificate needs ``need_c`` (4,; +inf: no certificate), no dead reckoning.
    Returns (the step (3,), its margins (4,), infeasible): the filter's last stage on its own,
    for tests of its tiers."""
    N = peers.shape[0]
    wn, reck, idx, _, _, cw, env = workspace(N, int(lim[L_LOITER_K]), bmin.shape[0])
    for j in range(N):
        wn[W_PLANE, j] = 1.0 * ((planes[j, 0] != 0.0) | (planes[j, 1] != 0.0) | (planes[j, 2] != 0.0))
        wn[W_STRICT, j], wn[W_LOOSE, j], wn[W_HARD, j] = strict[j], loose[j], hard[j]
        idx[j] = j
        for a in range(3):
            reck[0, j, a] = np.nan
            reck[1, j, a] = np.nan
    step = u.copy()
    cert = (peers, planes, wn, idx, N, source, keepout, lim[L_DOBS] + 0.5 * lim[L_SMIN], need_c, bmin, bmax, lim, cw)
    infeasible, pick = envelope_search(p, step, prev, has_prev, need, peers, planes, wn, reck, idx, N, source, keepout, cert, env)
    return step, env[2][0, pick].copy(), infeasible


@njit(cache=True)
def dead_reckoning_batch(p, cand, reck_now, reck_next, lim):
    """:func:`dead_reckoning_kept` of one drone at ``p`` (3,) for candidate steps (C, 3) and the
    peers' dead-reckoned positions now and next (N, 3) (NaN: none): (kept (C,), whether any peer
    has one)."""
    N = reck_now.shape[0]
    reck = np.empty((2, N, 3))
    reck[0], reck[1] = reck_now, reck_next
    idx = np.arange(N)
    ok = np.zeros(cand.shape[0], dtype=np.bool_)
    known = dead_reckoning_kept(p, cand, reck, idx, N, lim, ok)
    return ok, known


@inner(inline="always")
def plan_cost(b, scene, view_los, roles, config, cost, ws):
    """Drone b's cost of eq. 6 and its gradient w.r.t. its own position, to ``cost`` (value (B,),
    ∇C (B, 3), status (B,)): the predicted line of sight q of its own link (:func:`own_los`; q = 1
    without buildings), the FIM over its view at its estimate with the own term weighted by q
    (:func:`add_fim_terms`), and :func:`own_gradient` with the LOS weight's gradient
    (the cost :func:`planner.agent.plan` descends). ``roles``: (κ (N,), β (N,), the criterion is D)."""
    own_index, p, _, _, view_pos, valid, _, _, _, p_hat, _, _, _ = scene
    ranging, bearing, criterion_d = roles
    bmin, bmax, ch = config[6], config[7], config[9]
    rng, brg, los_w, gq, J, M, work, gwork = ws
    i = own_index[b]
    for j in range(valid.shape[1]):
        rng[j] = ranging[j] & valid[b, j]
        brg[j] = bearing[j] & valid[b, j]
        los_w[j] = 1.0 * (view_los[b, j] | (j == i))
    q = 1.0
    boxes = bmin.shape[0] > 0
    for a in range(3):
        gq[a] = 0.0
    if boxes:
        q = own_los(p[b], p_hat[b], view_los[b, i], True, bmin, bmax, gq, gwork)
        for j in range(valid.shape[1]):
            los_w[j] = q if j == i else 1.0 * view_los[b, j]
    for r in range(3):
        for c in range(3):
            J[r, c] = 0.0
    add_fim_terms(p_hat[b], view_pos[b], rng, brg, los_w, ch, J)
    values, grads, statuses = cost
    values[b], statuses[b] = own_gradient(J, p_hat[b], p[b], ranging[i], bearing[i], q, gq, boxes, ch, criterion_d, grads[b], M, work)


@njit(cache=True)
def plan_batch(scene, view_los, roles, old, config, new, out, cost, given_cost):
    """The planning step of B drones (:func:`plan_cost`, unless ``given_cost``, then
    :func:`plan_one`). ``scene``: (own index (B,), position (B, 3), own range (B,), own LOS (B,),
    view positions (B, N, 3), valid (B, N), saved steps (B, N), hop counts (B, N), lost contact
    (B, N), estimate (B, 3), information (B, 3, 3), observable (B,), uniforms (B, 2));
    ``view_los``: the records' LOS flags (B, N); ``roles``: (κ (N,), β (N,), the criterion is D);
    ``old``: the carried state's arrays (``ST_*``); ``config``: (k, start positions (N, 3),
    whether known, the hop rule, oracle, exact source, boxes min, max, ``lim``, ``ch``, ξ (NaN:
    normalised), perturbation (rad)). To ``new``: the new state's arrays (as ``old``); to
    ``out``: (the steps (B, 3), flags (B, 8): the active families (4), singular, filtered,
    infeasible, loiter; the keep-outs (B, 1), m); ``cost``: (value (B,), ∇C (B, 3), status (B,)),
    computed here or (``given_cost``: a registry with further components, whose terms the caller
    added) given."""
    N = scene[4].shape[1]
    wsc = (
        np.empty(N, dtype=np.bool_),
        np.empty(N, dtype=np.bool_),
        np.empty(N),
        np.empty(3),
        np.empty((3, 3)),
        np.empty((3, 3)),
        np.empty((2, 3, 3)),
        np.empty(9),
    )
    lim, bmin = config[8], config[6]
    ws = (
        np.empty((N, 3)),
        np.zeros(N, dtype=np.bool_),
        np.empty(N),
        np.empty((N, 3)),
        np.empty(3),
        workspace(N, int(lim[L_LOITER_K]), bmin.shape[0]),
    )
    # The tracks as they were (each drone's step then writes its own slot). Element loops, not
    # slice assignments: numba compiles a slice assignment's shape-mismatch message (string
    # formatting) into the kernel, a seventh of this group's first compile.
    # Flat loops over the C-contiguous arrays (the compiler vectorises them).
    track, track_steps = old[ST_TRACK].reshape(-1), old[ST_TRACK_STEPS].reshape(-1)
    new_track, new_steps = new[ST_TRACK].reshape(-1), new[ST_TRACK_STEPS].reshape(-1)
    for i in range(track_steps.shape[0]):
        new_steps[i] = track_steps[i]
    for i in range(track.shape[0]):
        new_track[i] = track[i]
    plan_drones(scene, view_los, roles, old, config, new, out, cost, given_cost, wsc, ws)


@inner
def plan_drones(scene, view_los, roles, old, config, new, out, cost, given_cost, wsc, ws):
    """:func:`plan_cost` (unless ``given_cost``) and :func:`plan_one` of every drone of
    :func:`plan_batch`, in order (their bodies compiled into this loop: the scene's and the
    workspace's arrays are not passed again for each drone)."""
    for b in range(scene[4].shape[0]):
        if not given_cost:
            plan_cost(b, scene, view_los, roles, config, cost, wsc)
        plan_one(b, scene, (cost[1], cost[2]), old, new, config, out, ws)


# The entry kernels built ahead of time, when they are (planner.aot): bound here, at import.
from planner.aot import bind as _bind  # noqa: E402

_bind("planning", globals())

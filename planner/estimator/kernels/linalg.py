"""Compiled small linear algebra of the estimator (one element at a time): 3 × 3 determinant,
adjugate inverse of a symmetric matrix, normalised determinant, a 3 × 3 solve with partial
pivoting, the eigen-decomposition of a small symmetric matrix (LAPACK, as numpy), a median,
sums in numpy's order, and NaN-propagating min/max and box projection (numpy's ``minimum``/``maximum`` semantics). Loops over elements
throughout: no array expressions (each would compile its own loop nest) and no slice
assignment of arrays (each would compile its shape checks and error messages)."""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from numba import njit

#: The decorator of an inner kernel that allocates nothing and returns no array: compiled without
#: numba's reference counting, its array arguments borrowed from its caller (package doc).
borrowing: Any = functools.partial(njit, cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True, _nrt=False)
#: The decorator of an inner kernel that allocates: with numba's reference counting, said
#: explicitly (a callee of a :data:`borrowing` kernel would otherwise inherit its setting).
counting: Any = functools.partial(njit, cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True, _nrt=True)


@borrowing
def nmin(a: float, b: float) -> float:
    """min(a, b), NaN if either is NaN (``numpy.minimum``)."""
    if a != a or b != b:
        return a + b
    return a if a <= b else b


@borrowing
def nmax(a: float, b: float) -> float:
    """max(a, b), NaN if either is NaN (``numpy.maximum``)."""
    if a != a or b != b:
        return a + b
    return a if a >= b else b


@borrowing
def clip(v: float, lo: float, hi: float) -> float:
    """``numpy.minimum(numpy.maximum(v, lo), hi)``: v projected onto [lo, hi], NaN kept."""
    return nmin(nmax(v, lo), hi)


@borrowing
def clip3(x: np.ndarray, p: np.ndarray, lo: int, out: np.ndarray) -> None:
    """``out`` = x (3,) projected into the box p[lo:lo+3], p[lo+3:lo+6] (the search box)."""
    for i in range(3):
        out[i] = clip(x[i], p[lo + i], p[lo + 3 + i])


@borrowing
def det3(a: np.ndarray) -> float:
    """Determinant of a 3 × 3 matrix."""
    return (
        a[0, 0] * (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1])
        - a[0, 1] * (a[1, 0] * a[2, 2] - a[1, 2] * a[2, 0])
        + a[0, 2] * (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0])
    )


@borrowing
def inv3_spd(a: np.ndarray, out: np.ndarray) -> bool:
    """``out`` = inverse of the symmetric 3 × 3 ``a`` (adjugate over determinant); returns
    whether it is well defined (finite det > 1e-14 (tr a)³)."""
    det = det3(a)
    t = nmax(a[0, 0] + a[1, 1] + a[2, 2], 1e-300)
    scale = t * t * t
    ok = np.isfinite(det) and det > 1e-14 * scale
    safe = det if ok else 1.0
    out[0, 0] = (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]) / safe
    out[0, 1] = (a[0, 2] * a[2, 1] - a[0, 1] * a[2, 2]) / safe
    out[0, 2] = (a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1]) / safe
    out[1, 1] = (a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]) / safe
    out[1, 2] = (a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2]) / safe
    out[2, 2] = (a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]) / safe
    out[1, 0] = out[0, 1]
    out[2, 0] = out[0, 2]
    out[2, 1] = out[1, 2]
    return ok


@borrowing
def normalised_det(a: np.ndarray) -> float:
    """det(A)/(tr(A)/3)³ of a symmetric PSD 3 × 3 matrix (0 where tr A ≤ 0)."""
    tr = (a[0, 0] + a[1, 1] + a[2, 2]) / 3.0
    if tr > 0.0:
        return det3(a) / (tr * tr * tr)
    return 0.0


@borrowing
def solve3_in_place(m: np.ndarray, y: np.ndarray) -> None:
    """y ← m⁻¹ y for a 3 × 3 ``m`` by LU with partial pivoting (LAPACK's ``gesv`` order: the
    column below the pivot scaled by the pivot's reciprocal); m is left holding the factors."""
    for k in range(3):
        piv = k
        for i in range(k + 1, 3):
            if abs(m[i, k]) > abs(m[piv, k]):
                piv = i
        if piv != k:
            for j in range(3):
                m[k, j], m[piv, j] = m[piv, j], m[k, j]
            y[k], y[piv] = y[piv], y[k]
        r = 1.0 / m[k, k]
        for i in range(k + 1, 3):
            m[i, k] *= r
            for j in range(k + 1, 3):
                m[i, j] -= m[i, k] * m[k, j]
    for k in range(3):  # forward substitution, unit lower triangle
        for i in range(k + 1, 3):
            y[i] -= y[k] * m[i, k]
    for k in range(2, -1, -1):  # back substitution, column by column
        y[k] /= m[k, k]
        for i in range(k):
            y[i] -= y[k] * m[i, k]


@counting
def eigh(a: np.ndarray, w: np.ndarray, v: np.ndarray) -> None:
    """Eigenvalues ``w`` (ascending) and eigenvectors ``v`` (columns) of a small symmetric
    matrix ``a`` (LAPACK's ``syevd``, as ``numpy.linalg.eigh``: the same digits); NaN where
    ``a`` is not finite."""
    n = a.shape[0]
    b = np.empty((n, n))
    finite = True
    for i in range(n):
        for j in range(n):
            b[i, j] = a[i, j]
            finite = finite and np.isfinite(a[i, j])
    if not finite:
        for i in range(n):
            w[i] = np.nan
            for j in range(n):
                v[i, j] = np.nan
        return
    ew, ev = np.linalg.eigh(b)
    for i in range(n):
        w[i] = ew[i]
        for j in range(n):
            v[i, j] = ev[i, j]


@counting
def eigvalsh_min(a: np.ndarray) -> float:
    """The smallest eigenvalue of a small symmetric matrix (LAPACK, as
    ``numpy.linalg.eigvalsh``); NaN where ``a`` is not finite."""
    n = a.shape[0]
    b = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            if not np.isfinite(a[i, j]):
                return np.nan
            b[i, j] = a[i, j]
    return np.linalg.eigvalsh(b)[0]


@borrowing
def median(z: np.ndarray, n: int) -> float:
    """The median of z[:n] (n ≥ 1), sorting z[:n] in place; the mean of the two middle values
    for even n."""
    for i in range(1, n):
        j = i
        while j > 0 and z[j - 1] > z[j]:
            z[j - 1], z[j] = z[j], z[j - 1]
            j -= 1
    h = n // 2
    return z[h] if n % 2 == 1 else (z[h - 1] + z[h]) / 2.0


@njit(cache=True, error_model="numpy")
def dot(a: np.ndarray, b: np.ndarray, n: int) -> float:
    """Σ a[k] b[k] over k < n in ``numpy.einsum``'s order for two contiguous operands (two
    lanes of even and odd k, four lane-pairs per step, then the lanes added): the pseudo-linear
    systems are summed this way so that a tie of their solutions (e.g. the mirror images of
    coplanar drones' ranges) is decided as numpy decides it."""
    acc0, acc1 = 0.0, 0.0
    i = 0
    while n - i >= 8:
        acc0 = a[i] * b[i] + (a[i + 2] * b[i + 2] + (a[i + 4] * b[i + 4] + (a[i + 6] * b[i + 6] + acc0)))
        acc1 = a[i + 1] * b[i + 1] + (a[i + 3] * b[i + 3] + (a[i + 5] * b[i + 5] + (a[i + 7] * b[i + 7] + acc1)))
        i += 8
    while i < n:
        acc0 = a[i] * b[i] + acc0
        if i + 1 < n:
            acc1 = a[i + 1] * b[i + 1] + acc1
        i += 2
    return acc0 + acc1


@borrowing
def _block_sum(a: np.ndarray, lo: int, n: int) -> float:
    """``numpy.sum``'s sum of at most 128 values a[lo:lo + n]: one by one below 8, else eight
    accumulators, added pairwise, then the rest one by one."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[lo + i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - n % 8:
        j = lo + i
        r0 += a[j]
        r1 += a[j + 1]
        r2 += a[j + 2]
        r3 += a[j + 3]
        r4 += a[j + 4]
        r5 += a[j + 5]
        r6 += a[j + 6]
        r7 += a[j + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@njit(cache=True, error_model="numpy", _nrt=True)  # counting said explicitly: borrowing callers
def pairwise_sum(a: np.ndarray, lo: int, n: int) -> float:
    """Σ a[lo:lo + n] in ``numpy.sum``'s pairwise order: blocks of at most 128 values
    (:func:`_block_sum`), longer runs halved (the first half a multiple of 8) and their sums
    added. Without recursion (an explicit stack): numba's cache cannot load a recursive
    function's specialisations."""
    if n <= 128:
        return _block_sum(a, lo, n)
    frames = np.zeros((64, 4))  # lo, n, stage, left sum
    frames[0, 0], frames[0, 1] = lo, n
    top, ret = 1, 0.0
    while top > 0:
        f = top - 1
        flo, fn, stage = int(frames[f, 0]), int(frames[f, 1]), frames[f, 2]
        n2 = fn // 2 - (fn // 2) % 8
        if fn <= 128 or stage == 2.0:
            ret = _block_sum(a, flo, fn) if fn <= 128 else frames[f, 3] + ret
            top -= 1
            continue
        if stage == 1.0:
            frames[f, 3] = ret
        frames[f, 2] = stage + 1.0
        frames[top, 0], frames[top, 1], frames[top, 2] = (flo, n2, 0.0) if stage == 0.0 else (flo + n2, fn - n2, 0.0)
        top += 1
    return ret

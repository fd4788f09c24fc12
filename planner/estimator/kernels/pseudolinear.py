"""Compiled pseudo-linear initialisation (one batch element at a time;
:mod:`planner.estimator.initialisation`'s successor, the package doc's step 1): the normal
equations of the rows (:func:`pl_rows`, :func:`pl_range_rows`), the distance scales of their
weights, the constrained solution (:func:`pl_solve`), the initialisation test
(:func:`determined`) and the Schur complement that marginalises R = ‖p0‖² (:func:`schur_prior`).
A system is A (4, 4), b (4,) in θ = (p0, R).

The sums run in numpy's order (:func:`~planner.estimator.kernels.linalg.dot`,
:func:`~planner.estimator.kernels.linalg.pairwise_sum`): for coplanar drones the two roots of
the range constraint are mirror images of equal cost and height, and which one is taken
depends on the last bits of the system.
"""

from __future__ import annotations

import math

import numpy as np

from planner.estimator.kernels.linalg import borrowing, counting, dot, eigh, eigvalsh_min, median, nmax, pairwise_sum
from planner.estimator.kernels.robust import R_AA, R_AE, R_AR, R_PX, R_PY, R_PZ, R_S0, R_ZA, R_ZE, R_ZR
from planner.estimator.layout import P_GAMMA, P_INIT_D, P_INIT_REL, P_MIRROR_BELOW, P_PL_RCOND, P_SB


@counting
def _normal_equations(c: np.ndarray, om: np.ndarray, beta: np.ndarray, m: int, A: np.ndarray, b: np.ndarray) -> None:
    """A += Σ ω c cᵀ, b += Σ ω c β over m equations (coefficients ``c`` (4, m)), each sum
    formed as numpy forms it: (ω c_i)·c_j."""
    wc = np.empty((4, m))
    for i in range(4):
        for k in range(m):
            wc[i, k] = om[k] * c[i, k]
    for i in range(4):
        for j in range(i, 4):
            s = dot(wc[i], c[j], m)
            A[i, j] += s
            if j != i:
                A[j, i] += s
        b[i] += dot(wc[i], beta, m)


@counting
def pl_rows(rows: np.ndarray, n: int, D: float, p: np.ndarray, A: np.ndarray, b: np.ndarray) -> None:
    """A, b += the pseudo-linear normal equations of the first n rows, weights at the distance
    D (m): azimuth (sin φ̂, −cos φ̂, 0)·(p0 − p) = 0, ω = a/(σ_b² (D cos θ̂)²); elevation with an
    azimuth, ω = a/(σ_b² D²); range with a bearing uᵀ(p0 − p) = d̂, ω = a/σ_r²(D); range alone
    2pᵀp0 − R = ‖p‖² − d̂² + σ_r²(D), ω = a/(4D²σ_r²(D)). Stacked as numpy stacks them: every
    azimuth, then every elevation, range with bearing, range alone."""
    gamma, inv_sb2 = p[P_GAMMA], 1.0 / p[P_SB] ** 2
    c, om, beta = np.zeros((4, 4 * n)), np.empty(4 * n), np.empty(4 * n)
    for k in range(n):
        px, py, pz = rows[k, R_PX], rows[k, R_PY], rows[k, R_PZ]
        has_r, has_az = rows[k, R_AR] > 0.0, rows[k, R_AA] > 0.0
        has_b = has_az and rows[k, R_AE] > 0.0
        var_r = rows[k, R_S0] * rows[k, R_S0] * (D * D if gamma == 2.0 else D**gamma)
        cphi, sphi = math.cos(rows[k, R_ZA]), math.sin(rows[k, R_ZA])
        cth, sth = math.cos(rows[k, R_ZE]), math.sin(rows[k, R_ZE])
        ux, uy, zr = cth * cphi, cth * sphi, rows[k, R_ZR]
        om[k] = rows[k, R_AA] * inv_sb2 / nmax(D * D * cth * cth, 1e-6 * D * D) if has_az else 0.0
        om[n + k] = rows[k, R_AE] * inv_sb2 / (D * D) if has_b else 0.0
        om[2 * n + k] = rows[k, R_AR] / var_r if (has_r and has_b) else 0.0
        om[3 * n + k] = rows[k, R_AR] / (4.0 * D * D * var_r) if (has_r and not has_b) else 0.0
        c[0, k], c[1, k] = sphi, -cphi
        c[0, n + k], c[1, n + k], c[2, n + k] = -sth * cphi, -sth * sphi, cth
        c[0, 2 * n + k], c[1, 2 * n + k], c[2, 2 * n + k] = ux, uy, sth
        c[0, 3 * n + k], c[1, 3 * n + k], c[2, 3 * n + k], c[3, 3 * n + k] = 2.0 * px, 2.0 * py, 2.0 * pz, -1.0
        beta[k] = sphi * px - cphi * py
        beta[n + k] = cth * pz - sth * (cphi * px + sphi * py)
        beta[2 * n + k] = ux * px + uy * py + sth * pz + zr
        beta[3 * n + k] = px * px + py * py + pz * pz - zr * zr + var_r
    _normal_equations(c, om, beta, 4 * n, A, b)


@borrowing
def pl_range_rows(rows: np.ndarray, n: int, scale: np.ndarray, gamma: float, A: np.ndarray, b: np.ndarray, work: np.ndarray) -> None:
    """A, b += the squared-range equations 2pᵀp0 − R = ‖p‖² − d̂² + σ_r²(D) of every range of the
    first n rows, ω = a/(4D²σ_r²(D)), D = ``scale[k]`` (m); summed in numpy's order. ``work``
    (8, ≥ n) scratch: the coefficients, their weighted copies, ω and the right-hand sides."""
    c, wc, om, beta = work[0:3], work[3:6], work[6], work[7]
    # D^γ in a loop of its own, not beside γ = 2's D²: the compiler would compute both and
    # keep one (a pow call for every row).
    if gamma == 2.0:
        for k in range(n):
            om[k] = scale[k] * scale[k]
    else:
        for k in range(n):
            om[k] = scale[k] ** gamma
    for k in range(n):
        px, py, pz = rows[k, R_PX], rows[k, R_PY], rows[k, R_PZ]
        D = scale[k]
        D2 = D * D
        var_r = rows[k, R_S0] * rows[k, R_S0] * om[k]
        om[k] = rows[k, R_AR] / (4.0 * D2 * var_r)
        c[0, k], c[1, k], c[2, k] = 2.0 * px, 2.0 * py, 2.0 * pz
        beta[k] = px * px + py * py + pz * pz - rows[k, R_ZR] * rows[k, R_ZR] + var_r
    for i in range(3):
        for k in range(n):
            wc[i, k] = om[k] * c[i, k]
    for i in range(3):
        for j in range(i, 3):
            s = dot(wc[i], c[j], n)
            A[i, j] += s
            if j != i:
                A[j, i] += s
        s = -pairwise_sum(wc[i], np.int64(0), n)
        A[i, 3] += s
        A[3, i] += s
        b[i] += dot(wc[i], beta, n)
    A[3, 3] += pairwise_sum(om, np.int64(0), n)
    b[3] += -dot(om, beta, n)


@counting
def distance_scale(rows: np.ndarray, n: int, p: np.ndarray) -> float:
    """The median measured range of the first n rows (at least 1 m), or ``init_distance_m``
    (m) where none has a range."""
    z = np.empty(max(n, 1))
    m = np.int64(0)
    for k in range(n):
        if rows[k, R_AR] > 0.0:
            z[m] = abs(rows[k, R_ZR])
            m += 1
    if m == 0:
        return p[P_INIT_D]
    return nmax(median(z, m), 1.0)


@borrowing
def range_scale(x: np.ndarray, initialised: bool, rows: np.ndarray, n: int, p: np.ndarray, out: np.ndarray) -> None:
    """``out[k]``, the distance scale of row k's squared-range weight (k < n): |x − p_k| (at
    least 1 m) where the element is initialised, else :func:`distance_scale` of the rows."""
    D = distance_scale(rows, n, p) if not initialised else 0.0
    for k in range(n):
        if initialised:
            rx, ry, rz = x[0] - rows[k, R_PX], x[1] - rows[k, R_PY], x[2] - rows[k, R_PZ]
            out[k] = math.sqrt(nmax(rx * rx + ry * ry + rz * rz, 1.0))
        else:
            out[k] = D


@borrowing
def pl_cost(A: np.ndarray, b: np.ndarray, x: np.ndarray) -> float:
    """θᵀAθ − 2bᵀθ at θ = (x, ‖x‖²), in numpy's order (bᵀθ as :func:`dot` sums four terms)."""
    t0, t1, t2 = x[0], x[1], x[2]
    t3 = dot(x, x, np.int64(3))
    q = 0.0
    for i in range(4):
        ti = t0 if i == 0 else (t1 if i == 1 else (t2 if i == 2 else t3))
        for j in range(4):
            tj = t0 if j == 0 else (t1 if j == 1 else (t2 if j == 2 else t3))
            q += ti * A[i, j] * tj
    acc0 = b[2] * t2 + (b[0] * t0 + 0.0)
    acc1 = b[3] * t3 + (b[1] * t1 + 0.0)
    return q - 2.0 * (acc0 + acc1)


@borrowing
def schur_prior(A: np.ndarray, b: np.ndarray, lam: np.ndarray, eta: np.ndarray) -> None:
    """Λ (3, 3), η (3,): R marginalised out of (A, b), Λ = A_pp − A_pR A_RR⁻¹ A_Rp,
    symmetrised."""
    arr = A[3, 3]
    big = arr > 1e-300
    for i in range(3):
        coupling = A[i, 3] / arr if big else 0.0
        for j in range(3):
            lam[i, j] = A[i, j] - coupling * A[3, j]
        eta[i] = b[i] - coupling * b[3]
    for i in range(3):
        for j in range(i + 1, 3):
            lam[i, j] = lam[j, i] = 0.5 * (lam[i, j] + lam[j, i])


@borrowing
def determined(A: np.ndarray, p: np.ndarray) -> bool:
    """Whether the PL system determines the source well enough to initialise from: any with a
    squared-range equation; with bearings only, one whose weakest direction's standard
    deviation is at most ``init_max_relative_sigma`` × ``init_distance_m``."""
    rel = p[P_INIT_REL]
    if rel != rel or A[3, 3] > 1e-300:
        return True
    limit = rel * p[P_INIT_D]
    return eigvalsh_min(A[:3, :3]) * limit * limit >= 1.0


@borrowing
def _ls_solution(A: np.ndarray, b: np.ndarray, p: np.ndarray, theta: np.ndarray, v: np.ndarray, work: np.ndarray) -> tuple[float, int]:
    """θ_LS (``theta``, 4) of the Jacobi-scaled system's well-conditioned part (R decoupled
    when it has no squared-range equation), its weakest direction in θ units (``v``, 4);
    returns that direction's R component in the scaled frame and the rank. ``work`` (≥ 48,)
    scratch."""
    As, s, bs = work[0:16].reshape((4, 4)), work[16:20], work[20:24]
    no_r = not A[3, 3] > 1e-300
    for i in range(4):
        d = 1.0 if (no_r and i == 3) else A[i, i]
        s[i] = 1.0 / math.sqrt(nmax(d, 1e-300)) if d > 1e-300 else 1.0
        bs[i] = (0.0 if (no_r and i == 3) else b[i]) * s[i]
    for i in range(4):
        for j in range(4):
            a = (1.0 if i == j else 0.0) if (no_r and (i == 3 or j == 3)) else A[i, j]
            As[i, j] = a * s[i] * s[j]
    ev, V = work[24:28], work[28:44].reshape((4, 4))
    eigh(As, ev, V)
    tol = p[P_PL_RCOND] * nmax(ev[3], 1e-300)
    inv_ev = work[44:48]
    rank = 0
    for j in range(4):
        inv_ev[j] = 0.0
        if ev[j] > tol:
            inv_ev[j] = 1.0 / ev[j]
            rank += 1
    for i in range(4):
        y = 0.0
        for k in range(4):
            for j in range(4):
                y += V[i, j] * inv_ev[j] * V[k, j] * bs[k]
        theta[i] = y * s[i]
        v[i] = V[i, 0] * s[i]
    return V[3, 0], rank


@borrowing
def pl_solve(A: np.ndarray, b: np.ndarray, p: np.ndarray, out: np.ndarray, work: np.ndarray) -> bool:
    """Solve the PL normal equations for p0 (``out``, 0 where not ok); returns ok. The
    candidates are θ_LS (if full rank) and the two points of the line θ_LS + t v along the
    weakest direction that satisfy R = ‖p0‖² (Cheung et al. 2004); the one of lowest
    constrained PL cost, near-ties broken by ``mirror`` (the lower or the upper point).
    ``work`` (≥ 65,) scratch."""
    has_r = A[3, 3] > 1e-300
    theta, v = work[0:4], work[4:8]
    v_r, rank = _ls_solution(A, b, p, theta, v, work[17:])
    x, r1, r2 = work[8:11], work[11:14], work[14:17]
    for i in range(3):
        x[i] = theta[i]
    cost_ls = pl_cost(A, b, x) if rank == 4 else np.inf
    qa = dot(v, v, np.int64(3))
    use_root = False
    if has_r and rank >= 3 and abs(v_r) > 1e-6 and qa > 1e-300:
        qb = 2.0 * dot(x, v, np.int64(3)) - v[3]
        qc = dot(x, x, np.int64(3)) - theta[3]
        sq = math.sqrt(abs(qb * qb - 4.0 * qa * qc))
        t1, t2 = (-qb - sq) / (2.0 * qa), (-qb + sq) / (2.0 * qa)
        for i in range(3):
            r1[i], r2[i] = x[i] + t1 * v[i], x[i] + t2 * v[i]
        c1, c2 = pl_cost(A, b, r1), pl_cost(A, b, r2)
        tie = np.isfinite(c1) and np.isfinite(c2) and abs(c1 - c2) <= 1e-9 * (abs(c1) + 1.0)
        prefer1 = r1[2] <= r2[2] if p[P_MIRROR_BELOW] != 0.0 else r1[2] >= r2[2]
        first = prefer1 if tie else c1 < c2
        c_root = c1 if first else c2
        use_root = c_root < cost_ls
        if use_root:
            x = r1 if first else r2
    ok = (rank == 4 or use_root) and np.isfinite(x[0]) and np.isfinite(x[1]) and np.isfinite(x[2])
    for i in range(3):
        out[i] = x[i] if ok else 0.0
    return ok

r"""The compiled estimator update (:func:`update_batch`): one call updates every batch element,
each on its own (the method of :mod:`planner.estimator`, steps 1-5; the numbered steps below are
:func:`planner.estimator.update`'s). The state is packed as :mod:`planner.estimator.layout`
describes; the new records come as arrays (E, M, ...).

Per element (:func:`_element`): forgetting (:func:`_start`); the raw window merged with the new
records (:func:`_merge`); the pseudo-linear initialisation (:func:`_initialise`); the global
re-check, on the range memory's exact likelihood or the squared-range PL cost
(:func:`_recheck`); the robust refinement (:func:`_refine`); the marginalisation of the rows
leaving the window, the score test and the reported estimate (:func:`_finish`); the windows'
and the memory's advance.

Compile-time hygiene (the first update compiles everything once, then loads it from numba's
cache): constants passed to another kernel are typed (``np.int64``, ``np.bool_``) so that each
kernel compiles once, not once per literal value, and arrays are copied by loops (no slice
assignment, no reshape: each compiles its shape checks and error messages). The element's body
and the steps it calls once per element (the copies, :func:`_start`, :func:`fill_rows`,
:func:`_new_raw`, :func:`_merge`, :func:`_takes`, :func:`_gate_previous`, :func:`_refine`,
:func:`_finish`, :func:`_advance_range_window`, :func:`_count`) are compiled into the loop over
the elements (:func:`_elements`, ``inline="always"``, without reference counting as they are):
the state, the new records and the workspace, some forty arrays each passed as several words,
are not passed again for each element and step.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from planner.estimator.kernels import memory as km
from planner.estimator.kernels.linalg import borrowing, clip, counting, det3, inv3_spd, nmax, nmin, normalised_det
from planner.estimator.kernels.pseudolinear import (
    determined,
    distance_scale,
    pl_cost,
    pl_range_rows,
    pl_rows,
    pl_solve,
    range_scale,
    schur_prior,
)
from planner.estimator.kernels.robust import (
    NE,
    NRC,
    R_AA,
    R_AE,
    R_AR,
    R_PX,
    R_PY,
    R_PZ,
    R_S0,
    R_ZA,
    R_ZE,
    R_ZR,
    XB_HEAD,
    accumulate,
    add_prior,
    cost_at,
    evaluate,
    lm_iterations,
    redescend,
)
from planner.estimator.kernels.robust import (
    gate as _gate_rows,
)
from planner.estimator.layout import (
    F_CONS,
    F_DRA,
    F_DRB,
    F_EST,
    F_INFO,
    F_PFISH,
    F_PINFO,
    F_PLA,
    F_PLB,
    F_PRA,
    F_PRB,
    F_PVEC,
    F_SH,
    F_SV,
    I_ANG,
    I_COUNT,
    I_INIT,
    I_OBS,
    I_SUSP,
    NF,
    NI,
    NM,
    NRW,
    NW,
    P_CELLS,
    P_CONS_LAMBDA,
    P_CONS_THR,
    P_GAMMA,
    P_GATE,
    P_GATE_FRAC,
    P_HI,
    P_HUBER,
    P_INIT_ITER,
    P_ITER,
    P_LAMBDA,
    P_LL_DROP,
    P_LO,
    P_MIN_RCOND,
    P_ML,
    P_NLOS_BW,
    P_RADIUS,
    P_RECHECK_THR,
    P_RECHECK_TRUST,
    P_S0_LOS,
    P_S0_NLOS,
    P_SB,
    P_SUSP_DEFL,
    P_SUSP_FRAC,
    P_TUKEY,
    RW_LOS,
    RW_R,
    RW_W,
    W_AZ,
    W_EL,
    W_LOS,
    W_R,
    W_W,
)

#: Offsets into the flat pseudo-linear scratch of :func:`workspace`: :func:`pl_solve` uses
#: [0, 65), a range system's A [PLS_AP, PLS_AP + 16) and b [PLS_BP, PLS_BP + 4), the re-check's
#: system, candidate and prior [PLS_A, PLS_A + 38).
PLS_AP, PLS_BP, PLS_A, PLS_SIZE = 72, 88, 96, 136


# --------------------------------------------------------------------------- array helpers
@borrowing
def _get(f: np.ndarray, off: int, n: int, out: np.ndarray) -> None:
    """``out`` (n, n) = the matrix stored row-major at f[off:]."""
    for i in range(n):
        for j in range(n):
            out[i, j] = f[off + n * i + j]


@borrowing
def _put(f: np.ndarray, off: int, a: np.ndarray, scale: float) -> None:
    """The n × n matrix ``a`` times ``scale`` stored row-major at f[off:]."""
    n = a.shape[0]
    for i in range(n):
        for j in range(n):
            f[off + n * i + j] = a[i, j] * scale if scale != 1.0 else a[i, j]


@borrowing(inline="always")
def _copy2(dst: np.ndarray, src: np.ndarray) -> None:
    """dst = src, two C-contiguous 2-D arrays of one shape (one flat loop, which the compiler
    vectorises: the rows are a few values each)."""
    d, s = dst.reshape(dst.size), src.reshape(src.size)
    for i in range(s.shape[0]):
        d[i] = s[i]


@borrowing(inline="always")
def _copy1(dst: np.ndarray, src: np.ndarray) -> None:
    """dst = src, two 1-D arrays of one length."""
    for i in range(src.shape[0]):
        dst[i] = src[i]


# --------------------------------------------------------------------------- the records
@borrowing(inline="always")
def fill_rows(raw: np.ndarray, n: int, p: np.ndarray, extra_used: np.ndarray, rows: np.ndarray, xz: np.ndarray, xa: np.ndarray) -> None:
    """The first n rows (component-major, NaN replaced by 0 and weight 0) of the raw records
    ``raw`` (position, range, azimuth, elevation, LOS, weight, extension values): ranges get
    the row weight, bearings the row weight in LOS and ``nlos_bearing_weight`` × it in NLOS,
    extension values of the components in use the row weight; σ_r0 of the link."""
    nlos_w = p[P_NLOS_BW]
    for k in range(n):
        px, py, pz = raw[k, 0], raw[k, 1], raw[k, 2]
        ok = np.isfinite(px + py + pz)
        w = raw[k, W_W]
        los = raw[k, W_LOS] != 0.0
        wb = w * (1.0 if los else nlos_w)
        rows[k, R_PX], rows[k, R_PY], rows[k, R_PZ] = (px, py, pz) if ok else (0.0, 0.0, 0.0)
        for col, zcol, weight in ((R_ZR, W_R, w), (R_ZA, W_AZ, wb), (R_ZE, W_EL, wb)):
            z = raw[k, zcol]
            present = ok and np.isfinite(z)
            rows[k, col] = z if present else 0.0
            rows[k, col + 3] = weight if present else 0.0  # R_AR = R_ZR + 3, ...
        rows[k, R_S0] = p[P_S0_LOS] if los else p[P_S0_NLOS]
        for j in range(xz.shape[1]):
            z = raw[k, NW + j]
            present = ok and np.isfinite(z) and extra_used[j]
            xz[k, j] = z if present else 0.0
            xa[k, j] = w if present else 0.0


@borrowing(inline="always")
def _new_raw(pos: np.ndarray, rng: np.ndarray, az: np.ndarray, el: np.ndarray, los: np.ndarray, xv: np.ndarray, nraw: np.ndarray) -> None:
    """The new records of one element as raw rows, weight 1 where the position is finite."""
    for m in range(rng.shape[0]):
        nraw[m, 0], nraw[m, 1], nraw[m, 2] = pos[m, 0], pos[m, 1], pos[m, 2]
        nraw[m, W_R], nraw[m, W_AZ], nraw[m, W_EL] = rng[m], az[m], el[m]
        nraw[m, W_LOS] = 1.0 if los[m] else 0.0
        nraw[m, W_W] = 1.0 if np.isfinite(pos[m, 0] + pos[m, 1] + pos[m, 2]) else 0.0
        for j in range(xv.shape[1]):
            nraw[m, NW + j] = xv[m, j]


@borrowing(inline="always")
def _merge(win: np.ndarray, nraw: np.ndarray, lam: float, raw: np.ndarray) -> int:
    """All rows of this call into ``raw``: the window (weights times λ) then the new ones; with
    a window and new rows, the invalid ones first (stable: by validity, then by age). Returns
    their count K."""
    W, M, cols = win.shape[0], nraw.shape[0], raw.shape[1]
    k = 0
    for valid in (False, True):
        for i in range(W):
            if (M > 0 and np.isfinite(win[i, 0]) != valid) or (M == 0 and valid):
                continue
            for j in range(cols):
                raw[k, j] = win[i, j]
            raw[k, W_W] = win[i, W_W] * lam
            k += 1
        for m in range(M):
            if (W > 0 and (nraw[m, W_W] > 0.0) != valid) or (W == 0 and valid):
                continue
            for j in range(cols):
                raw[k, j] = nraw[m, j]
            k += 1
    return k


@borrowing
def _range_rows(rw: np.ndarray, n: int, factor: float, p: np.ndarray, rrows: np.ndarray) -> None:
    """Rows (ranges only) of the first n range-window rows ``rw`` (position, range, LOS,
    weight), their weights times ``factor``."""
    for k in range(n):
        px, py, pz = rw[k, 0], rw[k, 1], rw[k, 2]
        ok = np.isfinite(px + py + pz)
        present = ok and np.isfinite(rw[k, RW_R])
        for j in range(NRC):
            rrows[k, j] = 0.0
        rrows[k, R_PX], rrows[k, R_PY], rrows[k, R_PZ] = (px, py, pz) if ok else (0.0, 0.0, 0.0)
        rrows[k, R_ZR] = rw[k, RW_R] if present else 0.0
        rrows[k, R_AR] = rw[k, RW_W] * factor if present else 0.0
        rrows[k, R_S0] = p[P_S0_LOS] if rw[k, RW_LOS] != 0.0 else p[P_S0_NLOS]


@borrowing
def _insert_ranges(mem: np.ndarray, nc: int, nrows: np.ndarray, memory: tuple, p: np.ndarray, keep: bool) -> int:
    """The ranges of the rows ``nrows`` join the memory ``mem`` whose first nc cells are used
    (``memory`` = :func:`workspace`'s memory scratch: contiguous columns for the rows'
    positions, ranges, weights and σ_r0, and the insertion's record of the cells it changed,
    their columns before it if ``keep``); returns the new count of used cells."""
    _, sc, iw, backup, cols = memory
    pos, zr, ar, s0 = cols
    for m in range(nrows.shape[0]):
        pos[m, 0], pos[m, 1], pos[m, 2] = nrows[m, R_PX], nrows[m, R_PY], nrows[m, R_PZ]
        zr[m], ar[m], s0[m] = nrows[m, R_ZR], nrows[m, R_AR], nrows[m, R_S0]
    return km.insert(mem, nc, pos, zr, ar, s0, p[P_RADIUS], iw, backup, sc, keep)


@borrowing(inline="always")
def _takes(angles_before: bool, nrows: np.ndarray, nxa: np.ndarray, p: np.ndarray) -> bool:
    """Whether this call's ranges join the range memory: the memory is on, the new rows carry a
    range and the element never used another component (these rows included)."""
    ranges, angles = False, angles_before
    for m in range(nrows.shape[0]):
        ranges = ranges or nrows[m, R_AR] > 0.0
        angles = angles or nrows[m, R_AA] > 0.0 or nrows[m, R_AE] > 0.0
        for j in range(nxa.shape[1]):
            angles = angles or nxa[m, j] > 0.0
    return ranges and p[P_CELLS] > 0 and not angles


# --------------------------------------------------------------------------- steps 1 and 3
@borrowing(inline="always")
def _start(fi: np.ndarray, io: np.ndarray, p: np.ndarray, fo: np.ndarray) -> None:
    """The output row before the call's records: the prior times λ (times λ·
    ``suspect_deflation`` for a suspect element), the PL systems times λ, the rest as was."""
    lam = p[P_LAMBDA]
    deflate = lam * p[P_SUSP_DEFL] if io[I_SUSP] != 0 else lam
    for j in range(fo.shape[0]):
        if F_PINFO <= j < F_PVEC + 3:
            fo[j] = fi[j] * deflate
        elif F_PLA <= j < F_PRB + 4:
            fo[j] = fi[j] * lam
        else:
            fo[j] = fi[j]


@borrowing
def _set_prior(fo: np.ndarray, lam: np.ndarray, fisher: np.ndarray, eta: np.ndarray, fisher_scale: float) -> None:
    """The prior (Λ, F × ``fisher_scale``, η) of the output row ``fo``."""
    _put(fo, np.int64(F_PINFO), lam, 1.0)
    _put(fo, np.int64(F_PFISH), fisher, fisher_scale)
    for i in range(3):
        fo[F_PVEC + i] = eta[i]


@counting
def _initialise(fo: np.ndarray, x: np.ndarray, nrows: np.ndarray, p: np.ndarray, pls: np.ndarray) -> bool:
    """Step 1 for an element not initialised: the new records' PL equations join its system;
    where it becomes solvable (and :func:`determined`) the estimate is its solution in the
    box and the records dropped before initialisation become the prior. Returns whether it
    initialised now. ``pls``: :func:`workspace`'s pseudo-linear scratch."""
    M = nrows.shape[0]
    A_new, b_new = np.zeros((4, 4)), np.zeros(4)
    pl_rows(nrows, M, distance_scale(nrows, M, p), p, A_new, b_new)
    A, b = np.empty((4, 4)), np.empty(4)
    for i in range(4):
        for j in range(4):
            fo[F_PLA + 4 * i + j] += A_new[i, j]
            A[i, j] = fo[F_PLA + 4 * i + j]
        fo[F_PLB + i] += b_new[i]
        b[i] = fo[F_PLB + i]
    xi = np.empty(3)
    if not (pl_solve(A, b, p, xi, pls) and determined(A, p)):
        return False
    for i in range(3):
        x[i] = clip(xi[i], p[P_LO + i], p[P_HI + i])
    lam, eta = np.empty((3, 3)), np.empty(3)
    dropped = np.empty((4, 4))
    _get(fo, np.int64(F_DRA), np.int64(4), dropped)
    schur_prior(dropped, fo[F_DRB : F_DRB + 4], lam, eta)
    _set_prior(fo, lam, lam, eta, 1.0)
    return True


@counting
def _recheck_memory(
    fo: np.ndarray,
    x: np.ndarray,
    flags: np.ndarray,
    mo: np.ndarray,
    memory: tuple,
    mi: np.ndarray,
    nrows: np.ndarray,
    cand: np.ndarray,
    p: np.ndarray,
) -> None:
    """Step 3 on the range memory (an initialised element that used only ranges): ``mo`` the
    element's memory, ``memory`` = (a scratch memory, pass scratch, the insertion's record, its
    saved cells, columns), ``mi`` = (cells used before this call's ranges, after, whether mo already holds
    them). memt = the memory with this call's ranges (mo, or the scratch). The previous
    estimate and the best start of another basin are polished to their optima on memt's
    likelihood; when the previous estimate is less likely than the better one by more than
    ``recheck_likelihood_drop``, the element moves there with the memory's cost before this
    call's ranges (those are rows) re-linearised there as its prior."""
    memt, sc, iw, backup, _ = memory
    gamma = p[P_GAMMA]
    nc0, take = mi[0], mi[2] != 0
    if take:
        memt, nct = mo, mi[1]
    else:
        _copy2(memt, mo)
        nct = _insert_ranges(memt, nc0, nrows, memory, p, np.bool_(False))
    x_prev, here, there = fo[F_EST : F_EST + 3], np.empty(3), np.empty(3)
    _copy1(here, x_prev)
    km.best_start(memt, nct, x_prev, cand, gamma, p, np.int64(16), sc, there)
    nll_here, start = km.polish(memt, nct, here, gamma, p, np.int64(15), 1e-3, sc)
    nll_there, _ = km.polish(memt, nct, there, gamma, p, np.int64(15), 1e-3, sc)
    best = there if nll_there < nll_here else here
    gain = start - nmin(nll_here, nll_there)
    if not (nct > 0 and gain > p[P_LL_DROP]):
        return
    if take:  # the cells as they were before this call's ranges
        km.swap_backup(mo, iw, backup)
    g, H, F = np.empty(3), np.empty((3, 3)), np.empty((3, 3))
    km.evaluate(mo, nc0, best, gamma, p[P_ML] != 0.0, sc, g, H)
    km.evaluate(mo, nc0, best, gamma, np.bool_(True), sc, np.empty(3), F)
    if take:
        km.swap_backup(mo, iw, backup)
    eta = np.empty(3)
    for i in range(3):
        eta[i] = (H[i, 0] * best[0] + H[i, 1] * best[1] + H[i, 2] * best[2]) - g[i]
    _set_prior(fo, H, F, eta, 1.0)
    _copy1(x, best)
    flags[0] = flags[1] = True  # fresh start, long run


@borrowing
def _recheck_system(
    fo: np.ndarray, x_prev: np.ndarray, rw: np.ndarray, rrows: np.ndarray, scale: np.ndarray, p: np.ndarray, A: np.ndarray, b: np.ndarray, pl: tuple
) -> None:
    """The re-check's system (A, b): the squared-range summary plus the ranges still in the
    range window, weighted at the previous estimate. ``pl`` = :func:`workspace`'s
    pseudo-linear scratch (rows, flat)."""
    R = rw.shape[0]
    plw, pls = pl
    _range_rows(rw, R, p[P_LAMBDA], p, rrows)
    range_scale(x_prev, np.bool_(True), rrows, R, p, scale)
    A_p, b_p = pls[PLS_AP : PLS_AP + 16].reshape((4, 4)), pls[PLS_BP : PLS_BP + 4]
    _zero_system(A_p, b_p)
    pl_range_rows(rrows, R, scale, p[P_GAMMA], A_p, b_p, plw)
    for i in range(4):
        for j in range(4):
            A[i, j] = fo[F_PRA + 4 * i + j] + A_p[i, j]
        b[i] = fo[F_PRB + i] + b_p[i]


@borrowing
def _zero_system(A: np.ndarray, b: np.ndarray) -> None:
    """A (4, 4) and b (4,) set to zero."""
    for i in range(4):
        for j in range(4):
            A[i, j] = 0.0
        b[i] = 0.0


@borrowing
def _recheck(
    fo: np.ndarray,
    x: np.ndarray,
    flags: np.ndarray,
    ranges_only: bool,
    rw: np.ndarray,
    new: tuple,
    mo: np.ndarray,
    memory: tuple,
    mi: np.ndarray,
    scratch: tuple,
    p: np.ndarray,
    cb,
) -> None:
    """Step 3, the global re-check of an initialised element, every ``recheck_every``-th call
    with records. The candidate is the squared-range PL solution of all past ranges
    (:func:`_recheck_system`). An element that used only ranges is re-checked on the range
    memory (:func:`_recheck_memory`); the others move to the candidate when the PL cost drops by more than
    ``recheck_threshold`` and the new records prefer it (their full likelihood, Huber loss),
    claiming ``recheck_trust`` of the summary's information. ``new`` = (rows, extension values,
    weights) of the new records; ``scratch`` = (range rows, scales, evaluation, buffer,
    pseudo-linear scratch: rows, flat)."""
    nrows, nxz, nxa = new
    rrows, scale, ev, buf, plw, pls = scratch
    M = nrows.shape[0]
    x_prev = fo[F_EST : F_EST + 3]
    A, b = pls[PLS_A : PLS_A + 16].reshape((4, 4)), pls[PLS_A + 16 : PLS_A + 20]
    _recheck_system(fo, x_prev, rw, rrows, scale, p, A, b, (plw, pls))
    if not A[0, 0] + A[1, 1] + A[2, 2] + A[3, 3] > 0.0:
        return
    x_pl, cand = pls[PLS_A + 20 : PLS_A + 23], pls[PLS_A + 23 : PLS_A + 26]
    ok = pl_solve(A, b, p, x_pl, pls)
    for i in range(3):
        cand[i] = clip(x_pl[i] if ok else x_prev[i], p[P_LO + i], p[P_HI + i])
    if p[P_CELLS] > 0 and ranges_only:
        _recheck_memory(fo, x, flags, mo, memory, mi, nrows, cand, p)
        return
    huber, ml, gls = np.bool_(False), np.bool_(True), np.bool_(False)
    c_prev = cost_at(x_prev, nrows, M, nxz, nxa, p, p[P_HUBER], huber, ml, ev, gls, cb, buf)
    drop = pl_cost(A, b, x_prev) - pl_cost(A, b, cand)
    c_cand = cost_at(cand, nrows, M, nxz, nxa, p, p[P_HUBER], huber, ml, ev, gls, cb, buf)
    if drop > p[P_RECHECK_THR] and c_cand < c_prev:
        lam, eta = pls[PLS_A + 26 : PLS_A + 35].reshape((3, 3)), pls[PLS_A + 35 : PLS_A + 38]
        schur_prior(A, b, lam, eta)
        _set_prior(fo, lam, lam, eta, p[P_RECHECK_TRUST])
        _copy1(x, cand)
        flags[0] = flags[1] = True


# --------------------------------------------------------------------------- step 2
@borrowing(inline="always")
def _gate_previous(fi: np.ndarray, observable: bool, x: np.ndarray, rows: np.ndarray, K: int, p: np.ndarray, J: np.ndarray, gate: np.ndarray) -> None:
    """The innovation gate against the previous state (when ``gate_sigma`` is set and it was
    observable): tr(J⁻¹) = tr(adj J)/det J, m², bounds the variance of the previous estimate
    along any direction (J its information). ``J`` (3, 3), ``gate`` (3,): scratch."""
    if not (p[P_GATE] == p[P_GATE] and observable):
        return
    _get(fi, np.int64(F_INFO), np.int64(3), J)
    det = det3(J)
    if det > 0.0:
        tr_adj = J[1, 1] * J[2, 2] - J[1, 2] ** 2 + J[0, 0] * J[2, 2] - J[0, 2] ** 2 + J[0, 0] * J[1, 1] - J[0, 1] ** 2
        gate[0], gate[1], gate[2] = p[P_GATE], p[P_GATE_FRAC], tr_adj / det
        _gate_rows(x, rows, K, p, gate)


@borrowing(inline="always")
def _refine(
    fo: np.ndarray,
    x: np.ndarray,
    flags: np.ndarray,
    before: bool,
    K: int,
    rows: tuple,
    work: tuple,
    p: np.ndarray,
    cb,
    buf: np.ndarray,
    out: tuple,
    small: tuple,
) -> None:
    """Step 2, the robust refinement of an initialised element (its ``rows`` = (rows,
    extension values, weights), the gate applied before): ``iterations`` LM iterations
    (``init_iterations`` where initialised or moved this call, ``flags`` = (fresh start, long
    run)). ``work`` = (ev, xg, xh, counts) then holds the evaluation at the last iterate and
    ``out`` = (g, H, F, x_lin); ``small`` as for :func:`_finish` (slots 13-14 and 8-10)."""
    r, xz, xa = rows
    sm, sv = small
    ev, xg, xh, counts = work
    g, H, F, x_lin = out
    n_short = int(p[P_ITER])
    n_el = max(n_short, int(p[P_INIT_ITER])) if flags[1] else n_short
    rd0 = redescend(p[P_TUKEY] != 0.0, np.int64(0), flags[0], before, n_el)
    cost0 = evaluate(x, r, K, xz, xa, p, rd0, ev, xg, xh, counts, cb, buf)
    lam, eta = sm[13], sv[10]
    _get(fo, np.int64(F_PINFO), np.int64(3), lam)
    for i in range(3):
        eta[i] = fo[F_PVEC + i]
    if K == 0:
        accumulate(ev, K, K, xg, xh, g, H, F)
        add_prior(x, lam, eta, g, H)
        _copy1(x_lin, x)
        return
    lm_iterations(x, r, K, xz, xa, p, lam, eta, cost0, (flags[0], before, n_el), work, cb, buf, out, (sv[8], sm[14], sm[15], sv[9]))


# --------------------------------------------------------------------------- steps 3-5
@borrowing
def _leaving(refined: tuple, lam: np.ndarray, eta: np.ndarray, work: tuple, lo: int, hi: int, out: tuple) -> None:
    """``out`` = (g, H, F) of the rows lo..hi−1 at x_lin: from the evaluation ``work``, or, when
    they are all its rows, the totals of ``refined`` = (g, H, F, x_lin) minus the prior's part
    (as the update subtracts it)."""
    g, H, F, x_lin = refined
    go, Ho, Fo = out
    if lo == 0 and hi == work[0].shape[0]:
        for i in range(3):
            go[i] = g[i] - ((lam[i, 0] * x_lin[0] + lam[i, 1] * x_lin[1] + lam[i, 2] * x_lin[2]) - eta[i])
            for j in range(3):
                Ho[i, j] = H[i, j] - lam[i, j]
                Fo[i, j] = F[i, j]
    else:
        accumulate(work[0], lo, hi, work[1], work[2], go, Ho, Fo)


@borrowing
def _score_test(fo: np.ndarray, g_new: np.ndarray, H_new: np.ndarray, x_lin: np.ndarray, x: np.ndarray, p: np.ndarray, scratch: tuple) -> bool:
    """Rao's score test of the recent records against the estimate x (package doc, step 3):
    S_H ← λ_c S_H + H_new, S_v ← λ_c S_v + H_new x_lin − g_new, T = sᵀS_H⁻¹s with s = S_H x − S_v
    (coordinates on the search box left out). Returns whether T exceeds the threshold (the
    recent model is then reset). ``scratch`` = (3, 3), (3,), (3, 3), (3, 3)."""
    lc = p[P_CONS_LAMBDA]
    S_H, s, S_t, S_inv = scratch
    for i in range(3):
        fo[F_SV + i] = fo[F_SV + i] * lc + ((H_new[i, 0] * x_lin[0] + H_new[i, 1] * x_lin[1] + H_new[i, 2] * x_lin[2]) - g_new[i])
        for j in range(3):
            S_H[i, j] = fo[F_SH + 3 * i + j] * lc + H_new[i, j]
    tr = nmax(S_H[0, 0] + S_H[1, 1] + S_H[2, 2], 1e-300)
    free = 0  # bit i: coordinate i inside the box
    for i in range(3):
        if x[i] > p[P_LO + i] and x[i] < p[P_HI + i]:
            free |= 1 << i
        si = (S_H[i, 0] * x[0] + S_H[i, 1] * x[1] + S_H[i, 2] * x[2]) - fo[F_SV + i]
        s[i] = si if (free >> i) & 1 else 0.0
    for i in range(3):
        for j in range(3):
            S_t[i, j] = S_H[i, j] if ((free >> i) & (free >> j) & 1) else (tr if i == j else 0.0)
    T = 0.0
    if inv3_spd(S_t, S_inv):
        for i in range(3):
            T += s[i] * (S_inv[i, 0] * s[0] + S_inv[i, 1] * s[1] + S_inv[i, 2] * s[2])
    fo[F_CONS] = T
    fail = p[P_CONS_THR] < T
    _put(fo, np.int64(F_SH), S_H, 0.0 if fail else 1.0)
    for i in range(3):
        fo[F_SV + i] = 0.0 if fail else fo[F_SV + i]
    return fail


@borrowing
def _suspect(counts: np.ndarray, p: np.ndarray) -> bool:
    """More than ``suspect_fraction`` of the values of one component type (at least 2.5,
    weighted) lie beyond ``suspect_sigma``."""
    for t in range(counts.shape[1]):  # noqa: SIM110 - compiled: no generator
        if counts[0, t] >= 2.5 and counts[1, t] > p[P_SUSP_FRAC] * counts[0, t]:
            return True
    return False


@borrowing(inline="always")
def _finish(fo: np.ndarray, fi: np.ndarray, x: np.ndarray, M: int, work: tuple, p: np.ndarray, refined: tuple, small: tuple) -> tuple[bool, bool]:
    """Steps 3-5 after the refinement of an initialised element: the suspect flag, the rows
    leaving the window (the oldest M) marginalised into the prior (linearised at x_lin), the
    score test of the newest M and the reported estimate (kept where not finite), information
    (symmetrised) and observability. Returns (observable, suspect). ``small`` = (matrices
    (≥ 13, 3, 3), vectors (≥ 8, 3)) scratch: slots 3.. of each."""
    sm, sv = small
    K = work[0].shape[0]
    F = refined[2]
    lam, fis = sm[3], sm[4]
    _get(fo, np.int64(F_PINFO), np.int64(3), lam)
    _get(fo, np.int64(F_PFISH), np.int64(3), fis)
    eta = sv[4]
    for i in range(3):
        eta[i] = fo[F_PVEC + i]
    fisher = sm[5]
    for i in range(3):
        for j in range(3):
            fisher[i, j] = F[i, j] + fis[i, j]
    suspect = _suspect(work[3], p)
    if M > 0:
        gl, Hl, Fl = sv[5], sm[6], sm[7]
        _leaving(refined, lam, eta, work, np.int64(0), M, (gl, Hl, Fl))
        if p[P_CONS_THR] == p[P_CONS_THR] and K > 0:
            gn, Hn, Fn = sv[6], sm[8], sm[9]
            _leaving(refined, lam, eta, work, K - M, K, (gn, Hn, Fn))
            if _score_test(fo, gn, Hn, refined[3], x, p, (sm[10], sv[7], sm[11], sm[12])):
                suspect = True
                for i in range(3):
                    for j in range(3):
                        fisher[i, j] *= p[P_SUSP_DEFL]
        x_lin = refined[3]
        for i in range(3):
            eta[i] += (Hl[i, 0] * x_lin[0] + Hl[i, 1] * x_lin[1] + Hl[i, 2] * x_lin[2]) - gl[i]
            for j in range(3):
                lam[i, j] += Hl[i, j]
                fis[i, j] += Fl[i, j]
        _set_prior(fo, lam, fis, eta, 1.0)
    return _report(fo, fi, x, fisher, p), suspect


@borrowing
def _report(fo: np.ndarray, fi: np.ndarray, x: np.ndarray, fisher: np.ndarray, p: np.ndarray) -> bool:
    """The reported estimate and information (symmetrised), the previous estimate and none
    where either is not finite; returns observability, det J/(tr J/3)³ ≥ ``min_rcond``."""
    finite = np.isfinite(x[0]) and np.isfinite(x[1]) and np.isfinite(x[2])
    for i in range(3):
        for j in range(i, 3):
            fisher[i, j] = fisher[j, i] = 0.5 * (fisher[i, j] + fisher[j, i])
            finite = finite and np.isfinite(fisher[i, j])
    for i in range(3):
        fo[F_EST + i] = x[i] if finite else fi[F_EST + i]
        for j in range(3):
            fo[F_INFO + 3 * i + j] = fisher[i, j] if finite else 0.0
    return finite and normalised_det(fisher) >= p[P_MIN_RCOND]


@counting
def _inactive(fo: np.ndarray, M: int, W: int, rows: np.ndarray, p: np.ndarray) -> None:
    """An element still not initialised: the estimate stays, no information; the rows leaving
    the window (the oldest M) join the PL equations dropped before initialisation."""
    for i in range(9):
        fo[F_INFO + i] = 0.0
    if W > 0 and M > 0:
        A, b = np.zeros((4, 4)), np.zeros(4)
        pl_rows(rows, M, distance_scale(rows, M, p), p, A, b)
        for i in range(4):
            for j in range(4):
                fo[F_DRA + 4 * i + j] += A[i, j]
            fo[F_DRB + i] += b[i]


# --------------------------------------------------------------------------- the windows and the memory
@borrowing(inline="always")
def _advance_range_window(
    fo: np.ndarray, initialised: bool, rw: np.ndarray, nraw: np.ndarray, scratch: tuple, p: np.ndarray, rwo: np.ndarray
) -> None:
    """The new ranges join the range window ``rwo`` (weights times λ); the oldest rows (the
    invalid ones first) leave it and join the re-check's squared-range summary, each weighted
    at this call's estimate. ``scratch`` = (range rows, scales, pool of ≥ M rows: the rows
    leaving, pseudo-linear scratch: rows, flat). One pass per validity over the window then
    the new rows, each row written once to where it goes."""
    R, M = rw.shape[0], nraw.shape[0]
    rrows, scale, pool, plw, pls = scratch
    lam = p[P_LAMBDA]
    k = 0
    for valid in (False, True):  # invalid rows first, stable: the first M leave
        for i in range(R + M):
            old = i < R
            m = i - R
            w = rw[i, RW_W] * lam if old else (1.0 if (nraw[m, W_W] > 0.0 and np.isfinite(nraw[m, W_R])) else 0.0)
            if M > 0 and R > 0 and (w > 0.0) != valid:
                continue
            if (M == 0 and not old) or ((M == 0 or R == 0) and valid):  # no partition: in order
                continue
            dst = pool[k] if k < M else rwo[k - M]
            if old:
                for j in range(NRW):
                    dst[j] = rw[i, j]
            else:
                dst[0], dst[1], dst[2] = nraw[m, 0], nraw[m, 1], nraw[m, 2]
                dst[RW_R], dst[RW_LOS] = nraw[m, W_R], nraw[m, W_LOS]
            dst[RW_W] = w
            k += 1
    if M == 0:
        return
    leaving = pool[:M]
    _range_rows(leaving, M, 1.0, p, rrows)
    has_range = False
    for m in range(M):
        has_range = has_range or rrows[m, R_AR] > 0.0
    if has_range:
        range_scale(fo[F_EST : F_EST + 3], initialised, rrows, M, p, scale)
        A_r, b_r = pls[PLS_AP : PLS_AP + 16].reshape((4, 4)), pls[PLS_BP : PLS_BP + 4]
        _zero_system(A_r, b_r)
        pl_range_rows(rrows, M, scale, p[P_GAMMA], A_r, b_r, plw)
        for i in range(4):
            for j in range(4):
                fo[F_PRA + 4 * i + j] += A_r[i, j]
            fo[F_PRB + i] += b_r[i]


@borrowing(inline="always")
def _count(io: np.ndarray, nrows: np.ndarray, nxa: np.ndarray) -> bool:
    """The values the new rows used join the count, and whether any record ever used a value
    other than a range; returns whether the new rows carry a range."""
    used, angles, ranges = 0, io[I_ANG] != 0, False
    for m in range(nrows.shape[0]):
        used += int(nrows[m, R_AR] > 0.0) + int(nrows[m, R_AA] > 0.0) + int(nrows[m, R_AE] > 0.0)
        angles = angles or nrows[m, R_AA] > 0.0 or nrows[m, R_AE] > 0.0
        ranges = ranges or nrows[m, R_AR] > 0.0
        for j in range(nxa.shape[1]):
            used += int(nxa[m, j] > 0.0)
            angles = angles or nxa[m, j] > 0.0
    io[I_COUNT] += used
    io[I_ANG] = angles
    return ranges


# --------------------------------------------------------------------------- one element, a batch
@borrowing(inline="always")
def _element(e: int, state: tuple, new: tuple, p: np.ndarray, due: bool, extra_used: np.ndarray, cb, ws: tuple, outs: tuple, overwrite: bool) -> None:
    """One element's update (the package doc's steps, in :func:`planner.estimator.update`'s
    order); ``ws`` = :func:`workspace`. With ``overwrite`` the outputs ``outs`` are the
    state's own arrays: the element's inputs are copied first (its range memory is updated
    in place)."""
    fs, ist, rwin, win, mem = state
    fs2, ist2, rwin2, win2, mem2 = outs
    raw, rows, xz, xa, nraw, nrows, nxz, nxa, ev, xg, xh, counts, rrows, scale, buf, memory, mi, pool, fi, ii, rw, small, flags, plw, pls = ws
    sm, sv = small
    _copy1(fi, fs[e])
    _copy1(ii, ist[e])
    _copy2(rw, rwin[e])
    fo, io, mo = fs2[e], ist2[e], mem2[e]
    _copy1(io, ii)
    if not overwrite:
        _copy2(mo, mem[e])
    _start(fi, io, p, fo)
    km.forget(mo, p[P_LAMBDA])
    _new_raw(new[0][e], new[1][e], new[2][e], new[3][e], new[4][e], new[5][e], nraw)
    M = nraw.shape[0]
    fill_rows(nraw, M, p, extra_used, nrows, nxz, nxa)
    K = _merge(win[e], nraw, p[P_LAMBDA], raw)
    fill_rows(raw, K, p, extra_used, rows, xz, xa)
    x = sv[0]
    for i in range(3):
        x[i] = fi[F_EST + i]
    before = ii[I_INIT] != 0
    flags[0] = ii[I_SUSP] != 0 and before  # fresh start, long run
    flags[1] = False
    if M > 0 and not before and _initialise(fo, x, nrows, p, pls):
        io[I_INIT] = 1
        flags[0] = flags[1] = True
    take = _takes(ii[I_ANG] != 0, nrows, nxa, p)
    ranges_only = ii[I_ANG] == 0
    # Read by the insertion and the re-check on the memory only (a scan of the cells: none for
    # an element that has used angles, whose memory stays empty).
    mi[0] = km.used_cells(mo) if (take or (due and before and ranges_only)) and mo.shape[1] > 0 else 0
    mi[1] = _insert_ranges(mo, mi[0], nrows, memory, p, np.bool_(due and before)) if take else mi[0]  # the re-check's swap reads the columns
    mi[2] = take
    if due and before:
        _recheck(fo, x, flags, ranges_only, rw, (nrows, nxz, nxa), mo, memory, mi, (rrows, scale, ev, buf, plw, pls), p, cb)
    obs, susp = False, False
    if io[I_INIT] != 0:
        _gate_previous(fi, ii[I_OBS] != 0 and before, x, rows, K, p, sm[2], sv[11])
        refined = (sv[1], sm[0], sm[1], sv[2])
        _refine(fo, x, flags, before, K, (rows, xz, xa), (ev, xg, xh, counts), p, cb, buf, refined, small)
        obs, susp = _finish(fo, fi, x, M, (ev, xg, xh, counts), p, refined, small)
    else:
        _inactive(fo, M, win.shape[1], rows, p)
    io[I_OBS], io[I_SUSP] = obs, susp
    _advance_range_window(fo, io[I_INIT] != 0, rw, nraw, (rrows, scale, pool, plw, pls), p, rwin2[e])
    if win.shape[1] > 0:
        _copy2(win2[e], raw[K - win.shape[1] : K])
    _count(io, nrows, nxa)


@counting
def workspace(W: int, M: int, R: int, C: int, X: int) -> tuple:
    """Scratch arrays of one element's update (reused by every element of a batch), K = W + M:
    the raw rows of the call, their rows, extension values and weights; the same for the new
    records; the evaluation (:func:`~planner.estimator.kernels.robust.evaluate`); range rows
    and distance scales; the extension callback's buffer; the memory scratch (a memory, pass
    scratch, the insertion's record and saved cells, columns of ranges) and its counts; the
    range window's pool; copies of the element's float row, flags and range window; small
    matrices (16, 3, 3) and vectors (16, 3) (slots: :func:`_element` 0-2, :func:`_finish`,
    :func:`_refine`; matrix 2 and vector 11: :func:`_gate_previous`); the element's two flags (fresh start, long run); the pseudo-linear
    scratch: rows (8, ·) of :func:`~planner.estimator.kernels.pseudolinear.pl_range_rows`
    and a flat array (:func:`~planner.estimator.kernels.pseudolinear.pl_solve`'s from 0,
    the range systems' from ``PLS_AP``, the re-check's from ``PLS_A``)."""
    K = W + M
    cols = (np.zeros((M, 3)), np.zeros(M), np.zeros(M), np.zeros(M))
    memory = (np.zeros((NM, C)), np.zeros((km.NSC, C)), np.zeros((6, 2 * M + 1), dtype=np.int64), np.zeros((NM, 2 * M)), cols)
    return (
        np.zeros((K, NW + X)),
        np.zeros((K, NRC)),
        np.zeros((K, X)),
        np.zeros((K, X)),
        np.zeros((M, NW + X)),
        np.zeros((M, NRC)),
        np.zeros((M, X)),
        np.zeros((M, X)),
        np.zeros((K, NE)),
        np.zeros((K, 3)),
        np.zeros((K, 9)),
        np.zeros((2, 3 + X)),
        np.zeros((R + M, NRC)),
        np.zeros(max(R + M, K, 1)),
        np.zeros(XB_HEAD + 3 * K + 5 * K * X),
        memory,
        np.zeros(3, dtype=np.int64),
        np.zeros((2 * (R + M), NRW)),
        np.zeros(NF),
        np.zeros(NI, dtype=np.int64),
        np.zeros((R, NRW)),
        (np.zeros((16, 3, 3)), np.zeros((16, 3))),
        np.zeros(2, dtype=np.bool_),
        np.zeros((8, max(R + M, K, 1))),
        np.zeros(PLS_SIZE),
    )


@njit(cache=True, error_model="numpy")
def update_batch(state: tuple, new: tuple, cfg: np.ndarray, channel: tuple, due: bool, extra_used: np.ndarray, cb, overwrite: bool) -> tuple:
    """One estimator update of every element of a batch, each on its own.

    Args:
        state: (fs, ist, rwin, win, mem), the packed state (:mod:`planner.estimator.layout`),
            leading axis E.
        new: the new records (positions (E, M, 3) m ENU, range (E, M) m, azimuth, elevation
            (E, M) rad, NaN where absent, LOS (E, M) bool, extension values (E, M, X)).
        cfg: the configuration (``EstimatorConfig.kernel_parameters``); ``channel`` = (γ,
            σ_r0 LOS, σ_r0 NLOS, σ_b).
        due: whether the global re-check runs in this call.
        extra_used: (X,) which extension values belong to a component in use.
        cb: the address of the extension components' callback (:attr:`planner.estimator.kernels.extension.Callback.address`; never called without such values).
        overwrite: write the new state into ``state``'s arrays (returned) instead of new ones.

    Returns:
        The packed state after the call.
    """
    p = cfg.copy()
    p[P_GAMMA], p[P_S0_LOS], p[P_S0_NLOS], p[P_SB] = channel
    fs, ist, rwin, win, mem = state
    outs = state if overwrite else (np.empty_like(fs), np.empty_like(ist), np.empty_like(rwin), np.empty_like(win), np.empty_like(mem))
    ws = workspace(win.shape[1], new[1].shape[1], rwin.shape[1], mem.shape[2], new[5].shape[2])
    _elements(state, new, p, due, extra_used, cb, ws, outs, overwrite)
    return outs


@borrowing
def _elements(state: tuple, new: tuple, p: np.ndarray, due: bool, extra_used: np.ndarray, cb, ws: tuple, outs: tuple, overwrite: bool) -> None:
    """:func:`_element` of every element of the batch, in order (its body compiled into this
    loop: the workspace's and the state's arrays are not passed again for each element)."""
    for e in range(state[0].shape[0]):
        _element(e, state, new, p, due, extra_used, cb, ws, outs, overwrite)


# The entry kernels built ahead of time, when they are (planner.aot): bound here, at import.
from planner.aot import bind as _bind  # noqa: E402

_bind("estimator", globals())

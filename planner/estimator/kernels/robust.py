r"""Compiled robust refinement (one batch element at a time; :mod:`planner.estimator.robust`
has the model): the records as rows, their normalised residuals and robust losses
(:func:`evaluate`, :func:`cost_at`), the gradient, scoring matrix and Fisher information summed
over rows (:func:`accumulate`) and the Levenberg-Marquardt iterations (:func:`lm_iterations`).

Rows (K, :data:`NRC`): drone position (m, ENU; 0 where invalid), measured range, azimuth,
elevation (0 where absent), their weights (0: unused) and the link's σ_r0. The X values of
components outside the range/bearing kernel come as ``xz`` (K, X) and weights ``xa`` (K, X);
their terms are computed by ``cb``, a callback into the components' own (Python) code, which
is called only when a row carries such a value (see :func:`extra_terms`).
"""

from __future__ import annotations

import math

import numpy as np

from planner.estimator.kernels.extension import call
from planner.estimator.kernels.linalg import borrowing, clip, counting, inv3_spd, nmax, nmin
from planner.estimator.layout import P_GAMMA, P_HI, P_HUBER, P_LM_DAMP, P_LO, P_ML, P_SB, P_SUSP_SIGMA, P_TUKEY, P_TUKEY_C

R_PX, R_PY, R_PZ, R_ZR, R_ZA, R_ZE, R_AR, R_AA, R_AE, R_S0 = 0, 1, 2, 3, 4, 5, 6, 7, 8, 9
NRC = 10

# Per-row evaluation (evaluate): r = x − p, ρ², then gradient factors gA, gB, gC, scoring
# factors hA, hB, hC, hF, distance d, the weights used (ar, aa, ae) and the extension
# components' summed weight; residuals e (er, ea, ee).
E_RX, E_RY, E_RZ, E_RHO2, E_GA, E_GB, E_GC, E_HA, E_HB, E_HC, E_HF, E_D = 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11
E_AR, E_AA, E_AE, E_XA, E_ER, E_EA, E_EE = 12, 13, 14, 15, 16, 17, 18
NE = 19

#: Floor (m²) of ρ², keeping the model finite right above or below a drone.
RHO2_FLOOR_M2 = 1e-12

# The extension callback's buffer: x (3), then the rows' positions (3 K) and values (K X), then
# its output e (K X) and ∂e/∂x (3 K X).
XB_HEAD = 3


@borrowing
def loss(e: float, k: float, c: float, tukey: bool) -> tuple[float, float, float]:
    """Robust loss ρ(e), influence ψ(e) and IRLS weight ψ/e: Tukey's biweight (threshold c)
    where ``tukey``, else Huber (threshold k)."""
    if tukey:
        t = 1.0 - nmin(e * e * (1.0 / (c * c)), 1.0)
        w = t * t
        return (c * c / 6.0) * (1.0 - w * t), w * e, w
    ae = abs(e)
    m = nmin(ae, k)
    return m * (ae - 0.5 * m), nmax(nmin(e, k), -k), k / nmax(ae, k)


@borrowing
def wrap(angle: float) -> float:
    """The angle wrapped into [−π, π] (rad)."""
    return angle - (2.0 * np.pi) * np.rint(angle * (0.5 / np.pi))


@borrowing
def residuals(
    x: np.ndarray, rows: np.ndarray, k: int, p: np.ndarray, dv_given: float
) -> tuple[float, float, float, float, float, float, float, float, float, float, float]:
    """Row k at source x: r = x − p (rx, ry, rz), ρ² (floored), ρ, d², d, σ_r = σ_r0 dv^{γ/2}
    (dv = ``dv_given`` if positive, else d) and e = (z − h)/σ for range, azimuth (wrapped),
    elevation (0 for an angle of weight 0)."""
    rx, ry, rz = x[0] - rows[k, R_PX], x[1] - rows[k, R_PY], x[2] - rows[k, R_PZ]
    rho2 = nmax(rx * rx + ry * ry, RHO2_FLOOR_M2)
    rho = math.sqrt(rho2)
    d2 = rz * rz + rho2
    d = math.sqrt(d2)
    gamma = p[P_GAMMA]
    dv = dv_given if dv_given > 0.0 else d
    sr = rows[k, R_S0] * (dv if gamma == 2.0 else dv ** (0.5 * gamma))
    inv_sr = 1.0 / sr
    inv_sb = 1.0 / p[P_SB]
    er = (rows[k, R_ZR] - d) * inv_sr
    # an angle of weight 0 is 0 (its terms are a·… = 0 whatever e is; the range's e carries a
    # NaN of x): no atan2 for a ranging-only row
    ea = wrap(rows[k, R_ZA] - math.atan2(ry, rx)) * inv_sb if rows[k, R_AA] != 0.0 else 0.0
    ee = (rows[k, R_ZE] - math.atan2(rz, rho)) * inv_sb if rows[k, R_AE] != 0.0 else 0.0
    return rx, ry, rz, rho2, rho, d2, d, sr, er, ea, ee


@borrowing
def extra_terms(
    cb, buf: np.ndarray, x: np.ndarray, rows: np.ndarray, K: int, xz: np.ndarray, xa: np.ndarray, p: np.ndarray, tukey: bool, grad: tuple, want: bool
) -> float:
    """The components outside the kernel at x: the callback at ``cb`` (their own code, an address:
    :func:`planner.estimator.kernels.extension.call`) leaves in ``buf`` the
    normalised residuals e (K, X) and gradients ∂e/∂x (K, X, 3) of the rows' values; returns
    their robust cost Σ a ρ(e) and, if ``want``, fills ``grad`` = (xg, xh, counts): per row
    Σ a ψ ∂e/∂x (K, 3) and Σ a w ∂e/∂x ∂e/∂xᵀ (K, 9) and their counts per value."""
    X = xz.shape[1]
    buf[0], buf[1], buf[2] = x[0], x[1], x[2]
    o = XB_HEAD
    for k in range(K):
        buf[o + k], buf[o + K + k], buf[o + 2 * K + k] = rows[k, R_PX], rows[k, R_PY], rows[k, R_PZ]
        for j in range(X):
            buf[o + 3 * K + k * X + j] = xz[k, j]
    call(cb, buf.ctypes.data, K, X)
    oe = o + 3 * K + K * X
    od = oe + K * X
    huber, c, c2 = p[P_HUBER], p[P_TUKEY_C], p[P_SUSP_SIGMA] * p[P_SUSP_SIGMA]
    cost = 0.0
    for k in range(K):
        for j in range(X):
            a = xa[k, j]
            e = buf[oe + k * X + j]
            rho_, psi, w = loss(e, huber, c, tukey)
            cost += a * rho_
            if not want:
                continue
            xg, xh, counts = grad
            for i in range(3):
                de_i = buf[od + 3 * (k * X + j) + i]
                xg[k, i] += a * psi * de_i
                for m in range(3):
                    xh[k, 3 * i + m] += a * w * de_i * buf[od + 3 * (k * X + j) + m]
            counts[0, 3 + j] += a
            counts[1, 3 + j] += a * (1.0 if e * e > c2 else 0.0)
    return cost


@borrowing
def cost_at(
    x: np.ndarray,
    rows: np.ndarray,
    K: int,
    xz: np.ndarray,
    xa: np.ndarray,
    p: np.ndarray,
    huber: float,
    tukey: bool,
    ml: bool,
    ev: np.ndarray,
    use_dvar: bool,
    cb,
    buf: np.ndarray,
) -> float:
    """Robust cost Σ a ρ(e) (+ ½ ln σ_r² of the ranges if ``ml``) of the rows at x, σ_r at the
    distances of the evaluation ``ev`` if ``use_dvar`` (generalised LS), plus the extension
    components'."""
    c = p[P_TUKEY_C]
    s_a = s_e = s_r = 0.0
    for k in range(K):
        _, _, _, _, _, _, _, sr, er, ea, ee = residuals(x, rows, k, p, ev[k, E_D] if use_dvar else -1.0)
        ar, aa, ae = rows[k, R_AR], rows[k, R_AA], rows[k, R_AE]
        cr = ar * loss(er, huber, c, tukey)[0]
        if ml:
            cr += ar * math.log(sr)
        s_a += aa * loss(ea, huber, c, tukey)[0]
        s_e += ae * loss(ee, huber, c, tukey)[0]
        s_r += cr
    cost = s_a + s_e + s_r
    if _has_extra(xa, K):
        cost = cost + _extra_cost(x, rows, K, xz, xa, p, tukey, cb, buf)
    return cost


@counting
def _extra_cost(x: np.ndarray, rows: np.ndarray, K: int, xz: np.ndarray, xa: np.ndarray, p: np.ndarray, tukey: bool, cb, buf: np.ndarray) -> float:
    """The extension components' cost at x (:func:`extra_terms`, their gradients not kept):
    apart from :func:`cost_at`, which allocates nothing without them."""
    grad = (np.zeros((K, 3)), np.zeros((K, 9)), np.zeros((2, 3 + xz.shape[1])))
    return extra_terms(cb, buf, x, rows, K, xz, xa, p, tukey, grad, np.bool_(False))


@borrowing
def _has_extra(xa: np.ndarray, K: int) -> bool:
    """Whether any of the first K rows carries a weighted extension value."""
    for k in range(K):
        for j in range(xa.shape[1]):
            if xa[k, j] != 0.0:
                return True
    return False


@borrowing
def gate(x: np.ndarray, rows: np.ndarray, K: int, p: np.ndarray, gate: np.ndarray) -> None:
    """The innovation gate (``gate`` = (σ, max fraction, variance bound tr Σ, m²)): a component
    whose innovation exceeds σ standard deviations of σ² + tr(Σ)‖∇h‖² gets weight 0 in
    ``rows``, unless more than the max fraction of the element's components would."""
    g2 = gate[0] * gate[0]
    tv = gate[2]
    inv_sb = 1.0 / p[P_SB]
    tb = tv * (inv_sb * inv_sb)
    n_out = n_all = 0
    for pas in range(2):
        for k in range(K):
            _, _, _, rho2, _, d2, _, sr, er, ea, ee = residuals(x, rows, k, p, -1.0)
            inv_sr = 1.0 / sr
            out_r = er * er > g2 * (1.0 + tv * inv_sr * inv_sr) and rows[k, R_AR] > 0.0
            out_a = ea * ea > g2 * (1.0 + tb / rho2) and rows[k, R_AA] > 0.0
            out_e = ee * ee > g2 * (1.0 + tb / d2) and rows[k, R_AE] > 0.0
            if pas == 0:
                n_out += int(out_r) + int(out_a) + int(out_e)
                n_all += int(rows[k, R_AR] > 0.0) + int(rows[k, R_AA] > 0.0) + int(rows[k, R_AE] > 0.0)
            else:
                rows[k, R_AR] = 0.0 if out_r else rows[k, R_AR]
                rows[k, R_AA] = 0.0 if out_a else rows[k, R_AA]
                rows[k, R_AE] = 0.0 if out_e else rows[k, R_AE]
        if not n_out <= gate[1] * n_all:
            return


@borrowing
def evaluate(
    x: np.ndarray,
    rows: np.ndarray,
    K: int,
    xz: np.ndarray,
    xa: np.ndarray,
    p: np.ndarray,
    tukey: bool,
    ev: np.ndarray,
    xg: np.ndarray,
    xh: np.ndarray,
    counts: np.ndarray,
    cb,
    buf: np.ndarray,
) -> float:
    """Robust cost of the rows at x (returned) and, per row, the factors of its gradient and
    scoring matrix (``ev``), the extension components' gradient ``xg`` (K, 3) and scoring
    matrix ``xh`` (K, 9), and per component type the weighted count of values used and of
    those beyond ``suspect_sigma`` (``counts`` (2, 3 + X))."""
    gamma, inv_sb = p[P_GAMMA], 1.0 / p[P_SB]
    huber, c, ml = p[P_HUBER], p[P_TUKEY_C], p[P_ML] != 0.0
    c2 = p[P_SUSP_SIGMA] * p[P_SUSP_SIGMA]
    sb2inv = inv_sb * inv_sb
    counts[:] = 0.0
    s_a = s_e = s_r = 0.0
    for k in range(K):
        rx, ry, rz, rho2, rho, _, d, sr, er, ea, ee = residuals(x, rows, k, p, -1.0)
        ar, aa, ae = rows[k, R_AR], rows[k, R_AA], rows[k, R_AE]
        rr_, pr_, wr_ = loss(er, huber, c, tukey)
        ra_, pa_, wa_ = loss(ea, huber, c, tukey)
        re_, pe_, we_ = loss(ee, huber, c, tukey)
        cr = ar * rr_
        if ml:
            cr += ar * math.log(sr)
        s_a += aa * ra_
        s_e += ae * re_
        s_r += cr
        inv_sr = 1.0 / sr
        inv_d, inv_rho = 1.0 / d, 1.0 / rho
        inv_d2, inv_rho2 = inv_d * inv_d, inv_rho * inv_rho
        wr = ar * inv_sr
        ir = wr * inv_sr * wr_
        gr = -wr * pr_
        gd = (0.5 * gamma) / d
        extra = ar * (2.0 * gd * gd)
        if ml:
            gr += ar * gd * (1.0 - pr_ * er)
            ir += extra
            extra = 0.0
        ev[k, E_RX], ev[k, E_RY], ev[k, E_RZ], ev[k, E_RHO2], ev[k, E_D] = rx, ry, rz, rho2, d
        ev[k, E_GA] = gr * inv_d
        ev[k, E_GB] = ((aa * -inv_sb) * pa_) * inv_rho2
        ev[k, E_GC] = ((ae * -inv_sb) * pe_) * (inv_d2 * inv_rho)
        ev[k, E_HA] = ir * inv_d2
        ev[k, E_HB] = (aa * sb2inv * wa_) * (inv_rho2 * inv_rho2)
        ev[k, E_HC] = (ae * sb2inv * we_) * (inv_d2 * inv_d2 * inv_rho2)
        ev[k, E_HF] = extra * inv_d2
        ev[k, E_AR], ev[k, E_AA], ev[k, E_AE], ev[k, E_XA] = ar, aa, ae, 0.0
        ev[k, E_ER], ev[k, E_EA], ev[k, E_EE] = er, ea, ee
        for t, (a, e) in enumerate(((ar, er), (aa, ea), (ae, ee))):
            counts[0, t] += a
            counts[1, t] += a * (1.0 if e * e > c2 else 0.0)
    cost = s_a + s_e + s_r
    xg[:K] = 0.0
    xh[:K] = 0.0
    if _has_extra(xa, K):
        cost = cost + extra_terms(cb, buf, x, rows, K, xz, xa, p, tukey, (xg, xh, counts), np.bool_(True))
        for k in range(K):
            ev[k, E_XA] = 0.0
            for j in range(xa.shape[1]):
                ev[k, E_XA] += xa[k, j]
    return cost


@borrowing
def accumulate(ev: np.ndarray, lo: int, hi: int, xg: np.ndarray, xh: np.ndarray, g: np.ndarray, H: np.ndarray, F: np.ndarray) -> None:
    """Gradient g (3,), scoring matrix H and Fisher information F (3, 3) of the rows lo..hi−1:
    with v = (−r_y, r_x, 0) and w = (−r_x r_z, −r_y r_z, ρ²), g = Σ gA r + gB v + gC w,
    H = Σ hA r rᵀ + hB v vᵀ + hC w wᵀ, F = H + Σ hF r rᵀ, plus the extension components'
    terms (their Fisher information is their scoring matrix)."""
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = s8 = s9 = s10 = 0.0
    s11 = s12 = s13 = s14 = s15 = s16 = s17 = s18 = s19 = s20 = 0.0
    for k in range(lo, hi):
        rx, ry, rz, rho2 = ev[k, E_RX], ev[k, E_RY], ev[k, E_RZ], ev[k, E_RHO2]
        gA, gB, gC = ev[k, E_GA], ev[k, E_GB], ev[k, E_GC]
        hA, hB, hC, hF = ev[k, E_HA], ev[k, E_HB], ev[k, E_HC], ev[k, E_HF]
        t = gA - gC * rz
        rzz = rz * rz
        q1, q2 = hA + hC * rzz, hA - hC * rho2
        rxx, ryy, rxy, rxz, ryz = rx * rx, ry * ry, rx * ry, rx * rz, ry * rz
        s0 += rx * t
        s1 += gB * ry
        s2 += ry * t
        s3 += gB * rx
        s4 += gA * rz
        s5 += gC * rho2
        s6 += rxx * q1
        s7 += ryy * hB
        s8 += ryy * q1
        s9 += rxx * hB
        s10 += rxy * (q1 - hB)
        s11 += rzz * hA
        s12 += rho2 * rho2 * hC
        s13 += rxz * q2
        s14 += ryz * q2
        s15 += rxx * hF
        s16 += ryy * hF
        s17 += rzz * hF
        s18 += rxy * hF
        s19 += rxz * hF
        s20 += ryz * hF
    g[0], g[1], g[2] = s0 - s1, s2 + s3, s4 + s5
    H[0, 0], H[1, 1], H[2, 2] = s6 + s7, s8 + s9, s11 + s12
    H[0, 1] = H[1, 0] = s10
    H[0, 2] = H[2, 0] = s13
    H[1, 2] = H[2, 1] = s14
    F[0, 0], F[1, 1], F[2, 2] = H[0, 0] + s15, H[1, 1] + s16, H[2, 2] + s17
    F[0, 1] = F[1, 0] = H[0, 1] + s18
    F[0, 2] = F[2, 0] = H[0, 2] + s19
    F[1, 2] = F[2, 1] = H[1, 2] + s20
    for k in range(lo, hi):
        if ev[k, E_XA] == 0.0:
            continue
        for i in range(3):
            g[i] += xg[k, i]
            for j in range(3):
                H[i, j] += xh[k, 3 * i + j]
                F[i, j] += xh[k, 3 * i + j]


@borrowing
def redescend(tukey: bool, it: int, fresh: bool, before: bool, n_el: int) -> bool:
    """Whether Tukey's biweight applies at iteration ``it`` (else Huber): settled elements
    always; after a pseudo-linear initialisation (``fresh`` and not initialised ``before``)
    from the second half of the element's ``n_el`` iterations; a suspect or moved element
    never in this call."""
    if not tukey:
        return False
    if not fresh:
        return True
    return 2 * it >= n_el and not before


@borrowing
def prior_cost(x: np.ndarray, lam: np.ndarray, eta: np.ndarray) -> float:
    """½ xᵀΛx − ηᵀx."""
    q = 0.0
    for i in range(3):
        q += x[i] * (lam[i, 0] * x[0] + lam[i, 1] * x[1] + lam[i, 2] * x[2])
    return 0.5 * q - (eta[0] * x[0] + eta[1] * x[1] + eta[2] * x[2])


@borrowing
def add_prior(x: np.ndarray, lam: np.ndarray, eta: np.ndarray, g: np.ndarray, H: np.ndarray) -> None:
    """g += Λx − η, H += Λ (the prior's gradient and curvature)."""
    for i in range(3):
        g[i] = g[i] + (lam[i, 0] * x[0] + lam[i, 1] * x[1] + lam[i, 2] * x[2]) - eta[i]
        for j in range(3):
            H[i, j] += lam[i, j]


@borrowing
def _lm_step(
    x: np.ndarray,
    g: np.ndarray,
    H: np.ndarray,
    mu: float,
    ev: np.ndarray,
    K: int,
    counts: np.ndarray,
    p: np.ndarray,
    cand: np.ndarray,
    scratch: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> None:
    """``cand``: the damped Fisher-scoring step from x, capped at half the mean distance to the
    records (weighted as used) and projected into the search box (x itself if the damped
    matrix is singular). ``scratch`` = two (3, 3) and a (3,)."""
    Hd, Hinv, step = scratch
    for i in range(3):
        for j in range(3):
            Hd[i, j] = H[i, j]
    tr = H[0, 0] + H[1, 1] + H[2, 2]
    for i in range(3):
        Hd[i, i] = H[i, i] + (mu * H[i, i] + 1e-12 * tr + 1e-300)
    ok = inv3_spd(Hd, Hinv)
    for i in range(3):
        step[i] = -(Hinv[i, 0] * g[0] + Hinv[i, 1] * g[1] + Hinv[i, 2] * g[2])
    n_w = nmax(np.sum(counts[0]), 1e-300)
    reach = 0.0
    for k in range(K):
        reach += ev[k, E_D] * (ev[k, E_AR] + ev[k, E_AA] + ev[k, E_AE] + ev[k, E_XA])
    reach = 0.5 * reach / n_w
    norm = math.sqrt(step[0] * step[0] + step[1] * step[1] + step[2] * step[2])
    shrink = reach / nmax(norm, 1e-300) if norm > reach else 1.0
    for i in range(3):
        cand[i] = clip(x[i] + (step[i] * shrink if ok else 0.0), p[P_LO + i], p[P_HI + i])


@borrowing
def lm_iterations(
    x: np.ndarray,
    rows: np.ndarray,
    K: int,
    xz: np.ndarray,
    xa: np.ndarray,
    p: np.ndarray,
    lam: np.ndarray,
    eta: np.ndarray,
    first_cost: float,
    schedule: tuple[bool, bool, int],
    work: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    cb,
    buf: np.ndarray,
    out: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    scratch: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
) -> None:
    """Levenberg-Marquardt (Fisher scoring) iterations of the robust cost plus the prior
    ½xᵀΛx − ηᵀx from x (3,), in place; ``schedule`` = (fresh, initialised before, n) with n the
    number of iterations (:func:`redescend`); ``work`` = (ev, xg, xh, counts) holds the
    evaluation at x on entry (cost ``first_cost``) and at the last iterate x_lin on exit. A
    step is kept only if the cost does not increase (then μ shrinks by 3, else grows by 4).
    ``out`` = (g, H, F, x_lin): gradient (prior included), scoring matrix (prior included) and
    Fisher information (prior excluded) at x_lin, and x_lin. ``scratch`` = (3,), two (3, 3), (3,)."""
    ev, xg, xh, counts = work
    g, H, F, x_lin = out
    fresh, before, n_el = schedule
    tukey, ml = p[P_TUKEY] != 0.0, p[P_ML] != 0.0
    mu = p[P_LM_DAMP]
    cost_ev = first_cost
    cand, Hd, Hinv, step = scratch
    for it in range(n_el):
        rd = redescend(tukey, it, fresh, before, n_el)
        if it > 0:
            cost_ev = evaluate(x, rows, K, xz, xa, p, rd, ev, xg, xh, counts, cb, buf)
        x_lin[0], x_lin[1], x_lin[2] = x[0], x[1], x[2]
        accumulate(ev, np.int64(0), K, xg, xh, g, H, F)
        add_prior(x, lam, eta, g, H)
        cost = cost_ev + prior_cost(x, lam, eta)
        _lm_step(x, g, H, mu, ev, K, counts, p, cand, (Hd, Hinv, step))
        c_new = cost_at(cand, rows, K, xz, xa, p, p[P_HUBER], rd, ml, ev, not ml, cb, buf) + prior_cost(cand, lam, eta)
        if np.isfinite(c_new) and c_new <= cost:
            x[0], x[1], x[2] = cand[0], cand[1], cand[2]
            mu = mu / 3.0
        else:
            mu = mu * 4.0

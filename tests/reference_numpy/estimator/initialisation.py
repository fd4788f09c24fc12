"""Initialisation: the pseudo-linear least-squares system of the ranges and bearings
(Cheung, So, Ma & Chan; the package doc, step 1), its solution with the range constraint,
and the Schur complement that turns records leaving the window into a prior."""

from __future__ import annotations

import numpy as np

from planner.params import Channel
from tests.reference_numpy.estimator.robust import _Rows, _sum
from tests.reference_numpy.estimator.state import BoolArray, EstimatorConfig, FloatArray


# --------------------------------------------------------------------------- pseudo-linear part
def _pl_rows(rows: _Rows, scale_d: FloatArray, channel: Channel) -> tuple[FloatArray, FloatArray]:
    """Pseudo-linear normal equations of the rows (..., K), summed: A (..., 4, 4), b (..., 4).

    Unknown θ = (x0, y0, z0, R = ‖p0‖²). Equations cᵀθ = β with weight ω, all linear in θ:

    * azimuth: (sin φ̂, −cos φ̂, 0)·(p0 − p) = 0, ω = a/(σ_b² (D cos θ̂)²);
    * elevation (with an azimuth): (−sin θ̂ cos φ̂, −sin θ̂ sin φ̂, cos θ̂)·(p0 − p) = 0,
      ω = a/(σ_b² D²);
    * range with a usable bearing u(φ̂, θ̂): uᵀ(p0 − p) = d̂, ω = a/σ_r²(D);
    * range alone: 2pᵀp0 − R = ‖p‖² − d̂² + σ_r²(D), ω = a/(4 D² σ_r²(D)) (the σ_r² term
      removes the bias E[d̂²] = d² + σ_r²; without it, 39 % ranging noise biases R).

    D = ``scale_d`` (..., K) is the distance used in the weights (see :func:`update`); it never
    depends on the row's own noisy range.
    """
    px, py, pz = rows.px, rows.py, rows.pz
    has_r = rows.ar > 0.0
    has_az = rows.aa > 0.0
    has_b = has_az & (rows.ae > 0.0)
    inv_sb2 = 1.0 / channel.sigma_bearing_rad**2
    D = scale_d
    var_r = rows.s0 * rows.s0 * (D * D if channel.gamma == 2.0 else D**channel.gamma)
    cphi, sphi = np.cos(rows.za), np.sin(rows.za)
    cth, sth = np.cos(rows.ze), np.sin(rows.ze)
    zero = np.zeros_like(px)
    rho_w2 = np.maximum(D * D * cth * cth, 1e-6 * D * D)
    w_az = np.where(has_az, rows.aa * inv_sb2 / rho_w2, 0.0)
    w_el = np.where(has_b, rows.ae * inv_sb2 / (D * D), 0.0)
    w_ru = np.where(has_r & has_b, rows.ar / var_r, 0.0)
    w_rr = np.where(has_r & ~has_b, rows.ar / (4.0 * D * D * var_r), 0.0)
    # Equations stacked along the last axis: (..., 4K).
    ux, uy = cth * cphi, cth * sphi
    c0 = np.concatenate((sphi, -sth * cphi, ux, 2.0 * px), axis=-1)
    c1 = np.concatenate((-cphi, -sth * sphi, uy, 2.0 * py), axis=-1)
    c2 = np.concatenate((zero, cth, sth, 2.0 * pz), axis=-1)
    c3 = np.concatenate((zero, zero, zero, zero - 1.0), axis=-1)
    b_az = sphi * px - cphi * py
    b_el = cth * pz - sth * (cphi * px + sphi * py)
    b_ru = ux * px + uy * py + sth * pz + rows.zr
    # E[d̂²] = d² + σ_r²(d): subtract σ_r²(D) so the squared-range equation is unbiased.
    b_rr = px * px + py * py + pz * pz - rows.zr * rows.zr + var_r
    beta = np.concatenate((b_az, b_el, b_ru, b_rr), axis=-1)
    om = np.concatenate((w_az, w_el, w_ru, w_rr), axis=-1)
    cs = (c0, c1, c2, c3)
    wc = [om * c for c in cs]
    A = np.empty(px.shape[:-1] + (4, 4))
    for i in range(4):
        for j in range(i, 4):
            A[..., i, j] = A[..., j, i] = _sum(wc[i], cs[j])
    b = np.stack([_sum(wc[i], beta) for i in range(4)], axis=-1)
    return A, b


def _pl_range_rows(rows: _Rows, scale_d: FloatArray, gamma: float) -> tuple[FloatArray, FloatArray]:
    """Squared-range pseudo-linear equations of every range in ``rows`` (with or without a
    bearing), summed: A (..., 4, 4), b (..., 4); 2pᵀp0 − R = ‖p‖² − d̂² + σ_r²(D),
    ω = a/(4D²σ_r²(D)).
    No trigonometry: cheap enough to accumulate at every call for the global re-check."""
    px, py, pz = rows.px, rows.py, rows.pz
    D2 = scale_d * scale_d
    var_r = rows.s0 * rows.s0 * (D2 if gamma == 2.0 else scale_d**gamma)
    om = rows.ar / (4.0 * D2 * var_r)
    cs = (2.0 * px, 2.0 * py, 2.0 * pz)
    beta = px * px + py * py + pz * pz - rows.zr * rows.zr + var_r  # E[d̂²] = d² + σ_r²
    wc = [om * c for c in cs]
    A = np.empty(px.shape[:-1] + (4, 4))
    for i in range(3):
        for j in range(i, 3):
            A[..., i, j] = A[..., j, i] = _sum(wc[i], cs[j])
        A[..., i, 3] = A[..., 3, i] = -wc[i].sum(axis=-1)
    A[..., 3, 3] = om.sum(axis=-1)
    b = np.stack((_sum(wc[0], beta), _sum(wc[1], beta), _sum(wc[2], beta), -_sum(om, beta)), axis=-1)
    return A, b


def _pl_cost(A: FloatArray, b: FloatArray, x: FloatArray) -> FloatArray:
    """Pseudo-linear cost θᵀAθ − 2bᵀθ at θ = (x, ‖x‖²) (up to a constant), (...,)."""
    theta = np.concatenate((x, np.einsum("...i,...i->...", x, x)[..., None]), axis=-1)
    return np.einsum("...i,...ij,...j->...", theta, A, theta) - 2.0 * np.einsum("...i,...i->...", b, theta)


def _distance_scale(rows: _Rows, config: EstimatorConfig) -> FloatArray:
    """Distance scale D (..., K) of the PL weights: the median measured range of the element's
    rows, or ``config.init_distance_m`` where it has none (m)."""
    z = np.where(rows.ar > 0.0, np.abs(rows.zr), np.nan)
    has = np.any(rows.ar > 0.0, axis=-1)
    med = np.nanmedian(np.where(has[..., None], z, 1.0), axis=-1)
    scale = np.where(has, np.maximum(med, 1.0), config.init_distance_m)
    return np.broadcast_to(scale[..., None], rows.zr.shape)


def _range_scale(x: FloatArray, initialised: BoolArray, rows: _Rows, config: EstimatorConfig) -> FloatArray:
    """Distance scale D (..., K) of the re-check's squared-range weights: |x − p| at the
    estimate x (..., 3) where the element is initialised, else the median measured range of
    the rows (:func:`_distance_scale`)."""
    rx = x[..., 0, None] - rows.px
    ry = x[..., 1, None] - rows.py
    rz = x[..., 2, None] - rows.pz
    scale = np.sqrt(np.maximum(rx * rx + ry * ry + rz * rz, 1.0))
    if not np.all(initialised):
        scale = scale.copy()
        scale[~initialised] = _distance_scale(rows.subset(~initialised), config)
    return scale


def _pl_solve(A: FloatArray, b: FloatArray, config: EstimatorConfig) -> tuple[FloatArray, BoolArray]:
    """Solve the pseudo-linear normal equations (n, 4, 4), (n, 4) -> p0 (n, 3), ok (n,).

    Without range-only equations R is decoupled and the 3x3 block is solved (ok if full rank).
    With them, the candidates are the weighted LS solution θ_LS (if full rank) and the two
    points of the line θ_LS + t v along the weakest direction v that satisfy R = ‖p0‖²
    (Cheung et al. 2004, constrained LS; for ranges from coplanar positions v is the null
    direction and the two points are mirror images). The candidate of lowest constrained PL
    cost θᵀAθ − 2bᵀθ, θ = (p0, ‖p0‖²), is returned; near-ties between the two roots are
    broken by ``config.mirror``.
    """
    n = A.shape[0]
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=bool)
    A0, b0 = A, b
    A = A.copy()
    b = b.copy()
    diag = np.einsum("...ii->...i", A)
    has_R = diag[:, 3] > 1e-300
    no_r = ~has_R
    A[no_r, 3, :] = 0.0
    A[no_r, :, 3] = 0.0
    A[no_r, 3, 3] = 1.0
    b[no_r, 3] = 0.0
    diag = np.einsum("...ii->...i", A)
    s = np.where(diag > 1e-300, 1.0 / np.sqrt(np.maximum(diag, 1e-300)), 1.0)
    As = A * s[:, :, None] * s[:, None, :]
    bs = b * s
    ev, V = np.linalg.eigh(As)
    tol = config.pl_rcond * np.maximum(ev[:, -1], 1e-300)
    good = ev > tol[:, None]
    rank = good.sum(axis=1)
    inv_ev = np.where(good, 1.0 / np.where(good, ev, 1.0), 0.0)
    ys = np.einsum("nij,nj,nkj,nk->ni", V, inv_ev, V, bs)
    theta = ys * s
    x = theta[:, :3].copy()
    full = rank == 4
    cost_ls = np.where(full, _pl_cost(A0, b0, x), np.inf)
    # Constrained roots along the weakest direction (its R component must be significant).
    v = V[:, :, 0] * s
    along = has_R & (rank >= 3) & (np.abs(V[:, 3, 0]) > 1e-6)
    vp, vr = v[:, :3], v[:, 3]
    qa = np.einsum("ni,ni->n", vp, vp)
    qb = 2.0 * np.einsum("ni,ni->n", x, vp) - vr
    qc = np.einsum("ni,ni->n", x, x) - theta[:, 3]
    disc = qb * qb - 4.0 * qa * qc
    # No real root (noise, or the bias correction): use |disc|, two points symmetric about
    # the vertex, rather than the vertex itself (for coplanar drones, a saddle on their plane).
    sq = np.sqrt(np.abs(disc))
    safe_qa = np.where(qa > 1e-300, qa, 1.0)
    along &= qa > 1e-300
    x1 = x + ((-qb - sq) / (2.0 * safe_qa))[:, None] * vp
    x2 = x + ((-qb + sq) / (2.0 * safe_qa))[:, None] * vp
    c1 = np.where(along, _pl_cost(A0, b0, x1), np.inf)
    c2 = np.where(along, _pl_cost(A0, b0, x2), np.inf)
    finite = np.isfinite(c1) & np.isfinite(c2)
    c1f, c2f = np.where(finite, c1, 0.0), np.where(finite, c2, 0.0)
    tie = finite & (np.abs(c1f - c2f) <= 1e-9 * (np.abs(c1f) + 1.0))
    prefer1 = (x1[:, 2] <= x2[:, 2]) if config.mirror == "below" else (x1[:, 2] >= x2[:, 2])
    first = np.where(tie, prefer1, c1 < c2)
    x_root = np.where(first[:, None], x1, x2)
    c_root = np.where(first, c1, c2)
    use_root = along & (c_root < cost_ls)
    x = np.where(use_root[:, None], x_root, x)
    ok = (full & has_R) | use_root | (no_r & (rank == 4))
    ok &= np.all(np.isfinite(x), axis=1)
    return np.where(ok[:, None], x, 0.0), ok


def _schur_prior(A: FloatArray, b: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Marginalise R out of PL normal equations: Λ = A_pp − A_pR A_RR⁻¹ A_Rp, η likewise."""
    arr = A[..., 3, 3]
    safe = np.where(arr > 1e-300, arr, 1.0)
    coupling = np.where((arr > 1e-300)[..., None], A[..., :3, 3] / safe[..., None], 0.0)
    lam = A[..., :3, :3] - coupling[..., :, None] * A[..., None, 3, :3]
    eta = b[..., :3] - coupling * b[..., 3:4]
    lam = 0.5 * (lam + np.swapaxes(lam, -1, -2))
    return lam, eta

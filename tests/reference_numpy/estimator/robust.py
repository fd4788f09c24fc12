"""Robust refinement: the records as rows, their residuals, robust losses and gradients
(:func:`_evaluate`), and the Levenberg-Marquardt iterations on the robust ML cost
(:func:`_lm_iterations`); see the package doc, step 2."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Literal, overload

import numpy as np
from numpy.typing import NDArray

from planner.params import Channel
from planner.sensing import BEARING, COMPONENTS, RANGE, LinkGeometry, SensingComponent
from tests.reference_numpy.estimator.linalg import _inv3_spd
from tests.reference_numpy.estimator.state import BoolArray, EstimatorConfig, FloatArray, Measurements

#: Floors (m) keeping the model finite when a drone sits on the source or right above it.
_RHO2_FLOOR_M2: float = 1e-12


#: The components of the fused range/bearing kernel (``_Rows`` fields zr, za, ze; the
#: pseudo-linear initialisation). Every other component is refined through its
#: :meth:`planner.sensing.SensingComponent.estimator_terms` (:class:`_ExtraRows`).
_KERNEL_COMPONENTS: frozenset[str] = frozenset((RANGE.name, BEARING.name))


@dataclass(frozen=True)
class _ExtraRows:
    """The values of one component outside the fused kernel (internal): ``z`` (..., K, n), NaN
    replaced by 0, and their weights ``a`` (..., K, n) (0 = unused), n = its value count."""

    component: SensingComponent
    z: FloatArray
    a: FloatArray


@dataclass(frozen=True)
class _Rows:
    """Records in component-major layout, NaN replaced by 0 and weight 0 (internal).

    Every array has shape (..., K): drone position (px, py, pz) in m; measured range, azimuth,
    elevation (zr, za, ze); component weights (ar, aa, ae) (0 = unused); σ_r0 of the link (m).
    ``extra``: the rows of the components outside the fused range/bearing kernel.
    """

    px: FloatArray
    py: FloatArray
    pz: FloatArray
    zr: FloatArray
    za: FloatArray
    ze: FloatArray
    ar: FloatArray
    aa: FloatArray
    ae: FloatArray
    s0: FloatArray
    extra: tuple[_ExtraRows, ...] = ()

    def with_weights(self, ar: FloatArray, aa: FloatArray, ae: FloatArray) -> _Rows:
        """The rows with the kernel's component weights replaced (``extra`` kept)."""
        return replace(self, ar=ar, aa=aa, ae=ae)

    def masked(self, keep: BoolArray) -> _Rows:
        """The rows with every weight zeroed where ``keep`` (...,) is False."""
        k = keep[..., None]
        extra = tuple(replace(e, a=np.where(k[..., None], e.a, 0.0)) for e in self.extra)
        return replace(self, ar=np.where(k, self.ar, 0.0), aa=np.where(k, self.aa, 0.0), ae=np.where(k, self.ae, 0.0), extra=extra)

    def sliced(self, sl: slice) -> _Rows:
        """The rows ``sl`` (last axis)."""
        extra = tuple(replace(e, z=e.z[..., sl, :], a=e.a[..., sl, :]) for e in self.extra)
        return replace(self, extra=extra, **{f: getattr(self, f)[..., sl] for f in _KERNEL_FIELDS})

    def subset(self, mask: BoolArray) -> _Rows:
        """The batch elements where ``mask`` (...,)."""
        extra = tuple(replace(e, z=e.z[mask], a=e.a[mask]) for e in self.extra)
        return replace(self, extra=extra, **{f: getattr(self, f)[mask] for f in _KERNEL_FIELDS})

    def used_count(self) -> NDArray[np.int64]:
        """The scalar values with a positive weight, per batch element (...,)."""
        used = (self.ar > 0.0).sum(axis=-1) + (self.aa > 0.0).sum(axis=-1) + (self.ae > 0.0).sum(axis=-1)
        for e in self.extra:
            used = used + (e.a > 0.0).sum(axis=(-2, -1))
        return used


_KERNEL_FIELDS: tuple[str, ...] = ("px", "py", "pz", "zr", "za", "ze", "ar", "aa", "ae", "s0")


def _rows(
    meas: Measurements, row_weight: FloatArray, channel: Channel, config: EstimatorConfig, components: Sequence[SensingComponent] = COMPONENTS
) -> _Rows:
    """Component-major rows with weights: ranges ``row_weight``; bearings ``row_weight`` in LOS
    and ``row_weight·nlos_bearing_weight`` when flagged NLOS; 0 where a value is absent. The
    ``components`` outside the kernel whose values ``meas.extra_values`` carries get
    ``row_weight`` (:class:`_ExtraRows`)."""
    p = meas.positions_m
    px, py, pz = p[..., 0], p[..., 1], p[..., 2]
    row_ok = np.isfinite(px + py + pz)  # NaN/inf in any coordinate
    los = meas.los
    wb = row_weight * np.where(los, 1.0, config.nlos_bearing_weight)

    def present(z: FloatArray, w: FloatArray) -> tuple[FloatArray, FloatArray]:
        ok = row_ok & np.isfinite(z)
        return np.where(ok, z, 0.0), np.where(ok, w, 0.0)

    zr, ar = present(meas.range_m, row_weight)
    za, aa = present(meas.azimuth_rad, wb)
    ze, ae = present(meas.elevation_rad, wb)
    s0 = channel.sigma_r0(los)
    extra = []
    for component in components:
        if component.name in _KERNEL_COMPONENTS or not all(n in meas.extra_values for n in component.value_names):
            continue
        z = np.stack([np.asarray(meas.extra_values[n], dtype=float) for n in component.value_names], axis=-1)
        ok = row_ok[..., None] & np.isfinite(z)
        extra.append(_ExtraRows(component, np.where(ok, z, 0.0), np.where(ok, row_weight[..., None], 0.0)))
    rows = (np.where(row_ok, px, 0.0), np.where(row_ok, py, 0.0), np.where(row_ok, pz, 0.0), zr, za, ze, ar, aa, ae, s0)
    return _Rows(*rows, extra=tuple(extra))


@dataclass(frozen=True)
class _Eval:
    """Robust cost of the rows at one source position and the per-row factors from which its
    gradient and scoring matrix are summed (internal; arrays (..., K))."""

    cost: FloatArray  # (...,) summed over rows
    rx: FloatArray
    ry: FloatArray
    rz: FloatArray
    rho2: FloatArray
    # gradient factors: g = Σ [gA r + gB v + gC w], v = (−r_y, r_x, 0), w = (−r_x r_z, −r_y r_z, ρ²)
    gA: FloatArray
    gB: FloatArray
    gC: FloatArray
    # scoring factors: H = Σ [hA r rᵀ + hB v vᵀ + hC w wᵀ]; Fisher adds hF r rᵀ
    hA: FloatArray
    hB: FloatArray
    hC: FloatArray
    hF: FloatArray
    d: FloatArray
    # component weights actually used (after the innovation gate)
    ar: FloatArray
    aa: FloatArray
    ae: FloatArray
    # per element and component type (range, azimuth, elevation, then every value of the
    # components outside the kernel), (..., 3 + n_extra): weighted count of the components
    # used, and of those with |e| beyond ``suspect_sigma``
    n_used: FloatArray
    n_big: FloatArray
    # the components outside the kernel (None: there are none): per row, their summed
    # gradient Σ a ψ ∂e/∂x (..., K, 3), scoring matrix Σ a w ∂e/∂x ∂e/∂xᵀ (..., K, 3, 3) (also
    # their Fisher information) and weight Σ a (..., K)
    extra_g: FloatArray | None = None
    extra_h: FloatArray | None = None
    extra_a: FloatArray | None = None


@dataclass(frozen=True)
class _Gate:
    """Innovation gate (internal): a bound on the variance of the previous estimate along any
    direction (tr Σ, m², shape (...,)), where to apply it (...,), the threshold in σ, and the
    largest gated fraction allowed per element."""

    var_bound_m2: FloatArray
    use: BoolArray
    sigma: float
    max_fraction: float


# The evaluation (cost_only False) or the cost alone (cost_only True): the return type follows.
@overload
def _evaluate(
    x: FloatArray,
    rows: _Rows,
    channel: Channel,
    k: float,
    ml: bool,
    d_var: FloatArray | None = None,
    gate: _Gate | None = None,
    cost_only: Literal[False] = False,
    redescend: bool | BoolArray = False,
    tukey_c: float = 4.685,
    suspect_sigma: float = 2.5,
) -> _Eval: ...


@overload
def _evaluate(
    x: FloatArray,
    rows: _Rows,
    channel: Channel,
    k: float,
    ml: bool,
    d_var: FloatArray | None = None,
    gate: _Gate | None = None,
    *,
    cost_only: Literal[True],
    redescend: bool | BoolArray = False,
    tukey_c: float = 4.685,
    suspect_sigma: float = 2.5,
) -> FloatArray: ...


def _evaluate(
    x: FloatArray,
    rows: _Rows,
    channel: Channel,
    k: float,
    ml: bool,
    d_var: FloatArray | None = None,
    gate: _Gate | None = None,
    cost_only: bool = False,
    redescend: bool | BoolArray = False,
    tukey_c: float = 4.685,
    suspect_sigma: float = 2.5,
) -> _Eval | FloatArray:
    r"""Robust negative log-likelihood of the rows at source ``x`` (..., 3) and its terms.

    Per component, with e = (z − h)/σ, robust loss ρ, ψ = ρ', w = ψ/e (:func:`_loss`: Huber
    with threshold k, or Tukey's biweight with threshold ``tukey_c`` where ``redescend``):

    .. math::
        C = \sum_i a_i\big[\rho(e_i) + [\text{ML, range}]\tfrac12\ln\sigma_{r,i}^2\big],\qquad
        \nabla C_i = -a\,\psi(e)\,\nabla h/\sigma
            + [\text{ML, range}]\,a\tfrac{\gamma}{2d}(1 - w e^2)\nabla d,

        I_i = a\,\nabla h\nabla h^T\big(w/\sigma^2 + [\text{range}]\,\gamma^2/(2d^2)\big)

    with ∇d = r/d, ∇φ = (−r_y, r_x, 0)/ρ², ∇θ = (−r_x r_z, −r_y r_z, ρ²)/(d²ρ), ρ the
    horizontal distance, σ_r = σ_r0 d^{γ/2} (eq. 5), σ_b constant. The γ²/(2d²) term is
    ∇σ²∇σ²ᵀ/(2σ⁴) (eq. 12's A_d): it enters the scoring matrix in ML mode and the reported
    Fisher information always. In GLS mode σ_r is evaluated at ``d_var`` if given.

    ``gate``: components whose innovation exceeds ``gate.sigma`` standard deviations of
    σ² + tr(Σ)‖∇h‖² (a bound on σ² + ∇hᵀΣ∇h) get weight 0, where ``gate.use`` and at most
    ``gate.max_fraction`` of the element's components are gated. ``cost_only``: return the
    summed cost (...,) only.
    """
    res = _residuals(x, rows, channel, d_var)
    ar, aa, ae = rows.ar, rows.aa, rows.ae
    if gate is not None:
        ar, aa, ae = _gated_weights(res, ar, aa, ae, gate)
    rr_, pr_, wr_ = _loss(res.er, k, tukey_c, redescend)
    ra_, pa_, wa_ = _loss(res.ea, k, tukey_c, redescend)
    re_, pe_, we_ = _loss(res.ee, k, tukey_c, redescend)
    cr = ar * rr_
    if ml:
        cr += ar * np.log(res.sr)
    cost = np.einsum("...k,...k->...", aa, ra_)
    cost += np.einsum("...k,...k->...", ae, re_)
    cost += cr.sum(axis=-1)
    extra = [_extra_terms(x, rows, e, channel, k, tukey_c, redescend) for e in rows.extra]
    for e_cost, *_ in extra:
        cost = cost + e_cost
    if cost_only:
        return cost
    ev = _factors(res, cost, (ar, aa, ae), (pr_, pa_, pe_), (wr_, wa_, we_), channel.gamma, ml, suspect_sigma)
    return _with_extra(ev, extra, suspect_sigma) if extra else ev


def _extra_terms(
    x: FloatArray, rows: _Rows, extra: _ExtraRows, channel: Channel, k: float, tukey_c: float, redescend: bool | BoolArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """One component outside the kernel at source ``x`` (..., 3): its robust cost Σ a ρ(e)
    (...,), per row its gradient Σ a ψ ∂e/∂x (..., K, 3), scoring matrix
    Σ a w ∂e/∂x ∂e/∂xᵀ (..., K, 3, 3) and weight Σ a (..., K), and its residuals e and weights
    a, (..., K, n) (:meth:`planner.sensing.SensingComponent.estimator_terms`)."""
    r = np.stack((x[..., 0, None] - rows.px, x[..., 1, None] - rows.py, x[..., 2, None] - rows.pz), axis=-1)
    rho2 = np.maximum(r[..., 0] * r[..., 0] + r[..., 1] * r[..., 1], _RHO2_FLOOR_M2)
    d2 = rho2 + r[..., 2] * r[..., 2]
    geom = LinkGeometry(r, rho2, d2, np.sqrt(d2))
    n = len(extra.component.value_names)
    e, de = extra.component.estimator_terms(tuple(extra.z[..., i] for i in range(n)), geom, channel)
    shape = e.shape[:-2] + (e.shape[-2] * n,)
    rho_, psi, w = (v.reshape(e.shape) for v in _loss(e.reshape(shape), k, tukey_c, redescend))
    a = extra.a
    cost = (a * rho_).sum(axis=(-2, -1))
    g = np.einsum("...kn,...kni->...ki", a * psi, de)
    h = np.einsum("...kn,...kni,...knj->...kij", a * w, de, de)
    return cost, g, h, a.sum(axis=-1), e, a


def _with_extra(ev: _Eval, extra: list[tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]], suspect_sigma: float) -> _Eval:
    """``ev`` with the terms of the components outside the kernel (:func:`_extra_terms`)."""
    c2 = suspect_sigma * suspect_sigma
    used, big = [ev.n_used], [ev.n_big]
    g, h, a_rows = extra[0][1], extra[0][2], extra[0][3]
    for i, (_, g_c, h_c, a_c, e, a) in enumerate(extra):
        used.append(a.sum(axis=-2))
        big.append((a * (e * e > c2)).sum(axis=-2))
        if i > 0:
            g, h, a_rows = g + g_c, h + h_c, a_rows + a_c
    return replace(ev, n_used=np.concatenate(used, axis=-1), n_big=np.concatenate(big, axis=-1), extra_g=g, extra_h=h, extra_a=a_rows)


@dataclass(frozen=True)
class _Residuals:
    """Geometry and normalised residuals of the rows at one source position (internal; arrays
    (..., K)): r = x − p (rx, ry, rz), m; ρ² (floored) and ρ, d² and d, m², m; ``dv`` the
    distance σ_r is evaluated at, m; σ_r = σ_r0 dv^{γ/2} (eq. 5) and 1/σ_r, m, m⁻¹; 1/σ_b,
    rad⁻¹ (scalar); e = (z − h)/σ for range, azimuth (wrapped) and elevation."""

    rx: FloatArray
    ry: FloatArray
    rz: FloatArray
    rho2: FloatArray
    rho: FloatArray
    d2: FloatArray
    d: FloatArray
    dv: FloatArray
    sr: FloatArray
    inv_sr: FloatArray
    inv_sb: float
    er: FloatArray
    ea: FloatArray
    ee: FloatArray


def _residuals(x: FloatArray, rows: _Rows, channel: Channel, d_var: FloatArray | None) -> _Residuals:
    """Normalised residuals e = (z − h(x))/σ of every row at source ``x`` (..., 3), m, ENU:
    h = d, φ = atan2(r_y, r_x), θ = atan2(r_z, ρ) (eq. 3), σ_r = σ_r0 d^{γ/2} (eq. 5) at
    ``d_var`` if given (GLS), σ_b constant."""
    rx = x[..., 0, None] - rows.px
    ry = x[..., 1, None] - rows.py
    rz = x[..., 2, None] - rows.pz
    rho2 = rx * rx
    rho2 += ry * ry
    np.maximum(rho2, _RHO2_FLOOR_M2, out=rho2)
    rho = np.sqrt(rho2)
    d2 = rz * rz
    d2 += rho2
    d = np.sqrt(d2)
    gamma = channel.gamma
    dv = d if d_var is None else d_var
    sr = rows.s0 * (dv if gamma == 2.0 else dv ** (0.5 * gamma))
    inv_sr = 1.0 / sr
    inv_sb = 1.0 / channel.sigma_bearing_rad
    er = RANGE.normalised_residual(rows.zr, d, inv_sr)
    ea, ee = BEARING.normalised_residuals(rows.za, rows.ze, rx, ry, rz, rho, inv_sb)
    return _Residuals(rx, ry, rz, rho2, rho, d2, d, dv, sr, inv_sr, inv_sb, er, ea, ee)


def _gated_weights(res: _Residuals, ar: FloatArray, aa: FloatArray, ae: FloatArray, gate: _Gate) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Component weights after the innovation gate: 0 for a component whose innovation exceeds
    ``gate.sigma`` standard deviations of σ² + tr(Σ)‖∇h‖² (‖∇φ‖² = 1/ρ², ‖∇θ‖² = 1/d²), where
    ``gate.use`` and at most ``gate.max_fraction`` of the element's components are gated."""
    g2 = gate.sigma * gate.sigma
    tv = gate.var_bound_m2[..., None]
    tb = tv * (res.inv_sb * res.inv_sb)
    out_r = (res.er * res.er > g2 * (1.0 + tv * res.inv_sr * res.inv_sr)) & (ar > 0.0)
    out_a = (res.ea * res.ea > g2 * (1.0 + tb / res.rho2)) & (aa > 0.0)
    out_e = (res.ee * res.ee > g2 * (1.0 + tb / res.d2)) & (ae > 0.0)
    n_out = out_r.sum(axis=-1) + out_a.sum(axis=-1) + out_e.sum(axis=-1)
    n_all = (ar > 0.0).sum(axis=-1) + (aa > 0.0).sum(axis=-1) + (ae > 0.0).sum(axis=-1)
    apply = (gate.use & (n_out <= gate.max_fraction * n_all))[..., None]
    if np.any(apply):
        ar = np.where(out_r & apply, 0.0, ar)
        aa = np.where(out_a & apply, 0.0, aa)
        ae = np.where(out_e & apply, 0.0, ae)
    return ar, aa, ae


def _factors(
    res: _Residuals,
    cost: FloatArray,
    weights: tuple[FloatArray, FloatArray, FloatArray],
    psi: tuple[FloatArray, FloatArray, FloatArray],
    irls: tuple[FloatArray, FloatArray, FloatArray],
    gamma: float,
    ml: bool,
    suspect_sigma: float,
) -> _Eval:
    """The per-row gradient and scoring factors of :class:`_Eval` (see :func:`_evaluate`) from
    the residuals, the component weights a, the influences ψ and IRLS weights w = ψ/e (range,
    azimuth, elevation), and the weighted counts of used and suspect (|e| > ``suspect_sigma``)
    components per type."""
    ar, aa, ae = weights
    pr_, pa_, pe_ = psi
    wr_, wa_, we_ = irls
    inv_sr, inv_sb = res.inv_sr, res.inv_sb
    inv_d = 1.0 / res.d
    inv_rho = 1.0 / res.rho
    inv_d2 = inv_d * inv_d
    inv_rho2 = inv_rho * inv_rho
    sb2inv = inv_sb * inv_sb
    wr = ar * inv_sr
    ir = wr * inv_sr * wr_
    ia = aa * sb2inv * wa_
    ie = ae * sb2inv * we_
    gr = -wr * pr_
    ga = (aa * -inv_sb) * pa_
    ge = (ae * -inv_sb) * pe_
    gd = (0.5 * gamma) / res.dv
    extra = ar * (2.0 * gd * gd)
    if ml:
        gr += ar * gd * (1.0 - pr_ * res.er)
        ir += extra
        extra = np.zeros_like(extra)
    # Weighted counts (weights are 0 or λ^age ≤ 1): used components and those beyond the
    # suspect threshold, per type.
    c2 = suspect_sigma * suspect_sigma
    n_used = np.stack((ar.sum(axis=-1), aa.sum(axis=-1), ae.sum(axis=-1)), axis=-1)
    n_big = np.stack((_sum(ar, res.er * res.er > c2), _sum(aa, res.ea * res.ea > c2), _sum(ae, res.ee * res.ee > c2)), axis=-1)
    return _Eval(
        cost=cost,
        rx=res.rx,
        ry=res.ry,
        rz=res.rz,
        rho2=res.rho2,
        gA=gr * inv_d,
        gB=ga * inv_rho2,
        gC=ge * (inv_d2 * inv_rho),
        hA=ir * inv_d2,
        hB=ia * (inv_rho2 * inv_rho2),
        hC=ie * (inv_d2 * inv_d2 * inv_rho2),
        hF=extra * inv_d2,
        d=res.d,
        ar=ar,
        aa=aa,
        ae=ae,
        n_used=n_used,
        n_big=n_big,
    )


def _loss(e: FloatArray, k: float, c: float, redescend: bool | BoolArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Robust loss ρ(e), influence ψ(e) = ρ'(e) and IRLS weight w = ψ/e of normalised residuals.

    Huber (threshold k): ρ = e²/2 for |e| ≤ k, k|e| − k²/2 beyond; ψ = clip(e, −k, k).
    Tukey's biweight (threshold c), where ``redescend`` ((...,) or scalar): with
    u = min(e²/c², 1), ρ = c²/6 (1 − (1 − u)³), w = (1 − u)², ψ = w e (no influence beyond c).
    """

    def huber() -> tuple[FloatArray, FloatArray, FloatArray]:
        ae = np.abs(e)
        m = np.minimum(ae, k)
        return m * (ae - 0.5 * m), np.maximum(np.minimum(e, k), -k), k / np.maximum(ae, k)

    def tukey() -> tuple[FloatArray, FloatArray, FloatArray]:
        t = 1.0 - np.minimum(e * e * (1.0 / (c * c)), 1.0)
        w = t * t
        return (c * c / 6.0) * (1.0 - w * t), w * e, w

    if isinstance(redescend, bool) or np.ndim(redescend) == 0:
        return tukey() if bool(redescend) else huber()
    if np.all(redescend):
        return tukey()
    if not np.any(redescend):
        return huber()
    sel = np.asarray(redescend)[..., None]
    (t_rho, t_psi, t_w), (h_rho, h_psi, h_w) = tukey(), huber()
    return np.where(sel, t_rho, h_rho), np.where(sel, t_psi, h_psi), np.where(sel, t_w, h_w)


def _sum(a: FloatArray, b: FloatArray | BoolArray) -> FloatArray:
    return np.einsum("...k,...k->...", a, b)


def _accumulate(ev: _Eval, sl: slice | None = None) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Gradient (..., 3), scoring matrix and Fisher information (..., 3, 3), summed over the
    rows (``sl`` of them).

    With v = (−r_y, r_x, 0) and w = (−r_x r_z, −r_y r_z, ρ²): g = Σ gA r + gB v + gC w,
    H = Σ hA r rᵀ + hB v vᵀ + hC w wᵀ, F = H + Σ hF r rᵀ; written entry by entry to avoid
    (..., K, 3, 3) temporaries.
    """
    if sl is None:
        sl = slice(None)
    rx, ry, rz, rho2 = ev.rx[..., sl], ev.ry[..., sl], ev.rz[..., sl], ev.rho2[..., sl]
    gA, gB, gC = ev.gA[..., sl], ev.gB[..., sl], ev.gC[..., sl]
    hA, hB, hC, hF = ev.hA[..., sl], ev.hB[..., sl], ev.hC[..., sl], ev.hF[..., sl]
    t = gA - gC * rz
    g = np.stack((_sum(rx, t) - _sum(gB, ry), _sum(ry, t) + _sum(gB, rx), _sum(gA, rz) + _sum(gC, rho2)), axis=-1)
    rzz = rz * rz
    hCrzz = hC * rzz
    q1 = hA + hCrzz
    q2 = hA - hC * rho2
    rxx, ryy, rxy = rx * rx, ry * ry, rx * ry
    rxz, ryz = rx * rz, ry * rz
    hxx = _sum(rxx, q1) + _sum(ryy, hB)
    hyy = _sum(ryy, q1) + _sum(rxx, hB)
    hxy = _sum(rxy, q1 - hB)
    hzz = _sum(rzz, hA) + _sum(rho2 * rho2, hC)
    hxz = _sum(rxz, q2)
    hyz = _sum(ryz, q2)
    H = np.stack((hxx, hxy, hxz, hxy, hyy, hyz, hxz, hyz, hzz), axis=-1).reshape(hxx.shape + (3, 3))
    fxx, fyy, fzz = _sum(rxx, hF), _sum(ryy, hF), _sum(rzz, hF)
    fxy, fxz, fyz = _sum(rxy, hF), _sum(rxz, hF), _sum(ryz, hF)
    F = H + np.stack((fxx, fxy, fxz, fxy, fyy, fyz, fxz, fyz, fzz), axis=-1).reshape(hxx.shape + (3, 3))
    if ev.extra_g is not None and ev.extra_h is not None:
        # The components outside the kernel: Fisher information = scoring matrix.
        h_extra = ev.extra_h[..., sl, :, :].sum(axis=-3)
        g = g + ev.extra_g[..., sl, :].sum(axis=-2)
        H = H + h_extra
        F = F + h_extra
    return g, H, F


def _prior_cost(x: FloatArray, lam: FloatArray, eta: FloatArray) -> FloatArray:
    """½ xᵀΛx − ηᵀx, (...,)."""
    return 0.5 * np.einsum("...i,...ij,...j->...", x, lam, x) - np.einsum("...i,...i->...", eta, x)


def _lm_iterations(
    x: FloatArray,
    mu: FloatArray,
    rows: _Rows,
    ev: _Eval | None,
    prior_info: FloatArray,
    prior_vec: FloatArray,
    active: BoolArray,
    its: range,
    redescend: Callable[[int], bool | BoolArray],
    channel: Channel,
    config: EstimatorConfig,
) -> tuple[FloatArray, FloatArray, _Eval, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Levenberg-Marquardt (Fisher scoring) iterations ``its`` of the robust cost plus the prior
    ½xᵀΛx − ηᵀx, for a batch of source positions x (..., 3), m, ENU.

    ``ev``: the evaluation at x for the first iteration (None: evaluate here). ``redescend(it)``:
    where Tukey's loss applies at iteration it. Each step is capped at half the mean distance
    to the records and projected into the search box; it is kept only if the cost does not
    increase (then the damping μ shrinks by 3, else it grows by 4).

    Returns:
        x, μ, the evaluation at the last iterate x_lin, the gradient g (m⁻¹), scoring matrix H
        and Fisher information F (m⁻²) there (prior included in g and H, not in F), and x_lin.
    """
    k = config.huber_k
    ml = config.range_cost == "ml"
    c = config.tukey_c
    x_lin = x
    g = H = F = None
    for it in its:
        rd = redescend(it)
        if ev is None:
            ev = _evaluate(x, rows, channel, k, ml, redescend=rd, tukey_c=c, suspect_sigma=config.suspect_sigma)
        x_lin = x
        g, H, F = _accumulate(ev)
        g = g + np.einsum("...ij,...j->...i", prior_info, x) - prior_vec
        H = H + prior_info
        cost = ev.cost + _prior_cost(x, prior_info, prior_vec)
        dH = np.einsum("...ii->...i", H)
        tr = dH.sum(axis=-1)
        Hd = H + (mu[..., None] * dH + 1e-12 * tr[..., None] + 1e-300)[..., None] * np.eye(3)
        Hinv, ok = _inv3_spd(Hd)
        step = -np.einsum("...ij,...j->...i", Hinv, g)
        # Trust region: a step at most half the mean distance to the records (angles are
        # linear only for steps small against the range; far from the data the robust cost
        # is nearly flat and an unbounded step could run away).
        n_w = np.maximum(ev.n_used.sum(axis=-1), 1e-300)
        a_rows = ev.ar + ev.aa + ev.ae if ev.extra_a is None else ev.ar + ev.aa + ev.ae + ev.extra_a
        reach = 0.5 * np.einsum("...k,...k->...", ev.d, a_rows) / n_w
        norm = np.sqrt(np.einsum("...i,...i->...", step, step))
        shrink = np.where(norm > reach, reach / np.maximum(norm, 1e-300), 1.0)
        cand = config.clip(x + np.where((ok & active)[..., None], step * shrink[..., None], 0.0))
        c_new = _evaluate(cand, rows, channel, k, ml, d_var=None if ml else ev.d, cost_only=True, redescend=rd, tukey_c=c)
        c_new = c_new + _prior_cost(cand, prior_info, prior_vec)
        accept = np.isfinite(c_new) & (c_new <= cost) & active
        x = np.where(accept[..., None], cand, x)
        mu = np.where(accept, mu / 3.0, mu * 4.0)
        last, ev = ev, None
    if g is None or H is None or F is None:
        raise ValueError(f"its: expected at least one iteration, found {its!r}")
    return x, mu, last, g, H, F, x_lin

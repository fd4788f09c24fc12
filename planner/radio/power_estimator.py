r"""The source estimate when the source's transmit power is unknown (mission ``source.power:
unknown``): the position p0 and the power offset b estimated jointly, batched, recursive.

Model (eqs. 3, 5 with the power a nuisance parameter, :mod:`planner.radio.unknown_power`): a
ranging record is d̂ = s + n_r, s = e^b d, n_r ~ N(0, σ_r0² s^γ); a bearing record does not
depend on the power (φ̂ = φ + n_b, θ̂ = θ + n_b, n_b ~ N(0, σ_b²); an NLOS bearing gets the
weight ``EstimatorConfig.nlos_bearing_weight``, 0 by default). b = 0 is the power the drones
assume; a source whose reference power is ΔP dB above it has b = −ΔP ln 10/(10γ)
(:func:`offset_of_power_db`; its ranges read short).

Method, per :func:`update` call and per batch element (vectorised over both):

1. The known-power estimator (:func:`planner.estimator.update`) runs on the same records: its
   estimate starts the joint one and stands in for it until the joint one is initialised (and
   for good where no drone ranges: bearing-only swarms are unaffected by the power).
2. The records are kept raw in a window of ``window_rows`` rows; a row leaving it is
   marginalised into a Gaussian prior on x = (p0, b) (information Λ and vector η, linearised at
   the estimate of that call), as the known-power estimator does with its window.
3. Initialisation: once the known-power estimate is observable and the window holds
   ``min_ranges`` ranges, x starts at (p̂0 known, b0), b0 = the median of ln(d̂/d) at p̂0.
4. Fisher scoring with step halving on the negative log-likelihood of the window, the prior and
   a weak prior on b (σ of ``offset_prior_sigma_db`` dB: it only keeps b finite before the
   geometry fixes it), warm-started from the last estimate: ``iterations`` per call
   (``init_iterations`` at initialisation), positions projected into the search box.
5. Every ``recheck_every`` calls a second start, (p̂0 known, b0 there), is polished as well and
   replaces the estimate when it is likelier by more than ``recheck_nll_drop`` (a move of the
   known-power estimate to another basin).

The reported information is the Schur complement J_eq = J₃ − c cᵀ/β of the 4 × 4 Fisher
information at the estimate (the position's information with b unknown, the PEB's), and
``observable`` is the joint estimate's det J_eq/(tr J_eq/3)³ ≥ ``min_rcond``.

Cost per call O(batch × window_rows × scoring evaluations), pure numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from planner import estimator as est
from planner.params import Channel
from planner.radio.power_offset import LN10_OVER_10, offset_of_power_db, offset_ranges, power_db_of_offset
from planner.radio.power_settings import UnknownPowerSettings
from planner.radio.unknown_power import schur_parts
from planner.sensing import COMPONENTS, SensingComponent

if TYPE_CHECKING:
    from collections.abc import Sequence

    from planner.config import PlannerConfig

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class PowerEstimatorState:
    """The joint estimator's state (batch shape ``...``, W = window rows). Treat as immutable.

    Attributes:
        known: the known-power estimator's state on the same records.
        estimate_m: p̂0 (..., 3), m, ENU: the joint estimate where :attr:`ready`, else the
            known-power one.
        offset: b̂ (...), dimensionless; NaN where not estimated.
        offset_db: the estimated source power above the assumed one (...), dB
            (:func:`power_db_of_offset`); NaN where not estimated.
        information: (..., 3, 3), m⁻²: J_eq of the joint estimate where ready, else the known one's.
        observable: (...) bool: the estimate can be trusted (module doc).
        ready: (...) bool: the joint estimate is initialised.
        x: the joint iterate (p0, b) (..., 4).
        rows_position_m (..., W, 3), rows_range_m, rows_azimuth_rad, rows_elevation_rad (..., W),
        rows_los (..., W) bool, rows_weight (..., W) (0: empty slot): the window.
        head: (...) the next slot to write.
        prior_information (..., 4, 4), prior_vector (..., 4): the marginalised bearings.
        cell_position_sum (..., C, 3), cell_weight, cell_range_sum, cell_square_sum (..., C),
        cell_los (..., C): the range cells (Σ w p, Σ w, Σ w d̂, Σ w d̂², the LOS class).
        calls: :func:`update` calls so far.
    """

    known: est.EstimatorState
    estimate_m: FloatArray
    offset: FloatArray
    offset_db: FloatArray
    information: FloatArray
    observable: BoolArray
    ready: BoolArray
    x: FloatArray
    rows_position_m: FloatArray
    rows_range_m: FloatArray
    rows_azimuth_rad: FloatArray
    rows_elevation_rad: FloatArray
    rows_los: BoolArray
    rows_weight: FloatArray
    head: NDArray[np.int64]
    prior_information: FloatArray
    prior_vector: FloatArray
    cell_position_sum: FloatArray
    cell_weight: FloatArray
    cell_range_sum: FloatArray
    cell_square_sum: FloatArray
    cell_los: BoolArray
    calls: int = 0

    @property
    def initialised(self) -> BoolArray:
        """(...) bool: some estimate exists (the known-power estimator's flag)."""
        return self.known.initialised


def initial_state(batch: tuple[int, ...], config: est.EstimatorConfig, settings: UnknownPowerSettings) -> PowerEstimatorState:
    """The state before the first record, batch shape ``batch``."""
    W = settings.window_rows
    known = est.initial_state(batch, config)
    return PowerEstimatorState(
        known=known,
        estimate_m=known.estimate_m,
        offset=np.full(batch, np.nan),
        offset_db=np.full(batch, np.nan),
        information=known.information,
        observable=known.observable,
        ready=np.zeros(batch, dtype=bool),
        x=np.zeros(batch + (4,)),
        rows_position_m=np.zeros(batch + (W, 3)),
        rows_range_m=np.full(batch + (W,), np.nan),
        rows_azimuth_rad=np.full(batch + (W,), np.nan),
        rows_elevation_rad=np.full(batch + (W,), np.nan),
        rows_los=np.zeros(batch + (W,), dtype=bool),
        rows_weight=np.zeros(batch + (W,)),
        head=np.zeros(batch, dtype=np.int64),
        prior_information=np.zeros(batch + (4, 4)),
        prior_vector=np.zeros(batch + (4,)),
        cell_position_sum=np.zeros(batch + (settings.range_cells, 3)),
        cell_weight=np.zeros(batch + (settings.range_cells,)),
        cell_range_sum=np.zeros(batch + (settings.range_cells,)),
        cell_square_sum=np.zeros(batch + (settings.range_cells,)),
        cell_los=np.zeros(batch + (settings.range_cells,), dtype=bool),
    )


@dataclass(frozen=True)
class _Rows:
    """Records of B elements, L rows each (flat batch; empty rows have weight 0)."""

    position: FloatArray  # (B, L, 3)
    range_m: FloatArray  # (B, L)
    azimuth: FloatArray
    elevation: FloatArray
    los: BoolArray
    weight: FloatArray
    #: The weighted mean of the squared ranges Σ w d̂²/Σ w of a range cell (B, L); None: d̂².
    range_sq: FloatArray | None = None

    def take(self, idx: NDArray[np.int64]) -> _Rows:
        sq = None if self.range_sq is None else self.range_sq[idx]
        return _Rows(self.position[idx], self.range_m[idx], self.azimuth[idx], self.elevation[idx], self.los[idx], self.weight[idx], sq)

    def joined(self, other: _Rows) -> _Rows:
        """These rows and ``other``'s, side by side (B, L + L')."""

        def sq(r: _Rows) -> FloatArray:
            return r.range_m * r.range_m if r.range_sq is None else r.range_sq

        def cat(f: str) -> Any:
            return np.concatenate([getattr(self, f), getattr(other, f)], axis=1)

        sqs = np.concatenate([sq(self), sq(other)], axis=1)
        return _Rows(cat("position"), cat("range_m"), cat("azimuth"), cat("elevation"), cat("los"), cat("weight"), sqs)


def _evaluate(
    x: FloatArray, rows: _Rows, channel: Channel, nlos_bearing_weight: float, derivatives: bool
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Negative log-likelihood of ``rows`` at x (B, 4) (constants dropped), its gradient (B, 4)
    and expected Fisher information (B, 4, 4) (zeros unless ``derivatives``)."""
    B = x.shape[0]
    w = rows.weight
    r = x[:, None, :3] - rows.position
    d2 = np.maximum((r * r).sum(-1), 1e-12)
    d = np.sqrt(d2)
    gamma = channel.gamma
    has_r = np.isfinite(rows.range_m) & (w > 0.0)
    wr = np.where(has_r, w, 0.0)
    z = np.where(has_r, rows.range_m, 0.0)
    z2 = z * z if rows.range_sq is None else np.where(has_r, rows.range_sq, 0.0)
    s = np.exp(x[:, None, 3]) * d
    inv = np.where(rows.los, 1.0 / channel.sigma_r0_los**2, 1.0 / channel.sigma_r0_nlos**2)
    v = (s * s if gamma == 2.0 else s**gamma) / inv
    # Σ w (d̂ − s)² = w (mean d̂² − 2 s mean d̂ + s²): a raw range or a cell of ranges (w = Σ w).
    q = z2 - 2.0 * s * z + s * s
    f = 0.5 * (wr * (q / v + np.log(v))).sum(-1)
    g = np.zeros((B, 4))
    F = np.zeros((B, 4, 4))
    if derivatives:
        # Ranges: ∇s = (s r/d², s); ∂(−ℓ)/∂s = −e/v + (γ/2s)(1 − e²/v); A_r(s) = s^−γ/σ² + γ²/(2s²).
        grad_s = np.concatenate([(s / d2)[..., None] * r, s[..., None]], axis=-1)
        ds = (s - z) / v + 0.5 * gamma / s * (1.0 - q / v)
        a = 1.0 / v + 0.5 * gamma * gamma / (s * s)  # s^−γ/σ_r0² = 1/v
        g += ((wr * ds)[:, None, :] @ grad_s)[:, 0]
        F += np.swapaxes(grad_s * (wr * a)[..., None], 1, 2) @ grad_s
    if not (np.isfinite(rows.azimuth) | np.isfinite(rows.elevation)).any():
        return f, g, F
    # Bearings: LOS ones at full weight, NLOS ones at nlos_bearing_weight.
    bw = w * np.where(rows.los, 1.0, nlos_bearing_weight) / channel.sigma_bearing_rad**2
    has_az = np.isfinite(rows.azimuth) & (bw > 0.0)
    has_el = np.isfinite(rows.elevation) & (bw > 0.0)
    rho2 = np.maximum(r[..., 0] ** 2 + r[..., 1] ** 2, 1e-12)
    rho = np.sqrt(rho2)
    e_az = np.where(has_az, (np.where(has_az, rows.azimuth, 0.0) - np.arctan2(r[..., 1], r[..., 0]) + math.pi) % (2.0 * math.pi) - math.pi, 0.0)
    e_el = np.where(has_el, np.where(has_el, rows.elevation, 0.0) - np.arctan2(r[..., 2], rho), 0.0)
    wa, we = np.where(has_az, bw, 0.0), np.where(has_el, bw, 0.0)
    f = f + 0.5 * (wa * e_az * e_az + we * e_el * e_el).sum(-1)
    if not derivatives:
        return f, g, F
    # Bearings: ∇φ = (−r_y, r_x, 0)/ρ², ∇θ = (−r_x r_z, −r_y r_z, ρ²)/(d² ρ).
    zero = np.zeros_like(rho)
    gphi = np.stack([-r[..., 1] / rho2, r[..., 0] / rho2, zero], axis=-1)
    gth = np.stack([-r[..., 0] * r[..., 2], -r[..., 1] * r[..., 2], rho2], axis=-1) / (d2 * rho)[..., None]
    if wa.any() or we.any():
        g[:, :3] -= ((wa * e_az)[:, None, :] @ gphi)[:, 0] + ((we * e_el)[:, None, :] @ gth)[:, 0]
        F[:, :3, :3] += np.swapaxes(gphi * wa[..., None], 1, 2) @ gphi + np.swapaxes(gth * we[..., None], 1, 2) @ gth
    return f, g, F


@dataclass(frozen=True)
class _Problem:
    """What the scoring of B elements takes besides x: their window, prior and settings."""

    rows: _Rows
    prior_information: FloatArray  # (B, 4, 4), including the weak prior on b
    prior_vector: FloatArray  # (B, 4)
    channel: Channel
    config: est.EstimatorConfig
    settings: UnknownPowerSettings

    def take(self, idx: NDArray[np.int64]) -> _Problem:
        return _Problem(self.rows.take(idx), self.prior_information[idx], self.prior_vector[idx], self.channel, self.config, self.settings)

    def evaluate(self, x: FloatArray, derivatives: bool) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The whole cost (window, prior, b's prior) at x (B, 4), its gradient and information."""
        f, g, F = _evaluate(x, self.rows, self.channel, self.config.nlos_bearing_weight, derivatives)
        Lx = (self.prior_information @ x[..., None])[..., 0]
        f = f + 0.5 * (x * Lx).sum(-1) - (self.prior_vector * x).sum(-1)
        if derivatives:
            g = g + Lx - self.prior_vector
            F = F + self.prior_information
        return f, g, F


def _scoring(problem: _Problem, x: FloatArray, iterations: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``iterations`` Fisher-scoring steps with step halving from x (B, 4); the position is
    projected into the search box and a position step capped at half the mean distance to the
    window's records, an offset step at 1. Returns (x, cost at x, the information at the last
    iterate before x: one evaluation less per call, and the next call starts there)."""
    settings, config = problem.settings, problem.config
    f = np.zeros(x.shape[0])
    F = np.zeros(x.shape + (4,))
    for _ in range(iterations):
        f, g, F = problem.evaluate(x, True)
        scale = np.einsum("bii->b", F)[:, None, None]
        H = F + 1e-10 * (scale + 1e-30) * np.eye(4)
        try:
            step = -np.linalg.solve(H, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            step = -(np.linalg.pinv(H) @ g[..., None])[..., 0]
        step = np.where(np.isfinite(step), step, 0.0)
        w = problem.rows.weight
        dist = np.linalg.norm(x[:, None, :3] - problem.rows.position, axis=-1)
        mean_d = (w * dist).sum(-1) / np.maximum(w.sum(-1), 1e-300)
        norm = np.linalg.norm(step[:, :3], axis=-1)
        cap = np.where(w.sum(-1) > 0.0, 0.5 * mean_d, np.inf)
        step[:, :3] *= np.minimum(1.0, cap / np.maximum(norm, 1e-300))[:, None]
        step[:, 3] = np.clip(step[:, 3], -1.0, 1.0)
        t = np.ones(x.shape[0])
        # Negligible predicted decrease: converged, nothing to try.
        accepted = -(g * step).sum(-1) < 1e-9
        new_x, new_f = x.copy(), f.copy()
        for _halving in range(settings.max_halvings):
            todo = ~accepted
            cand = x[todo] + t[todo, None] * step[todo]
            cand[:, :3] = config.clip(cand[:, :3])
            fc, _, _ = problem.take(np.flatnonzero(todo)).evaluate(cand, False)
            ok = np.isfinite(fc) & (fc <= f[todo] + 1e-12 * np.abs(f[todo]))
            idx = np.flatnonzero(todo)[ok]
            new_x[idx], new_f[idx] = cand[ok], fc[ok]
            accepted[idx] = True
            if accepted.all():
                break
            t[todo] *= 0.5
        x, f = new_x, new_f
    return x, f, F


def _start_offset(x_known: FloatArray, rows: _Rows) -> FloatArray:
    """b0 (B,): the median of ln(d̂/d) over the rows' ranges at the position x_known (B, 3); 0
    without a range."""
    d = np.linalg.norm(x_known[:, None, :] - rows.position, axis=-1)
    ok = np.isfinite(rows.range_m) & (rows.range_m > 0.0) & (rows.weight > 0.0) & (d > 0.0)
    ratio = np.where(ok, np.log(np.where(ok, rows.range_m, 1.0) / np.where(ok, d, 1.0)), np.nan)
    with np.errstate(all="ignore"):
        out = np.nanmedian(np.where(ok.any(-1, keepdims=True), ratio, 0.0), axis=-1)
    return np.where(np.isfinite(out), out, 0.0)


@dataclass
class _Cells:
    """The range cells of B elements (flat batch, C cells; mutable while a call builds them)."""

    position_sum: FloatArray  # (B, C, 3)
    weight: FloatArray  # (B, C)
    range_sum: FloatArray
    square_sum: FloatArray
    los: BoolArray

    def rows(self) -> _Rows:
        """The cells as rows: at their mean position, of their mean range and mean squared range."""
        n = np.maximum(self.weight, 1e-300)
        full = self.weight > 0.0
        nan = np.full(self.weight.shape, np.nan)
        return _Rows(
            self.position_sum / n[..., None],
            np.where(full, self.range_sum / n, np.nan),
            nan,
            nan,
            self.los,
            self.weight,
            np.where(full, self.square_sum / n, np.nan),
        )

    def add(self, position: FloatArray, range_m: FloatArray, los: BoolArray, weight: FloatArray, radius: float) -> BoolArray:
        """One range per element (B,) (weight 0 or a NaN range: none) into its cell: the nearest
        cell of its LOS class within ``radius`` × that cell's mean range, else an empty cell.
        Returns (B,) the ranges no cell took (every cell taken and none near: a range merged
        into a distant cell would be read at the wrong place)."""
        have = np.isfinite(range_m) & (weight > 0.0) & np.isfinite(position).all(-1)
        if not have.any():
            return have
        n = np.maximum(self.weight, 1e-300)
        full = self.weight > 0.0
        centre = self.position_sum / n[..., None]
        dist = np.where(full, np.linalg.norm(centre - position[:, None, :], axis=-1), np.inf)
        same = full & (self.los == los[:, None])
        near = np.where(same & (dist <= radius * self.range_sum / n), dist, np.inf)
        empty = ~full
        found = np.isfinite(near.min(-1))
        cell = np.where(found, near.argmin(-1), empty.argmax(-1))
        left = have & ~found & ~empty.any(-1)
        b = np.flatnonzero(have & ~left)
        c = cell[b]
        w = weight[b]
        self.position_sum[b, c] += w[:, None] * position[b]
        self.weight[b, c] += w
        self.range_sum[b, c] += w * range_m[b]
        self.square_sum[b, c] += w * range_m[b] ** 2
        self.los[b, c] = los[b]
        return left


def _insert(
    state: PowerEstimatorState, meas: est.Measurements, channel: Channel, config: est.EstimatorConfig, settings: UnknownPowerSettings
) -> tuple[_Rows, _Cells, FloatArray, FloatArray, NDArray[np.int64]]:
    """The window (flat batch) after forgetting and the new records; the rows they pushed out:
    ranges into the range cells, bearings into the prior (Λ, η) linearised at the current
    estimate (elements not ready drop their bearings); the new heads."""
    B = int(np.prod(state.ready.shape, dtype=np.int64))
    W = settings.window_rows
    lam = config.forgetting
    rows = _Rows(
        state.rows_position_m.reshape(B, W, 3).copy(),
        state.rows_range_m.reshape(B, W).copy(),
        state.rows_azimuth_rad.reshape(B, W).copy(),
        state.rows_elevation_rad.reshape(B, W).copy(),
        state.rows_los.reshape(B, W).copy(),
        state.rows_weight.reshape(B, W) * lam,
    )
    lam_p = state.prior_information.reshape(B, 4, 4) * lam
    eta = state.prior_vector.reshape(B, 4) * lam
    C = settings.range_cells
    cells = _Cells(
        state.cell_position_sum.reshape(B, C, 3) * lam,
        state.cell_weight.reshape(B, C) * lam,
        state.cell_range_sum.reshape(B, C) * lam,
        state.cell_square_sum.reshape(B, C) * lam,
        state.cell_los.reshape(B, C).copy(),
    )
    head = state.head.reshape(B).copy()
    M = meas.count
    if M == 0:
        return rows, cells, lam_p, eta, head
    pos = np.asarray(meas.positions_m, dtype=float).reshape(B, M, 3)
    rng = np.asarray(meas.range_m, dtype=float).reshape(B, M)
    az = np.asarray(meas.azimuth_rad, dtype=float).reshape(B, M)
    el = np.asarray(meas.elevation_rad, dtype=float).reshape(B, M)
    valid = np.isfinite(pos).all(-1) & (np.isfinite(rng) | np.isfinite(az) | np.isfinite(el))
    rank = np.cumsum(valid, axis=-1) - 1
    slot = (head[:, None] + rank) % W
    b_idx, m_idx = np.nonzero(valid)
    s_idx = slot[b_idx, m_idx]
    # Rows pushed out: ranges into the cells (in arrival order), bearings and the ranges no cell
    # took into the prior.
    leaving = rows.weight[b_idx, s_idx] > 0.0
    if leaving.any():
        lb, lm, ls = b_idx[leaving], m_idx[leaving], s_idx[leaving]
        linear = np.isfinite(rows.azimuth[lb, ls]) | np.isfinite(rows.elevation[lb, ls])  # in the prior
        uncelled = np.zeros(lb.shape, dtype=bool)  # ranges no cell took
        for col in np.unique(lm):  # one row per element at a time: a cell may take several
            at = lm == col
            bb, ss = lb[at], ls[at]
            vec = np.zeros((B, 3))
            rng_c = np.full(B, np.nan)
            los_c = np.zeros(B, dtype=bool)
            w_c = np.zeros(B)
            vec[bb], rng_c[bb], los_c[bb], w_c[bb] = rows.position[bb, ss], rows.range_m[bb, ss], rows.los[bb, ss], rows.weight[bb, ss]
            left = cells.add(vec, rng_c, los_c, w_c, settings.cell_radius)
            uncelled[at] = left[bb]
        ready = state.ready.reshape(B)
        prior = ready[lb] & (linear | uncelled)
        if prior.any():
            L = np.zeros((B, W), dtype=bool)
            L[lb[prior], ls[prior]] = True
            R = np.zeros((B, W), dtype=bool)  # the ranges that go into the prior
            R[lb[prior & uncelled], ls[prior & uncelled]] = True
            sub = np.flatnonzero(L.any(-1))
            o = rows.take(sub)
            out_range = np.where(R[sub], o.range_m, np.nan)
            out_rows = _Rows(o.position, out_range, o.azimuth, o.elevation, o.los, np.where(L[sub], o.weight, 0.0))
            x = state.x.reshape(B, 4)[sub]
            _, g, F = _evaluate(x, out_rows, channel, config.nlos_bearing_weight, True)
            lam_p[sub] += F
            eta[sub] += (F @ x[..., None])[..., 0] - g
    rows.position[b_idx, s_idx] = pos[b_idx, m_idx]
    rows.range_m[b_idx, s_idx] = rng[b_idx, m_idx]
    rows.azimuth[b_idx, s_idx] = az[b_idx, m_idx]
    rows.elevation[b_idx, s_idx] = el[b_idx, m_idx]
    rows.los[b_idx, s_idx] = np.asarray(meas.los, dtype=bool).reshape(B, M)[b_idx, m_idx]
    rows.weight[b_idx, s_idx] = 1.0
    head = (head + valid.sum(-1)) % W
    return rows, cells, lam_p, eta, head


def update(
    state: PowerEstimatorState,
    meas: est.Measurements,
    channel: Channel,
    config: est.EstimatorConfig,
    settings: UnknownPowerSettings,
    components: Sequence[SensingComponent] = COMPONENTS,
) -> PowerEstimatorState:
    """One call with a batch of new records (the module doc's steps 1-5); pure.

    Args:
        state: the last state (:func:`initial_state`). meas: the new records (batch shape of
            the state; NaN rows are empty). channel: γ, σ_r0 (LOS/NLOS), σ_b.
        config: the known-power estimator's settings (its forgetting, bounds, NLOS bearing
            weight and observability threshold apply here too). settings: this estimator's.
        components: the measurement components the known-power estimator takes.
    """
    known = est.update(state.known, meas, channel, config, components)
    batch = state.ready.shape
    B = int(np.prod(batch, dtype=np.int64))
    W = settings.window_rows
    rows, cells, lam_p, eta, head = _insert(state, meas, channel, config, settings)
    sigma_b = settings.offset_prior_sigma_db * LN10_OVER_10 / channel.gamma
    b_prior = np.zeros((4, 4))
    b_prior[3, 3] = 1.0 / sigma_b**2
    # Only the slots written so far (the ring fills from slot 0).
    used = np.flatnonzero((rows.weight > 0.0).any(0))
    width = int(used[-1]) + 1 if used.size else 1
    view = _Rows(
        rows.position[:, :width],
        rows.range_m[:, :width],
        rows.azimuth[:, :width],
        rows.elevation[:, :width],
        rows.los[:, :width],
        rows.weight[:, :width],
    )
    taken = np.flatnonzero((cells.weight > 0.0).any(0))
    if taken.size:  # the range cells in use, as rows after the window's
        c = int(taken[-1]) + 1
        kept = _Cells(cells.position_sum[:, :c], cells.weight[:, :c], cells.range_sum[:, :c], cells.square_sum[:, :c], cells.los[:, :c])
        view = view.joined(kept.rows())
    problem = _Problem(view, lam_p + b_prior, eta, channel, config, settings)

    x = state.x.reshape(B, 4).copy()
    ready = state.ready.reshape(B).copy()
    known_x = known.estimate_m.reshape(B, 3)
    n_ranges = (np.isfinite(view.range_m) & (view.weight > 0.0)).sum(-1)
    start = ~ready & known.observable.reshape(B) & (n_ranges >= settings.min_ranges)
    iters = np.where(start, settings.init_iterations, settings.iterations)
    if start.any():
        idx = np.flatnonzero(start)
        x[idx, :3] = known_x[idx]
        x[idx, 3] = _start_offset(known_x[idx], view.take(idx))
        ready[idx] = True
    F_out = np.zeros((B, 4, 4))
    calls = state.calls + 1
    for count in np.unique(iters[ready]):
        idx = np.flatnonzero(ready & (iters == count))
        sub = problem.take(idx)
        xi, fi, Fi = _scoring(sub, x[idx], int(count))
        recheck = settings.recheck_every > 0 and calls % settings.recheck_every == 0
        if recheck:
            alt = np.concatenate([known_x[idx], _start_offset(known_x[idx], sub.rows)[:, None]], axis=-1)
            xa, fa, Fa = _scoring(sub, alt, settings.iterations)
            better = fa < fi - settings.recheck_nll_drop
            xi, Fi = np.where(better[:, None], xa, xi), np.where(better[:, None, None], Fa, Fi)
        x[idx], F_out[idx] = xi, Fi

    parts = schur_parts(F_out)
    jeq = parts.equivalent
    tr = np.einsum("bii->b", jeq) / 3.0
    rcond = np.where(tr > 0.0, np.linalg.det(jeq) / np.where(tr > 0.0, tr, 1.0) ** 3, 0.0)
    observable = np.where(ready, (rcond >= config.min_rcond) & known.initialised.reshape(B), known.observable.reshape(B))
    estimate = np.where(ready[:, None], x[:, :3], known_x)
    information = np.where(ready[:, None, None], jeq, known.information.reshape(B, 3, 3))
    offset = np.where(ready, x[:, 3], np.nan).reshape(batch)
    return PowerEstimatorState(
        known=known,
        estimate_m=estimate.reshape(batch + (3,)),
        offset=offset,
        offset_db=power_db_of_offset(offset, channel.gamma),
        information=information.reshape(batch + (3, 3)),
        observable=observable.reshape(batch),
        ready=ready.reshape(batch),
        x=x.reshape(batch + (4,)),
        rows_position_m=rows.position.reshape(batch + (W, 3)),
        rows_range_m=rows.range_m.reshape(batch + (W,)),
        rows_azimuth_rad=rows.azimuth.reshape(batch + (W,)),
        rows_elevation_rad=rows.elevation.reshape(batch + (W,)),
        rows_los=rows.los.reshape(batch + (W,)),
        rows_weight=rows.weight.reshape(batch + (W,)),
        head=head.reshape(batch),
        prior_information=lam_p.reshape(batch + (4, 4)),
        prior_vector=eta.reshape(batch + (4,)),
        cell_position_sum=cells.position_sum.reshape(batch + (settings.range_cells, 3)),
        cell_weight=cells.weight.reshape(batch + (settings.range_cells,)),
        cell_range_sum=cells.range_sum.reshape(batch + (settings.range_cells,)),
        cell_square_sum=cells.square_sum.reshape(batch + (settings.range_cells,)),
        cell_los=cells.los.reshape(batch + (settings.range_cells,)),
        calls=calls,
    )


#: Either estimator's state (the known-power one, or the joint one of this module).
SourceEstimatorState = est.EstimatorState | PowerEstimatorState


def initial_source_state(batch: tuple[int, ...], planner: PlannerConfig, config: est.EstimatorConfig | None = None) -> SourceEstimatorState:
    """The source estimator's first state for a mission's planner config: the joint one with
    ``planner.unknown_power``, else :func:`planner.estimator.initial_state`. ``config``: the
    estimator settings (default ``planner.estimator``)."""
    cfg = planner.estimator if config is None else config
    if planner.unknown_power is None:
        return est.initial_state(batch, cfg)
    return initial_state(batch, cfg, planner.unknown_power)


def update_source(
    state: SourceEstimatorState, meas: est.Measurements, planner: PlannerConfig, config: est.EstimatorConfig | None = None
) -> SourceEstimatorState:
    """One estimator call for a mission's planner config (:func:`update` with unknown power,
    :func:`planner.estimator.update` otherwise), the components of ``planner.sensing``."""
    cfg = planner.estimator if config is None else config
    components = planner.sensing.components
    if isinstance(state, PowerEstimatorState):
        if planner.unknown_power is None:
            raise ValueError("update_source: a joint power state but the power is known")
        return update(state, meas, planner.channel, cfg, planner.unknown_power, components)
    return est.update(state, meas, planner.channel, cfg, components)


def planning_offset(state: SourceEstimatorState) -> FloatArray | None:
    """The power offset the planning FIM is evaluated at (...): b̂, 0 where not estimated; None
    for the known-power estimator."""
    if not isinstance(state, PowerEstimatorState):
        return None
    return np.where(np.isfinite(state.offset), state.offset, 0.0)


__all__ = [
    "PowerEstimatorState",
    "SourceEstimatorState",
    "UnknownPowerSettings",
    "initial_source_state",
    "initial_state",
    "offset_of_power_db",
    "offset_ranges",
    "planning_offset",
    "power_db_of_offset",
    "update",
    "update_source",
]

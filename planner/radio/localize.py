r"""An emitter's position from a received-power log, with its 95 % confidence region and its PEB.

Model (:mod:`planner.radio.pathloss`): sample i, taken at the receiver position r_i, has power

.. math::
    y_i = P_0 - 10\gamma\log_{10}\lVert r_i - p\rVert + g(\psi_i) + \sigma k_i\varepsilon_i,
    \qquad \varepsilon_i\sim\mathcal N(0,1)

censored below its threshold when the receiver did not detect it (:mod:`planner.radio.tobit`);
k_i = 1 in line of sight, the NLOS/LOS ratio of σ behind a building. The emitter position p
(the horizontal position at a given height, or all three coordinates) is the parameter of
interest; the reference power P_0 (*unknown transmit power*: a receiver's dB are uncalibrated
anyway), the exponent γ (optionally) and σ are nuisance parameters. A bearing column adds
independent azimuth measurements φ̂_i ~ N(φ_i(p), σ_b²).

Method:

1. **Profile likelihood on a grid** over the search area: at every candidate p the nuisance
   parameters are fitted exactly (the censored linear fit of :func:`planner.radio.tobit.fit_linear`,
   concave), giving ℓ_p(p) = max over (P_0, γ, σ) of ℓ.
2. **Maximum likelihood**: a quasi-Newton climb of the full likelihood (analytic gradient) from
   the best grid points; p̂ and ℓ̂.
3. **Confidence region** {p : 2(ℓ̂ − ℓ_p(p)) ≤ χ²_{q, 0.95}} (q = 2 or 3 coordinates): the
   profile-likelihood region (Wilks; asymptotically of coverage 95 %, and not forced to be an
   ellipse: a flight on one side of the emitter gives a banana, a straight pass two mirror
   lobes), drawn on a refined grid.
4. **PEB**: √tr of the position block of the inverse of the expected Fisher information of
   all parameters (the position block of J⁻¹ is the inverse of the Schur complement
   J_pp − J_pν J_νν⁻¹ J_νp: the information left for p once the nuisance parameters ν are
   estimated; the paper's eq. 18 with unknown power).
5. **Verdict**: the log localizes the emitter only if the region is closed inside the search
   area and connected, and the Fisher information of the position is not singular. Otherwise
   it says why (:attr:`Localization.reasons`) and gives no point as the answer.

Frame: a local Cartesian frame in metres (the mission ENU frame). Pure numpy/scipy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage
from scipy.stats import chi2

from planner.geometry import line_of_sight
from planner.radio.pathloss import Estimate, Pattern, censored_values, decorrelation_distance, link_terms, path_length_m, thin_by_distance
from planner.radio.tobit import expected_information, fit_linear, loglik_terms

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Candidate positions evaluated per batch (bounds the memory of one batch: candidates × samples).
_BATCH_ELEMENTS: int = 2_000_000
#: Detected samples needed beyond the number of parameters.
MIN_EXTRA_DETECTED: int = 5
_Z95: float = 1.959963984540054
#: Grid peaks whose profile log-likelihood is this far below the best are not climbed from.
_START_MARGIN: float = 15.0
#: Peaks of the refined grid this far below the first stage's maximum are not climbed from
#: (a climb from a refined cell gains less).
_REFINE_MARGIN: float = 3.0
#: At most this many refined grids, each over the region of the one before.
_REFINE_STAGES: int = 3


@dataclass(frozen=True)
class RadioLog:
    """Samples of received power along a flight, in a local frame.

    Attributes:
        positions_m: receiver positions r_i (n, 3), m (ENU).
        power_db: received power (n,), dB (any reference; ignored where censored); NaN where
            a sample that is not censored carries no power (a bearing alone).
        censored: (n,) bool: not detected (below its threshold, or the receiver unlocked).
        threshold_db: (n,) each sample's detection threshold, dB; NaN where none applies
            (required where censored).
        azimuth_rad: (n,) measured azimuth from the receiver to the emitter (ENU: from east
            towards north), rad; NaN where the sample has none. None: no bearings.
        time_s: (n,) sample times, s (time order).
    """

    positions_m: FloatArray
    power_db: FloatArray
    censored: BoolArray
    threshold_db: FloatArray
    azimuth_rad: FloatArray | None = None
    time_s: FloatArray | None = None

    def __post_init__(self) -> None:
        n = len(self.power_db)
        if self.positions_m.shape != (n, 3):
            raise ValueError(f"RadioLog.positions_m: expected shape ({n}, 3), found {self.positions_m.shape}")
        for name in ("censored", "threshold_db", "azimuth_rad", "time_s"):
            v = getattr(self, name)
            if v is not None and np.shape(v) != (n,):
                raise ValueError(f"RadioLog.{name}: expected shape ({n},), found {np.shape(v)}")
        if not np.isfinite(self.positions_m).all():
            raise ValueError("RadioLog.positions_m: expected finite positions")
        if not np.isfinite(self.threshold_db[self.censored]).all():
            raise ValueError("RadioLog: expected a finite threshold for every censored sample")

    def __len__(self) -> int:
        return len(self.power_db)

    def subset(self, index: ArrayLike) -> RadioLog:
        """The log of the samples at ``index`` (indices or a mask)."""
        i = np.asarray(index)
        return RadioLog(
            positions_m=self.positions_m[i],
            power_db=self.power_db[i],
            censored=self.censored[i],
            threshold_db=self.threshold_db[i],
            azimuth_rad=None if self.azimuth_rad is None else self.azimuth_rad[i],
            time_s=None if self.time_s is None else self.time_s[i],
        )

    @property
    def power_mask(self) -> BoolArray:
        """(n,) samples with a power value or censored: the samples of the power likelihood."""
        return self.censored | np.isfinite(self.power_db)

    @property
    def detected(self) -> int:
        """Samples with a detected power."""
        return int((~self.censored & np.isfinite(self.power_db)).sum())

    @property
    def has_bearings(self) -> bool:
        """Some sample carries a bearing."""
        return self.azimuth_rad is not None and bool(np.isfinite(self.azimuth_rad).any())


@dataclass(frozen=True)
class LocalizeOptions:
    """What is known about the emitter and the channel, and where to search.

    Attributes:
        area_min_m, area_max_m: the horizontal search area (x, y), m.
        emitter_z_m: the emitter's height (m, the log's frame), or None to estimate it in
            ``z_range_m``.
        z_range_m: heights searched when ``emitter_z_m`` is None, (low, high), m.
        reference_power_db: P_0 (dB at 1 m) if known; None: unknown transmit power (estimated).
        gamma: the path-loss exponent if known; None: estimated jointly.
        nlos_sigma_factor: σ_NLOS/σ_LOS (with ``boxes``: links they block get it).
        pattern: the emitter's antenna pattern.
        bearing_sigma_rad: σ_b of the bearings, rad.
        boxes_min, boxes_max: buildings (B, 3), m: the links they block are NLOS.
        level: the confidence level of the region.
        grid: grid points per horizontal axis of the coarse search (the refined grid has as many).
        z_levels: heights of the coarse grid when the height is estimated.
    """

    area_min_m: tuple[float, float]
    area_max_m: tuple[float, float]
    emitter_z_m: float | None = None
    z_range_m: tuple[float, float] = (0.0, 30.0)
    reference_power_db: float | None = None
    gamma: float | None = None
    nlos_sigma_factor: float = 1.0
    pattern: Pattern = field(default_factory=lambda: Pattern("isotropic"))
    bearing_sigma_rad: float = math.radians(10.0)
    boxes_min: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    boxes_max: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    level: float = 0.95
    grid: int = 48
    z_levels: int = 9

    def __post_init__(self) -> None:
        lo, hi = np.asarray(self.area_min_m, float), np.asarray(self.area_max_m, float)
        if lo.shape != (2,) or hi.shape != (2,) or not (np.isfinite(lo).all() and np.isfinite(hi).all() and (hi > lo).all()):
            raise ValueError(f"LocalizeOptions: expected a search area with max > min on x and y, found {self.area_min_m}, {self.area_max_m}")
        if not 0.0 < self.level < 1.0:
            raise ValueError(f"LocalizeOptions.level: expected a probability in (0, 1), found {self.level}")
        if self.gamma is not None and not self.gamma > 0.0:
            raise ValueError(f"LocalizeOptions.gamma: expected a positive exponent, found {self.gamma}")
        if self.grid < 8 or self.z_levels < 2:
            raise ValueError(f"LocalizeOptions: expected grid >= 8 and z_levels >= 2, found {self.grid}, {self.z_levels}")
        if self.emitter_z_m is None and not self.z_range_m[1] > self.z_range_m[0]:
            raise ValueError(f"LocalizeOptions.z_range_m: expected high > low, found {self.z_range_m}")

    @property
    def dims(self) -> int:
        """Position coordinates estimated: 2 (height given) or 3."""
        return 2 if self.emitter_z_m is not None else 3

    @property
    def nuisance_names(self) -> tuple[str, ...]:
        """The nuisance parameters fitted besides σ, in order: ``P0`` (unknown power), ``gamma``."""
        return tuple(n for n, free in (("P0", self.reference_power_db is None), ("gamma", self.gamma is None)) if free)


@dataclass(frozen=True)
class RegionGrid:
    """The confidence region on a grid: {p : deviance ≤ threshold}.

    Attributes:
        x_m, y_m: grid coordinates (nx,), (ny,), m.
        deviance: 2(ℓ̂ − ℓ_p) at the grid points (ny, nx), minimised over the height when the
            height is estimated.
        threshold: χ²_{q, level}.
    """

    x_m: FloatArray
    y_m: FloatArray
    deviance: FloatArray
    threshold: float

    @property
    def mask(self) -> BoolArray:
        """(ny, nx) True inside the region."""
        return self.deviance <= self.threshold

    @property
    def cell_area_m2(self) -> float:
        """Area of one grid cell, m²."""
        return float((self.x_m[1] - self.x_m[0]) * (self.y_m[1] - self.y_m[0]))


@dataclass(frozen=True)
class Localization:
    """The answer of :func:`localize`.

    Attributes:
        localized: the log localizes the emitter (see :attr:`reasons` otherwise).
        reasons: why not, one sentence each (empty when localized).
        estimate_m: the maximum-likelihood position p̂ (3,), m (the best fit; not an answer
            when ``localized`` is False).
        peb_m: √tr of the position block of the inverse Fisher information at p̂, m (+inf if
            singular).
        covariance_m2: that block (q, q), m² (the Wald covariance of p̂).
        region: the refined grid of the confidence region; coarse: the grid over the whole
            search area.
        region_area_m2: the horizontal area of the region, m².
        region_radius_m: the largest horizontal distance from p̂ to a point of the region, m.
        components: connected parts of the region on the coarse grid.
        reference_power: P_0 (dB at 1 m) with its 95 % interval if estimated, else None.
        gamma: γ with its 95 % interval if estimated, else None.
        sigma_db: σ (dB, LOS links).
        loglik: ℓ̂.
        detected, censored: samples by kind.
    """

    localized: bool
    reasons: tuple[str, ...]
    estimate_m: FloatArray
    peb_m: float
    covariance_m2: FloatArray
    region: RegionGrid
    coarse: RegionGrid
    region_area_m2: float
    region_radius_m: float
    components: int
    reference_power: Estimate | None
    gamma: Estimate | None
    sigma_db: float
    loglik: float
    detected: int
    censored: int


# ------------------------------------------------------------------------------------ profile
def _nlos_scale(log: RadioLog, points: FloatArray, options: LocalizeOptions) -> FloatArray | float:
    """k_i of every sample for every candidate (G, n): 1 in LOS, the NLOS factor behind a box."""
    if len(options.boxes_min) == 0 or options.nlos_sigma_factor == 1.0:
        return 1.0
    los = line_of_sight(np.broadcast_to(log.positions_m, points.shape[:-1] + log.positions_m.shape), points, options.boxes_min, options.boxes_max)
    return np.where(los, 1.0, options.nlos_sigma_factor)


def _design(log: RadioLog, points: FloatArray, options: LocalizeOptions) -> tuple[FloatArray, FloatArray, FloatArray | float]:
    """Offsets o (G, n), regressors X (G, n, k) and scales k_i of candidates ``points`` (G, 3)."""
    terms = link_terms(points, log.positions_m, options.pattern, derivatives=False)
    offset = terms.gain.copy()
    cols = []
    if options.reference_power_db is None:
        cols.append(np.ones_like(terms.log_d))
    else:
        offset += options.reference_power_db
    if options.gamma is None:
        cols.append(-terms.log_d)
    else:
        offset -= options.gamma * terms.log_d
    X = np.stack(cols, axis=-1) if cols else np.zeros(terms.log_d.shape + (0,))
    return offset, X, _nlos_scale(log, points, options)


def _bearing_loglik(log: RadioLog, points: FloatArray, sigma_b: float) -> FloatArray | float:
    """Σ ln N(wrap(φ̂_i − φ_i(p)); 0, σ_b²) over the samples with a bearing, per candidate (G,)."""
    if not log.has_bearings or log.azimuth_rad is None:
        return 0.0
    has = np.isfinite(log.azimuth_rad)
    r = log.positions_m[has]
    v = points[..., None, :2] - r[:, :2]
    phi = np.arctan2(v[..., 1], v[..., 0])
    e = log.azimuth_rad[has] - phi
    e = e - 2.0 * np.pi * np.rint(e / (2.0 * np.pi))
    return -0.5 * ((e / sigma_b) ** 2).sum(-1) - has.sum() * (math.log(sigma_b) + 0.5 * math.log(2.0 * math.pi))


def profile_loglik(log: RadioLog, options: LocalizeOptions, points: ArrayLike) -> FloatArray:
    """ℓ_p(p): the log-likelihood maximised over the nuisance parameters, at candidates (..., 3), m.

    Batched over the candidates (in chunks that bound the memory). The coverage of the region
    is judged with it: the truth p0 is inside iff 2(ℓ̂ − ℓ_p(p0)) ≤ χ²_{q, level}.
    """
    pts = np.asarray(points, dtype=float)
    flat = pts.reshape(-1, 3)
    plog = log.subset(log.power_mask)
    y = censored_values(plog.power_db, plog.censored, plog.threshold_db)
    out = np.empty(len(flat))
    chunk = max(1, _BATCH_ELEMENTS // max(len(log), 1))
    for s in range(0, len(flat), chunk):
        p = flat[s : s + chunk]
        offset, X, scale = _design(plog, p, options)
        fit = fit_linear(y, plog.censored, X, offset=offset, scale=scale)
        out[s : s + chunk] = fit.loglik + _bearing_loglik(log, p, options.bearing_sigma_rad)
    return out.reshape(pts.shape[:-1])


# ------------------------------------------------------------------------- full likelihood
@dataclass(frozen=True)
class _Full:
    """The full parameter vector x = (p free coords, nuisance β, ln σ) and its likelihood:
    the power samples ``plog`` (with ``y`` of :func:`censored_values`), the bearings of ``log``."""

    log: RadioLog
    options: LocalizeOptions
    plog: RadioLog
    y: FloatArray

    @classmethod
    def of(cls, log: RadioLog, options: LocalizeOptions) -> _Full:
        plog = log.subset(log.power_mask)
        return cls(log, options, plog, censored_values(plog.power_db, plog.censored, plog.threshold_db))

    @property
    def q(self) -> int:
        return self.options.dims

    @property
    def k(self) -> int:
        return len(self.options.nuisance_names)

    def point(self, x: FloatArray) -> FloatArray:
        if self.q == 3:
            return x[:3]
        assert self.options.emitter_z_m is not None  # noqa: S101 - dims == 2 says so
        return np.array([x[0], x[1], self.options.emitter_z_m])

    def mean(self, x: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """μ (n,), ∂μ/∂(p, β) (n, q + k), σ_i (n,), k_i (n,)."""
        p = self.point(x)
        o = self.options
        terms = link_terms(p, self.plog.positions_m, o.pattern)
        beta = dict(zip(o.nuisance_names, x[self.q : self.q + self.k]))
        p0 = beta.get("P0", o.reference_power_db)
        gamma = beta.get("gamma", o.gamma)
        assert p0 is not None and gamma is not None  # noqa: S101 - fitted or given
        mu = p0 - gamma * terms.log_d + terms.gain
        cols = [(-gamma * terms.dlogd_dp + terms.dgain_dp)[:, : self.q]]  # ∂μ/∂p (n, q)
        if "P0" in beta:
            cols.append(np.ones((len(mu), 1)))
        if "gamma" in beta:
            cols.append(-terms.log_d[:, None])
        jac = np.concatenate(cols, axis=1)
        kk = np.broadcast_to(np.asarray(_nlos_scale(self.plog, p[None], o), float), (1, len(mu)))[0]
        return mu, jac, math.exp(x[-1]) * kk, kk

    def nll(self, x: FloatArray) -> tuple[float, FloatArray]:
        mu, jac, sig, _kk = self.mean(x)
        ll, dmu, dsig = loglik_terms(self.y, self.plog.censored, mu, sig)
        grad = np.empty_like(x)
        grad[:-1] = dmu @ jac
        grad[-1] = float((dsig * sig).sum())
        total = float(ll.sum())
        if self.log.has_bearings:
            p = self.point(x)
            total += float(np.sum(_bearing_loglik(self.log, p[None], self.options.bearing_sigma_rad)))
            grad[:2] += _bearing_gradient(self.log, p, self.options.bearing_sigma_rad)
        return -total, -grad

    def fisher(self, x: FloatArray) -> FloatArray:
        """Expected Fisher information of (p, β, σ) at x, (q + k + 1) square."""
        mu, jac, sig, kk = self.mean(x)
        i_mm, i_ms, i_ss = expected_information(mu, sig, self.plog.threshold_db)
        m = jac.shape[1]
        J = np.zeros((m + 1, m + 1))
        J[:m, :m] = (jac * i_mm[:, None]).T @ jac
        J[:m, m] = (jac * (i_ms * kk)[:, None]).sum(0)
        J[m, :m] = J[:m, m]
        J[m, m] = float((i_ss * kk * kk).sum())
        if self.log.has_bearings and self.log.azimuth_rad is not None:
            has = np.isfinite(self.log.azimuth_rad)
            v = self.point(x)[None, :2] - self.log.positions_m[has, :2]
            rho2 = np.maximum((v * v).sum(-1), 1e-12)
            g = np.column_stack([-v[:, 1], v[:, 0]]) / rho2[:, None]
            J[:2, :2] += g.T @ g / self.options.bearing_sigma_rad**2
        return J


def _bearing_gradient(log: RadioLog, p: FloatArray, sigma_b: float) -> FloatArray:
    """∂/∂(p_x, p_y) of the bearings' log-likelihood (2,)."""
    assert log.azimuth_rad is not None  # noqa: S101 - has_bearings says so
    has = np.isfinite(log.azimuth_rad)
    v = p[None, :2] - log.positions_m[has, :2]
    rho2 = np.maximum((v * v).sum(-1), 1e-12)
    e = log.azimuth_rad[has] - np.arctan2(v[:, 1], v[:, 0])
    e = e - 2.0 * np.pi * np.rint(e / (2.0 * np.pi))
    dphi = np.column_stack([-v[:, 1], v[:, 0]]) / rho2[:, None]
    return (e / sigma_b**2) @ dphi


def _start_vector(full: _Full, point: FloatArray) -> FloatArray:
    """x at a candidate: its nuisance parameters from the exact profile fit."""
    offset, X, scale = _design(full.plog, point[None], full.options)
    fit = fit_linear(full.y, full.plog.censored, X, offset=offset, scale=scale)
    return np.concatenate([point[: full.q], fit.beta[0], [math.log(float(fit.sigma[0]))]])


def _scoring(full: _Full, x: FloatArray, lo: FloatArray, hi: FloatArray, iterations: int = 60) -> tuple[FloatArray, float]:
    """Fisher scoring with step halving on the full likelihood from x (ln σ as its last
    coordinate), the position kept in [lo, hi]: the expected information makes each step a
    Newton step of the right scale (a few iterations), where a quasi-Newton method wanders.
    Stops when the Newton decrement gᵀJ⁻¹g (twice the log-likelihood still to gain, to second
    order) is below 1e-9: far below the deviance threshold (≈ 6) the region is drawn at."""
    f, g = full.nll(x)
    for _ in range(iterations):
        J = full.fisher(x)
        s = math.exp(x[-1])
        J[-1, :] *= s  # σ → ln σ
        J[:, -1] *= s
        try:
            step = np.linalg.solve(J + 1e-12 * np.trace(J) * np.eye(len(x)), -g)
        except np.linalg.LinAlgError:
            break
        decrement = float(-g @ step)
        if decrement < 1e-9:
            break
        t = 1.0
        for _halving in range(30):
            cand = x + t * step
            cand[: full.q] = np.clip(cand[: full.q], lo, hi)
            fc, gc = full.nll(cand)
            if fc <= f:
                break
            t *= 0.5
        else:
            break
        x, f, g = cand, fc, gc
    return x, -f


def _climb(full: _Full, starts: Sequence[FloatArray], options: LocalizeOptions) -> tuple[FloatArray, float]:
    """The best local maximum of the full likelihood from the candidate points ``starts``."""
    lo = np.array([options.area_min_m[0], options.area_min_m[1]] + ([options.z_range_m[0]] if full.q == 3 else []))
    hi = np.array([options.area_max_m[0], options.area_max_m[1]] + ([options.z_range_m[1]] if full.q == 3 else []))
    best_x, best = None, -np.inf
    for point in starts:
        x, value = _scoring(full, _start_vector(full, point), lo, hi)
        if value > best:
            best, best_x = value, x
    assert best_x is not None  # noqa: S101 - at least one start
    return best_x, best


def _grid_points(options: LocalizeOptions, lo: FloatArray, hi: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Grid axes x (nx,), y (ny,) over [lo, hi] and its points (nz, ny, nx, 3)."""
    x = np.linspace(lo[0], hi[0], options.grid)
    y = np.linspace(lo[1], hi[1], options.grid)
    z = np.array([options.emitter_z_m]) if options.emitter_z_m is not None else np.linspace(*options.z_range_m, options.z_levels)
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    return x, y, np.stack([X, Y, Z], axis=-1)


@dataclass(frozen=True)
class MaximumLikelihood:
    """The maximum-likelihood fit of :func:`maximum_likelihood`.

    Attributes:
        x: x̂ = (p's free coordinates, the nuisance parameters of
            :attr:`LocalizeOptions.nuisance_names`, ln σ).
        loglik: ℓ̂. estimate_m: p̂ (3,), m.
        coarse: the deviance 2(ℓ̂ − ℓ_p) on the grid over the search area.
        fine: the deviance on the refined grid about the region.
    """

    x: FloatArray
    loglik: float
    estimate_m: FloatArray
    coarse: RegionGrid
    fine: RegionGrid


def _peaks(ll2: FloatArray, size: int) -> NDArray[np.intp]:
    """Flat indices of the separated local maxima of a grid (size × size neighbourhoods), best
    first."""
    peaks = (ll2 == ndimage.maximum_filter(ll2, size=size, mode="nearest")) & np.isfinite(ll2)
    order = np.argsort(-np.where(peaks, ll2, -np.inf), axis=None)
    return order[: int(peaks.sum())]


def _grid_starts(ll: FloatArray, pts: FloatArray, starts: int, margin: float, size: int = 5) -> list[FloatArray]:
    """Candidate points to climb from: the best ``starts`` peaks of the profile grid ``ll``
    (nz, ny, nx) (maxima of their size × size neighbourhood), those more than ``margin`` below
    the best left out (the best always in)."""
    ll2 = ll.max(axis=0)
    which_z = ll.argmax(axis=0)
    best = float(ll2.max())
    out: list[FloatArray] = []
    for flat in _peaks(ll2, size)[: max(1, starts)]:
        iy, ix = np.unravel_index(flat, ll2.shape)
        if not out or ll2[iy, ix] > best - margin:
            out.append(pts[which_z[iy, ix], iy, ix])
    if not out:  # no finite peak: the grid's best point
        iy, ix = np.unravel_index(int(np.nanargmax(ll2)), ll2.shape)
        out.append(pts[which_z[iy, ix], iy, ix])
    return out


def _fine_box(coarse: RegionGrid, p_hat: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The refined grid's horizontal box: the coarse region's bounding box with one coarse cell
    of margin, or two coarse cells about p̂ when the coarse grid holds no more than its cell."""
    dx = coarse.x_m[1] - coarse.x_m[0]
    dy = coarse.y_m[1] - coarse.y_m[0]
    iy, ix = np.nonzero(coarse.mask)
    if len(ix) > 1:
        return (np.array([coarse.x_m[ix.min()] - dx, coarse.y_m[iy.min()] - dy]), np.array([coarse.x_m[ix.max()] + dx, coarse.y_m[iy.max()] + dy]))
    return p_hat[:2] - 2.0 * np.array([dx, dy]), p_hat[:2] + 2.0 * np.array([dx, dy])


def maximum_likelihood(log: RadioLog, options: LocalizeOptions, starts: int = 3) -> MaximumLikelihood:
    """The maximum-likelihood estimate, found in stages, and the deviance on the first and the
    last grid.

    1. A grid over the search area; a climb (Fisher scoring) from its best ``starts``
       separated peaks.
    2. Up to :data:`_REFINE_STAGES` refined grids, each over the region of the one before
       (:func:`_fine_box`), until the region spans a third of the grid on both axes; a climb
       from each one's peaks that are not the maximum seen again. A likelihood with a null in
       the pattern has maxima closer together than a coarse cell (a ring about the null): the
       refined grids find the one the first climb missed, and the last one draws the region.
    """
    full = _Full.of(log, options)
    threshold = float(chi2.ppf(options.level, options.dims))
    x_ax, y_ax, pts = _grid_points(options, np.asarray(options.area_min_m, float), np.asarray(options.area_max_m, float))
    ll = profile_loglik(log, options, pts)  # (nz, ny, nx)
    x_hat, ll_hat = _climb(full, _grid_starts(ll, pts, starts, _START_MARGIN), options)
    coarse = RegionGrid(x_ax, y_ax, 2.0 * (ll_hat - ll.max(axis=0)), threshold)
    lo, hi = _fine_box(coarse, full.point(x_hat))
    fine = coarse
    grids = [(ll, pts)]
    for _stage in range(_REFINE_STAGES):
        fx, fy, fpts = _grid_points(options, lo, hi)
        fll = profile_loglik(log, options, fpts)
        grids.append((fll, fpts))
        p_hat = full.point(x_hat)
        cell = math.hypot(fx[1] - fx[0], fy[1] - fy[0])
        # Peaks of the refined grid close enough to the maximum to be it: climb from them too,
        # unless one is the maximum seen again (nearby and not above it).
        others = []
        for p in _grid_starts(fll, fpts, starts, _REFINE_MARGIN, size=3):
            value = float(profile_loglik(log, options, p))
            if value > ll_hat or (value > ll_hat - _REFINE_MARGIN and math.hypot(*(p[:2] - p_hat[:2])) > 1.5 * cell):
                others.append(p)
        if others:
            x2, ll2 = _climb(full, others, options)
            if ll2 > ll_hat:
                x_hat, ll_hat = x2, ll2
        fine = RegionGrid(fx, fy, 2.0 * (ll_hat - fll.max(axis=0)), threshold)
        # Zoom in while the region spans fewer than a third of the grid's cells on an axis: a
        # pattern's null makes maxima closer together than such a cell.
        iy, ix = np.nonzero(fine.mask)
        if len(ix) and min(np.ptp(ix), np.ptp(iy)) + 1 >= options.grid // 3:
            break
        lo, hi = _fine_box(fine, full.point(x_hat))
    # A grid point above every climb (a climb stopped short) is the estimate then.
    for grid_ll, grid_pts in grids:
        if float(grid_ll.max()) > ll_hat:
            x_hat = _start_vector(full, grid_pts.reshape(-1, 3)[int(np.argmax(grid_ll))])
            ll_hat = -full.nll(x_hat)[0]
    coarse = RegionGrid(x_ax, y_ax, 2.0 * (ll_hat - ll.max(axis=0)), threshold)
    fine = RegionGrid(fine.x_m, fine.y_m, 2.0 * (ll_hat - grids[-1][0].max(axis=0)), threshold)
    return MaximumLikelihood(x_hat, ll_hat, full.point(x_hat), coarse, fine)


def localize(log: RadioLog, options: LocalizeOptions) -> Localization:
    """Estimate the emitter's position from ``log``, with its region, its PEB and a verdict.

    Raises:
        ValueError: fewer detected samples than the parameters plus
            :data:`MIN_EXTRA_DETECTED`.
    """
    q, k = options.dims, len(options.nuisance_names)
    detected = log.detected
    if detected < q + k + 1 + MIN_EXTRA_DETECTED:
        raise ValueError(f"expected at least {q + k + 1 + MIN_EXTRA_DETECTED} detected samples to localize, found {detected}")
    ml = maximum_likelihood(log, options)
    x_hat, ll_hat, p_hat, coarse, region = ml.x, ml.loglik, ml.estimate_m, ml.coarse, ml.fine
    full = _Full.of(log, options)
    J = full.fisher(x_hat)
    reasons: list[str] = []
    cov_all: FloatArray | None
    try:
        eig = np.linalg.eigvalsh(J)
        cov_all = np.asarray(np.linalg.inv(J), dtype=float) if eig[0] > 1e-12 * eig[-1] and eig[-1] > 0 else None
    except np.linalg.LinAlgError:
        cov_all = None
    if cov_all is None:
        cov = np.full((q, q), np.inf)
        peb = math.inf
        reasons.append("the Fisher information of the position is singular: the samples do not constrain it")
    else:
        cov = cov_all[:q, :q]
        peb = float(math.sqrt(max(np.trace(cov), 0.0)))
    mask = coarse.mask
    edge = np.concatenate([mask[0], mask[-1], mask[:, 0], mask[:, -1]])
    if edge.any():
        reasons.append("the 95 % region reaches the edge of the search area: the log does not bound the emitter (did the flight come near it?)")
    _, components = ndimage.label(region.mask, structure=np.ones((3, 3)))
    _, coarse_components = ndimage.label(mask, structure=np.ones((3, 3)))
    components = max(int(components), int(coarse_components))
    if components > 1:
        reasons.append(f"the 95 % region has {components} separate parts: the log leaves the emitter ambiguous")
    xs, ys = np.meshgrid(region.x_m, region.y_m)
    inside = region.mask
    radius = float(np.hypot(xs[inside] - p_hat[0], ys[inside] - p_hat[1]).max()) if inside.any() else 0.0
    area = float(inside.sum() * region.cell_area_m2)
    if edge.any():
        area = max(area, float(mask.sum() * coarse.cell_area_m2))
        radius = max(radius, float(np.hypot(*np.meshgrid(coarse.x_m - p_hat[0], coarse.y_m - p_hat[1]))[mask].max()))
    names = options.nuisance_names
    se = np.sqrt(np.diag(cov_all)) if cov_all is not None else np.full(len(x_hat), np.inf)

    def interval(name: str) -> Estimate | None:
        if name not in names:
            return None
        i = q + names.index(name)
        v = float(x_hat[i])
        return Estimate(v, v - _Z95 * float(se[i]), v + _Z95 * float(se[i]))

    return Localization(
        localized=not reasons,
        reasons=tuple(reasons),
        estimate_m=p_hat,
        peb_m=peb,
        covariance_m2=cov,
        region=region,
        coarse=coarse,
        region_area_m2=area,
        region_radius_m=radius,
        components=components,
        reference_power=interval("P0"),
        gamma=interval("gamma"),
        sigma_db=math.exp(float(x_hat[-1])),
        loglik=ll_hat,
        detected=detected,
        censored=int(log.censored.sum()),
    )


@dataclass(frozen=True)
class Thinning:
    """Which samples a localization uses, spaced along the flight.

    Attributes:
        kept: indices of the samples kept (time order).
        spacing_m: the least distance flown between two kept samples, m (0: all kept).
        correlation_m: the residual's correlation distance measured on a pilot fit (m), None
            when the spacing was given.
    """

    kept: NDArray[np.intp]
    spacing_m: float
    correlation_m: float | None


def residual_correlation_m(log: RadioLog, mean_db: ArrayLike) -> float:
    """The distance flown over which the detected samples' residuals y − μ decorrelate (1/e),
    m (:func:`planner.radio.pathloss.decorrelation_distance`); ``mean_db`` (n,) the model's
    mean power of every sample."""
    det = ~log.censored & np.isfinite(log.power_db)
    path = path_length_m(log.positions_m)
    return decorrelation_distance(path[det], (log.power_db - np.asarray(mean_db, dtype=float))[det])


def model_mean_db(log: RadioLog, options: LocalizeOptions, x: ArrayLike) -> FloatArray:
    """μ_i (n,) dB of every sample at the full parameter vector x of :func:`maximum_likelihood`
    (NaN for a sample without power)."""
    full = _Full.of(log, options)
    out = np.full(len(log), np.nan)
    out[log.power_mask] = full.mean(np.asarray(x, dtype=float))[0]
    return out


def thinning(log: RadioLog, options: LocalizeOptions, spacing_m: float | None, pilot_samples: int = 3000) -> Thinning:
    """The samples to use: one per ``spacing_m`` of flight, or (None) per the residual's
    correlation distance, measured on a pilot fit of at most ``pilot_samples`` evenly chosen
    samples (real shadowing is correlated along the flight: consecutive samples of a 30 Hz log
    are not independent, and treating them so would shrink the region by √(samples per
    correlation distance))."""
    path = path_length_m(log.positions_m)
    if spacing_m is not None:
        return Thinning(thin_by_distance(path, spacing_m), float(spacing_m), None)
    pilot = log.subset(np.unique(np.linspace(0, len(log) - 1, min(len(log), pilot_samples)).astype(np.intp)))
    x_hat = maximum_likelihood(pilot, options).x
    corr = residual_correlation_m(log, model_mean_db(log, options, x_hat))
    return Thinning(thin_by_distance(path, corr), corr, corr)


__all__ = [
    "MIN_EXTRA_DETECTED",
    "Localization",
    "LocalizeOptions",
    "RadioLog",
    "RegionGrid",
    "Thinning",
    "localize",
    "maximum_likelihood",
    "model_mean_db",
    "profile_loglik",
    "residual_correlation_m",
    "thinning",
]

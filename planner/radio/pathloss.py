r"""The log-distance model of received power, antenna patterns, and a channel fitted to a log.

The paper's ranging model (eqs. 3-5) rests on the log-distance path loss with log-normal
shadowing (its reference 16, Dardari et al.; Gezici 2008):

.. math::
    P_i = P_0 - 10\gamma\log_{10}(d_i/d_0) + g(\psi_i) + X_i,\qquad X_i\sim\mathcal N(0, \sigma_{sh}^2)

with P_i the received power (dB, in whatever unit the receiver reports: the model needs no
calibration of the absolute level), P_0 the power at d_0 = 1 m (the *reference power*), γ the
path-loss exponent, σ_sh the shadowing standard deviation (dB; the paper's σ_sh/γ is the
ratio its eq. 5 uses: σ_r0 = (ln 10/10)(σ_sh/γ)), and g(ψ) an optional antenna gain (dB) that
depends on the elevation ψ of the receiver seen from the emitter. Samples the receiver did not
detect are censored (:mod:`planner.radio.tobit`).

* :class:`Pattern` and :data:`PATTERNS`: isotropic, or a vertical half-wave dipole (a null
  at the zenith: the power straight above a ground emitter is lower than some way off).
* :func:`fit_channel`: P_0, γ, σ_sh (one σ for line-of-sight links and one for the others,
  the paper's two ratios with one γ) with 95 % confidence intervals, from samples at known
  distances (the emitter's position known: a calibration flight).
* :func:`decorrelation_distance`, :func:`thin_by_distance`: real shadowing is correlated along
  the flight (a slow residual, not fast fading), so consecutive samples are not independent;
  the fits and the localization use samples spaced by the residual's correlation distance.

Pure numpy/scipy. Frame: any Cartesian frame in metres (the mission ENU frame).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import minimize

from planner.radio.tobit import expected_information, fit_linear, loglik_terms

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: dB per decade of distance per unit of exponent: μ = P0 − 10 γ log10 d.
DB_PER_DECADE: float = 10.0
#: 10/ln 10: d(10 log10 d)/d(ln d).
TEN_OVER_LN10: float = 10.0 / math.log(10.0)
#: Two-sided 95 % standard normal quantile.
Z95: float = 1.959963984540054
#: The lowest gain a pattern reports (dB): a model's null is never −∞ (a real antenna's is not,
#: and a sample right above a null would otherwise have zero likelihood).
PATTERN_FLOOR_DB: float = -30.0


@dataclass(frozen=True)
class Pattern:
    """An emitter's antenna gain as a function of the receiver's elevation ψ (dB).

    Attributes:
        name: ``"isotropic"`` (0 dB), ``"dipole"`` (a vertical half-wave dipole,
            G(ψ) = [cos(π/2 · sin ψ)/cos ψ]², 0 dB at the horizon, a null at ψ = ±90°,
            floored at :data:`PATTERN_FLOOR_DB`) or ``"dipole-pair"`` (vertical half-wave
            dipoles at both ends, the receiver's too: the receiver sees the emitter at −ψ, so
            the gain doubles in dB).
    """

    name: str

    def __post_init__(self) -> None:
        if self.name not in PATTERNS:
            raise ValueError(f"pattern: expected one of {', '.join(repr(p) for p in PATTERNS)}, found {self.name!r}")

    def gain_db(self, psi: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """(g(ψ) dB, dg/dψ dB/rad) at elevations ψ (rad, in [−π/2, π/2])."""
        psi = np.asarray(psi, dtype=float)
        return self.gain_db_sc(np.sin(psi), np.cos(psi))

    def gain_db_sc(self, sin_psi: ArrayLike, cos_psi: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """:meth:`gain_db` from sin ψ and cos ψ ≥ 0 (no trigonometry of ψ itself: the grid of a
        localization evaluates it for every candidate and sample)."""
        sn = np.asarray(sin_psi, dtype=float)
        c = np.asarray(cos_psi, dtype=float)
        if self.name == "isotropic":
            z = np.zeros(np.broadcast_shapes(sn.shape, c.shape))
            return z, z
        inner = (0.5 * np.pi) * sn
        ci = np.cos(inner)
        safe = (c > 1e-9) & (ci > 1e-12)
        cs = np.where(safe, c, 1.0)
        cis = np.where(safe, ci, 1.0)
        k = 2.0 * TEN_OVER_LN10
        g = np.where(safe, k * (np.log(cis) - np.log(cs)), PATTERN_FLOOR_DB)
        dg = np.where(safe, k * (-(np.sin(inner) / cis) * (0.5 * np.pi) * c + sn / cs), 0.0)
        low = g <= PATTERN_FLOOR_DB
        ends = 2.0 if self.name == "dipole-pair" else 1.0
        return ends * np.where(low, PATTERN_FLOOR_DB, g), ends * np.where(low, 0.0, dg)


#: The patterns by name.
PATTERNS: tuple[str, ...] = ("isotropic", "dipole", "dipole-pair")


@dataclass(frozen=True)
class LinkTerms:
    """Geometry of receiver → emitter links for the log-distance model, with derivatives.

    Attributes:
        log_d: 10 log10 d (dB·m scale: the regressor of −γ), (..., n).
        gain: the pattern's g(ψ) (dB), (..., n).
        dlogd_dp: ∂(10 log10 d)/∂p of the emitter position p, (..., n, 3), 1/m.
        dgain_dp: ∂g/∂p, (..., n, 3), dB/m.
    """

    log_d: FloatArray
    gain: FloatArray
    dlogd_dp: FloatArray
    dgain_dp: FloatArray


def link_terms(emitter: ArrayLike, receivers: ArrayLike, pattern: Pattern, derivatives: bool = True) -> LinkTerms:
    """:class:`LinkTerms` of an emitter at ``emitter`` (..., 3) and receivers (n, 3), m.

    ψ = atan2(z_r − z_p, ρ), ρ the horizontal distance: ∂ψ/∂p_xy = Δz (r − p)_xy/(ρ d²),
    ∂ψ/∂p_z = −ρ/d²; ∂(10 log10 d)/∂p = −(10/ln 10)(r − p)/d². Without ``derivatives`` the
    two derivative arrays are empty (shape (0,)): the profile likelihood on a grid needs none.
    """
    p = np.asarray(emitter, dtype=float)[..., None, :]
    r = np.asarray(receivers, dtype=float)
    v = r - p  # emitter → receiver
    rho2 = np.maximum(v[..., 0] ** 2 + v[..., 1] ** 2, 1e-12)
    d2 = rho2 + v[..., 2] ** 2
    log_d = (0.5 * TEN_OVER_LN10) * np.log(d2)
    if pattern.name == "isotropic":
        gain = np.zeros_like(log_d)
        dg = gain
        rho = None
    else:
        rho = np.sqrt(rho2)
        inv_d = 1.0 / np.sqrt(d2)
        gain, dg = pattern.gain_db_sc(v[..., 2] * inv_d, rho * inv_d)
    if not derivatives:
        empty = np.zeros(0)
        return LinkTerms(log_d=log_d, gain=gain, dlogd_dp=empty, dgain_dp=empty)
    dlogd = -TEN_OVER_LN10 * v / d2[..., None]
    if rho is None:
        return LinkTerms(log_d=log_d, gain=gain, dlogd_dp=dlogd, dgain_dp=np.zeros_like(v))
    dpsi = np.empty_like(v)
    dpsi[..., 0] = v[..., 2] * v[..., 0] / (rho * d2)
    dpsi[..., 1] = v[..., 2] * v[..., 1] / (rho * d2)
    dpsi[..., 2] = -rho / d2
    return LinkTerms(log_d=log_d, gain=gain, dlogd_dp=dlogd, dgain_dp=dg[..., None] * dpsi)


@dataclass(frozen=True)
class Estimate:
    """A fitted value with its 95 % confidence interval (the unit of the quantity)."""

    value: float
    low: float
    high: float


@dataclass(frozen=True)
class ChannelFit:
    """The log-distance channel fitted to samples at known distances (:func:`fit_channel`).

    Attributes:
        reference_power_db: P_0, received power at d_0 = 1 m (the log's dB units).
        gamma: the path-loss exponent γ.
        sigma_los_db: σ_sh of line-of-sight links (dB).
        sigma_nlos_db: σ_sh of the other links (dB); None when no sample was NLOS.
        detected, censored: samples used, by kind (LOS and NLOS together).
        nlos: samples of NLOS links among them.
        residual_rms_db: RMS of the detected samples' residuals y − μ (dB).
        loglik: the maximised log-likelihood.
    """

    reference_power_db: Estimate
    gamma: Estimate
    sigma_los_db: Estimate
    sigma_nlos_db: Estimate | None
    detected: int
    censored: int
    nlos: int
    residual_rms_db: float
    loglik: float

    @property
    def sigma_ratio_los(self) -> float:
        """σ_sh/γ of LOS links (the paper's ratio, eq. 5; 1.7 in its case study)."""
        return self.sigma_los_db.value / self.gamma.value

    @property
    def sigma_ratio_nlos(self) -> float | None:
        """σ_sh/γ of NLOS links (the paper's 3.2), None without NLOS samples."""
        return None if self.sigma_nlos_db is None else self.sigma_nlos_db.value / self.gamma.value


def _check_samples(power_db: FloatArray, censored: BoolArray, threshold_db: FloatArray) -> None:
    if not (power_db.shape == censored.shape == threshold_db.shape) or power_db.ndim != 1:
        raise ValueError(f"samples: expected equal 1-D shapes, found {power_db.shape}, {censored.shape}, {threshold_db.shape}")
    if not np.isfinite(threshold_db[censored]).all():
        raise ValueError("samples: expected a finite threshold for every censored sample")
    if not np.isfinite(power_db[~censored]).all():
        raise ValueError("samples: expected a finite power for every detected sample")


def censored_values(power_db: ArrayLike, censored: ArrayLike, threshold_db: ArrayLike) -> FloatArray:
    """y of :mod:`planner.radio.tobit`: the power of a detected sample, the threshold of a
    censored one (dB)."""
    return np.where(np.asarray(censored, dtype=bool), np.asarray(threshold_db, float), np.asarray(power_db, float))


def fit_channel(
    distance_m: ArrayLike,
    power_db: ArrayLike,
    censored: ArrayLike,
    threshold_db: ArrayLike,
    los: ArrayLike | None = None,
    gain_db: ArrayLike | None = None,
) -> ChannelFit:
    """Fit P_0, γ and σ_sh (LOS and NLOS) by maximum likelihood, censored samples included.

    Args:
        distance_m: emitter-receiver distances d_i (n,), m, > 0.
        power_db: received power (n,), dB (ignored where censored).
        censored: (n,) bool: the sample was not detected (below its threshold or unlocked).
        threshold_db: (n,) the detection threshold of each sample, dB (NaN where none applies;
            required where censored).
        los: (n,) bool, True for a line-of-sight link (default: all LOS).
        gain_db: (n,) the emitter's antenna gain towards each sample (dB), default 0.

    Returns:
        The :class:`ChannelFit`. Confidence intervals: Wald, from the expected Fisher
        information of the censored model at the estimate (σ's on a log scale), 95 %.

    Raises:
        ValueError: fewer than 3 detected samples, distances not positive, or shapes differ.
    """
    d = np.asarray(distance_m, dtype=float)
    pw = np.asarray(power_db, dtype=float)
    cens = np.asarray(censored, dtype=bool)
    thr = np.asarray(threshold_db, dtype=float)
    _check_samples(pw, cens, thr)
    if not (np.isfinite(d).all() and (d > 0.0).all()):
        raise ValueError("expected positive finite distances to fit the channel")
    lo = np.ones(d.shape, dtype=bool) if los is None else np.asarray(los, dtype=bool)
    g = np.zeros(d.shape) if gain_db is None else np.asarray(gain_db, dtype=float)
    if (~cens).sum() < 3:
        raise ValueError(f"expected at least 3 detected samples to fit the channel, found {(~cens).sum()}")
    y = censored_values(pw, cens, thr)
    logd = 0.5 * TEN_OVER_LN10 * np.log(d * d)
    x = _channel_maximum(y, cens, logd, lo, g)
    mu = x[0] - x[1] * logd + g
    sig = np.where(lo, math.exp(x[2]), math.exp(x[3]))
    se = _channel_standard_errors(mu, sig, thr, logd, lo)

    def wald(i: int, value: float) -> Estimate:
        return Estimate(value, value - Z95 * float(se[i]), value + Z95 * float(se[i]))

    def log_wald(i: int, value: float) -> Estimate:
        f = math.exp(Z95 * float(se[i]) / value)
        return Estimate(value, value / f, value * f)

    det = ~cens
    return ChannelFit(
        reference_power_db=wald(0, float(x[0])),
        gamma=wald(1, float(x[1])),
        sigma_los_db=log_wald(2, math.exp(x[2])),
        sigma_nlos_db=log_wald(3, math.exp(x[3])) if (~lo).any() else None,
        detected=int(det.sum()),
        censored=int(cens.sum()),
        nlos=int((~lo).sum()),
        residual_rms_db=float(np.sqrt(np.mean((pw[det] - mu[det]) ** 2))),
        loglik=float(loglik_terms(y, cens, mu, sig)[0].sum()),
    )


def _channel_maximum(y: FloatArray, cens: BoolArray, logd: FloatArray, lo: BoolArray, g: FloatArray) -> FloatArray:
    """x̂ = (P0, γ, ln σ_LOS, ln σ_NLOS) of :func:`fit_channel`: the exact censored fit of the
    LOS samples (one σ), then with NLOS samples a quasi-Newton climb of the full likelihood."""
    X = np.column_stack([np.ones_like(logd), -logd])
    first = fit_linear(y[lo], cens[lo], X[lo], offset=g[lo]) if lo.sum() >= 3 else fit_linear(y, cens, X, offset=g)
    start = np.array([first.beta[0], first.beta[1], math.log(first.sigma), math.log(first.sigma)])
    if lo.all():
        return start

    def nll(x: FloatArray) -> tuple[float, FloatArray]:
        mu = x[0] - x[1] * logd + g
        sig = np.where(lo, math.exp(x[2]), math.exp(x[3]))
        ll, dmu, dsig = loglik_terms(y, cens, mu, sig)
        grad = np.array([dmu.sum(), -(dmu * logd).sum(), (dsig * sig)[lo].sum(), (dsig * sig)[~lo].sum()])
        return -float(ll.sum()), -grad

    return np.asarray(minimize(nll, start, jac=True, method="BFGS", options={"gtol": 1e-9, "maxiter": 500}).x, dtype=float)


def _channel_standard_errors(mu: FloatArray, sig: FloatArray, thr: FloatArray, logd: FloatArray, lo: BoolArray) -> FloatArray:
    """Standard errors of (P0, γ, σ_LOS[, σ_NLOS]) from the expected information of the censored
    model (∂μ/∂(P0, γ) = (1, −10 log10 d); σ_NLOS only when a link is NLOS)."""
    i_mm, i_ms, i_ss = expected_information(mu, sig, thr)
    dmu = np.column_stack([np.ones_like(logd), -logd])
    dsg = np.column_stack([lo.astype(float), (~lo).astype(float)])
    J = np.zeros((4, 4))
    J[:2, :2] = np.einsum("n,ni,nj->ij", i_mm, dmu, dmu)
    J[:2, 2:] = np.einsum("n,ni,nj->ij", i_ms, dmu, dsg)
    J[2:, :2] = J[:2, 2:].T
    J[2:, 2:] = np.einsum("n,ni,nj->ij", i_ss, dsg, dsg)
    keep = [0, 1, 2, 3] if (~lo).any() else [0, 1, 2]
    return np.sqrt(np.diag(np.linalg.inv(J[np.ix_(keep, keep)])))


def path_length_m(positions: ArrayLike) -> FloatArray:
    """Cumulative distance flown along a track of positions (n, 3), m (0 at the first)."""
    p = np.asarray(positions, dtype=float)
    if len(p) == 0:
        return np.zeros(0)
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])


def decorrelation_distance(path_m: ArrayLike, residual_db: ArrayLike, max_lag: int = 4000) -> float:
    """The distance flown (m) over which a residual's autocorrelation falls below 1/e.

    Args:
        path_m: cumulative distance flown at each sample (n,), m, non-decreasing (time order).
        residual_db: the residual y − μ of each sample (n,), dB (detected samples only).
        max_lag: the longest lag examined, in samples.

    Returns:
        The mean distance flown between samples L apart, at the first lag L whose sample
        autocorrelation is below 1/e; 0.0 when the first lag already is (independent samples);
        the distance at ``max_lag`` (or the whole track) if it never falls that low.
    """
    s = np.asarray(path_m, dtype=float)
    e = np.asarray(residual_db, dtype=float)
    e = e - e.mean()
    n = len(e)
    if n < 3:
        return 0.0
    var = float(e @ e)
    if var <= 0.0:
        return 0.0
    size = 1 << int(math.ceil(math.log2(2 * n)))
    f = np.fft.rfft(e, size)
    acf = np.fft.irfft(f * np.conj(f), size)[: min(n, max_lag + 1)] / var
    below = np.nonzero(acf[1:] < math.exp(-1.0))[0]
    lag = int(below[0]) + 1 if len(below) else len(acf) - 1
    if lag == 1 and acf[1] < math.exp(-1.0):
        return 0.0
    return float(np.mean(s[lag:] - s[:-lag]))


def thin_by_distance(path_m: ArrayLike, spacing_m: float) -> NDArray[np.intp]:
    """Indices of the samples kept when each kept sample is at least ``spacing_m`` of flight
    after the previous kept one (the first is kept); all of them for a spacing of 0."""
    s = np.asarray(path_m, dtype=float)
    if spacing_m <= 0.0 or len(s) == 0:
        return np.arange(len(s))
    kept = [0]
    last = s[0]
    # One pass; a track has at most some 10⁵ samples.
    for i in range(1, len(s)):
        if s[i] - last >= spacing_m:
            kept.append(i)
            last = s[i]
    return np.asarray(kept, dtype=np.intp)


__all__ = [
    "PATTERNS",
    "PATTERN_FLOOR_DB",
    "ChannelFit",
    "Estimate",
    "LinkTerms",
    "Pattern",
    "censored_values",
    "decorrelation_distance",
    "fit_channel",
    "link_terms",
    "path_length_m",
    "thin_by_distance",
]

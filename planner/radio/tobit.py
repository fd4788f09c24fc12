r"""The censored normal model of a received-power sample (a Tobit model), for real radio logs.

A receiver reports the power y (dB) of a sample when it detects the signal; below a detection
threshold c (dB), or when it has lost lock, it reports nothing usable: the sample is
*censored*, and all it says is y* < c. With y* ~ N(μ, σ²) the log-likelihood of one sample is

.. math::
    \ell = \begin{cases}
        -\ln\sigma - \tfrac12 \ln 2\pi - \tfrac12 u^2, & u = (y-\mu)/\sigma \quad\text{(detected)}\\
        \ln\Phi(a), & a = (c-\mu)/\sigma \quad\text{(censored)}
    \end{cases}

(Tobin 1958). The mean μ is the log-distance model of :mod:`planner.radio.pathloss` (the
RSS counterpart of the paper's eq. 5); this module only knows μ and σ.

* :func:`loglik_terms`: ℓ per sample and its derivatives with respect to μ and σ.
* :func:`fit_linear`: the maximum-likelihood fit of μ_i = o_i + X_i β, σ_i = k_i σ (known
  offsets o, regressors X, relative scales k), batched over many candidate source positions
  at once, by Newton's method in Olsen's parametrisation (α = β/σ, h = 1/σ), in which the
  log-likelihood is concave (Olsen, Econometrica 46(5), 1978), so Newton with step halving
  reaches the global maximum.
* :func:`expected_information`: the expected Fisher information of (μ, σ) of one sample that
  would have been censored below c (Amemiya, Econometrica 41(6), 1973; written out below);
  with no threshold (c = −∞) it is diag(1/σ², 2/σ²).

Pure numpy/scipy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import log_ndtr, ndtr

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

_LOG_SQRT_2PI: float = 0.5 * math.log(2.0 * math.pi)


def inverse_mills(a: ArrayLike) -> FloatArray:
    """λ(a) = φ(a)/Φ(a), computed in logs (finite for any finite a; ≈ −a for a ≪ 0)."""
    a = np.asarray(a, dtype=float)
    return np.exp(-0.5 * a * a - _LOG_SQRT_2PI - log_ndtr(a))


def loglik_terms(y: ArrayLike, censored: ArrayLike, mu: ArrayLike, sigma: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per-sample log-likelihood of the censored normal model and its derivatives.

    Args:
        y: the detected power (dB) of a detected sample, the threshold c (dB) of a censored one.
        censored: True where the sample is censored (y* < c), bool.
        mu: the model's mean power μ (dB). sigma: its standard deviation σ (dB), > 0.
        (All broadcast together.)

    Returns:
        (ℓ, ∂ℓ/∂μ (1/dB), ∂ℓ/∂σ (1/dB)), each of the broadcast shape.
    """
    y, mu, sigma = np.broadcast_arrays(np.asarray(y, float), np.asarray(mu, float), np.asarray(sigma, float))
    cens = np.broadcast_to(np.asarray(censored, dtype=bool), y.shape)
    u = (y - mu) / sigma
    lam = inverse_mills(np.where(cens, u, 0.0))
    ll = np.where(cens, log_ndtr(np.where(cens, u, 0.0)), -np.log(sigma) - _LOG_SQRT_2PI - 0.5 * u * u)
    d_mu = np.where(cens, -lam / sigma, u / sigma)
    d_sigma = np.where(cens, -u * lam / sigma, (u * u - 1.0) / sigma)
    return ll, d_mu, d_sigma


def expected_information(mu: ArrayLike, sigma: ArrayLike, threshold: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    r"""Expected Fisher information of (μ, σ) of one sample censored below ``threshold``.

    With a = (c − μ)/σ, Q = 1 − Φ(a), φ = φ(a), Φ = Φ(a) (moments of the standard normal above
    a: ∫u² = Q + aφ, ∫u³ = (a² + 2)φ, ∫u⁴ = 3Q + (a³ + 3a)φ):

    .. math::
        I_{\mu\mu} = \frac{Q + a\varphi + \varphi^2/\Phi}{\sigma^2},\quad
        I_{\mu\sigma} = \frac{(a^2+1)\varphi + a\varphi^2/\Phi}{\sigma^2},\quad
        I_{\sigma\sigma} = \frac{2Q + (a^3+a)\varphi + a^2\varphi^2/\Phi}{\sigma^2}

    Args:
        mu, sigma: mean and standard deviation (dB). threshold: c (dB); NaN or −inf where the
            sample cannot be censored.

    Returns:
        (I_μμ, I_μσ, I_σσ), 1/dB², of the broadcast shape.
    """
    mu, sigma, c = np.broadcast_arrays(np.asarray(mu, float), np.asarray(sigma, float), np.asarray(threshold, float))
    has = np.isfinite(c)
    a = np.where(has, (np.where(has, c, 0.0) - mu) / sigma, -np.inf)
    af = np.where(has, a, 0.0)
    phi = np.where(has, np.exp(-0.5 * af * af - _LOG_SQRT_2PI), 0.0)
    big_phi = np.where(has, ndtr(af), 0.0)
    q = 1.0 - big_phi
    lam_phi = np.where(has, phi * inverse_mills(af), 0.0)  # φ²/Φ
    s2 = sigma * sigma
    i_mm = (q + af * phi + lam_phi) / s2
    i_ms = ((af * af + 1.0) * phi + af * lam_phi) / s2
    i_ss = (2.0 * q + (af**3 + af) * phi + af * af * lam_phi) / s2
    return i_mm, i_ms, i_ss


@dataclass(frozen=True)
class LinearFit:
    """A batch of censored linear fits (:func:`fit_linear`).

    Attributes:
        beta: β, (..., k) (the units of y over those of X).
        sigma: σ, (...), dB (the scale of a sample with relative scale k_i = 1).
        loglik: the maximised log-likelihood, (...).
        converged: Newton's relative change fell below the tolerance, (...) bool.
    """

    beta: FloatArray
    sigma: FloatArray
    loglik: FloatArray
    converged: BoolArray


@dataclass(frozen=True)
class _Scaled:
    """The scaled problem of :func:`fit_linear`, batch flattened to (B,): the detected samples'
    sufficient statistics (Σ X̃X̃ᵀ, Σ X̃ỹ, Σ ỹ², their count) and the censored samples' rows
    (X̃, c̃) with ∂z/∂(α, h) = (−X̃, c̃)."""

    sxx: FloatArray  # (B, k, k)
    sxy: FloatArray  # (B, k)
    syy: FloatArray  # (B,)
    n_det: float
    xc: FloatArray  # (B, nc, k)
    cc: FloatArray  # (B, nc)
    dz: FloatArray  # (B, nc, k + 1)
    const: FloatArray  # (B,): −n_det ln √2π − Σ_det ln k_i

    def loglik(self, alpha: FloatArray, h: FloatArray, idx: NDArray[np.intp]) -> tuple[FloatArray, FloatArray, FloatArray]:
        """ℓ(α, h) of the batch elements ``idx``, their censored rows' z = h c̃ − X̃α and ln Φ(z)."""
        sxx, sxy = self.sxx[idx], self.sxy[idx]
        quad = h * h * self.syy[idx] - 2.0 * h * (sxy * alpha).sum(-1) + (alpha[:, :, None] * sxx * alpha[:, None, :]).sum((-1, -2))
        ll = self.n_det * np.log(h) - 0.5 * quad + self.const[idx]
        z = h[:, None] * self.cc[idx] - (self.xc[idx] @ alpha[:, :, None])[:, :, 0]
        log_phi = log_ndtr(z)
        return ll + log_phi.sum(-1), z, log_phi


def _scaled_problem(y: ArrayLike, cens: BoolArray, X: FloatArray, offset: ArrayLike, scale: ArrayLike) -> tuple[_Scaled, tuple[int, ...]]:
    """The :class:`_Scaled` problem of :func:`fit_linear` and the batch shape."""
    n, k = X.shape[-2], X.shape[-1]
    batch = np.broadcast_shapes(X.shape[:-2], np.shape(y)[:-1], np.shape(offset)[:-1], np.shape(scale)[:-1])
    nb = int(np.prod(batch, dtype=int))

    def flat(v: ArrayLike) -> FloatArray:
        return np.broadcast_to(np.asarray(v, float), batch + (n,)).reshape(nb, n)

    kk = flat(scale)
    yt = (flat(y) - flat(offset)) / kk
    Xt = np.broadcast_to(X, batch + (n, k)).reshape(nb, n, k) / kk[:, :, None]
    det = ~cens
    Xd, yd = Xt[:, det, :], yt[:, det]
    nd = float(det.sum())
    xc, cc = Xt[:, cens, :], yt[:, cens]
    prob = _Scaled(
        sxx=np.swapaxes(Xd, -1, -2) @ Xd,
        sxy=(np.swapaxes(Xd, -1, -2) @ yd[:, :, None])[:, :, 0],
        syy=(yd * yd).sum(-1),
        n_det=nd,
        xc=xc,
        cc=cc,
        dz=np.concatenate([-xc, cc[:, :, None]], axis=-1),
        const=-nd * _LOG_SQRT_2PI - np.log(kk[:, det]).sum(-1),
    )
    return prob, batch


def _least_squares_start(prob: _Scaled) -> tuple[FloatArray, FloatArray]:
    """(α, h) of least squares on the detected samples and the censored ones at their threshold."""
    nb, k = prob.sxy.shape
    if k:
        xc, cc = prob.xc, prob.cc
        A = prob.sxx + 0.3 * (np.swapaxes(xc, -1, -2) @ xc) + 1e-9 * np.eye(k)
        beta0 = np.linalg.solve(A, (prob.sxy + 0.3 * (np.swapaxes(xc, -1, -2) @ cc[:, :, None])[:, :, 0])[:, :, None])[:, :, 0]
    else:
        beta0 = np.zeros((nb, 0))
    rss = prob.syy - 2.0 * (prob.sxy * beta0).sum(-1) + (beta0[:, :, None] * prob.sxx * beta0[:, None, :]).sum((-1, -2))
    h = 1.0 / np.sqrt(np.maximum(rss / max(prob.n_det, 1.0), 1e-6))
    return beta0 * h[:, None], h


def _newton_step(prob: _Scaled, a: FloatArray, hh: FloatArray, z: FloatArray, log_phi: FloatArray, idx: NDArray[np.intp]) -> FloatArray:
    """Newton's step in (α, h) of the batch elements ``idx`` at (α, h) = (a, hh), their censored
    rows at z with ln Φ(z) = ``log_phi``: (len(idx), k + 1)."""
    k = a.shape[1]
    m = k + 1
    nd = prob.n_det
    sxx_i, sxy_i = prob.sxx[idx], prob.sxy[idx]
    # Detected samples: g = (S_xy h − S_xx α, n/h − S_yy h + S_xyᵀα); H from the same sums.
    g = np.empty((len(idx), m))
    g[:, :k] = hh[:, None] * sxy_i - (sxx_i @ a[:, :, None])[:, :, 0]
    g[:, k] = nd / hh - hh * prob.syy[idx] + (sxy_i * a).sum(-1)
    H = np.empty((len(idx), m, m))
    H[:, :k, :k] = -sxx_i
    H[:, :k, k] = sxy_i
    H[:, k, :k] = sxy_i
    H[:, k, k] = -nd / (hh * hh) - prob.syy[idx]
    if z.shape[-1]:
        lam = np.exp(-0.5 * z * z - _LOG_SQRT_2PI - log_phi)  # φ(z)/Φ(z), Φ from the last ℓ
        dz = prob.dz[idx]
        g += (np.swapaxes(dz, -1, -2) @ lam[:, :, None])[:, :, 0]
        H -= np.swapaxes(dz, -1, -2) @ (dz * (lam * (z + lam))[:, :, None])
    return np.asarray(np.linalg.solve(H - 1e-12 * np.eye(m), -g[:, :, None])[:, :, 0], dtype=float)


@dataclass
class _Iterate:
    """The accepted points of one halving line search, for the batch elements of a step."""

    ll: FloatArray
    alpha: FloatArray
    h: FloatArray
    z: FloatArray
    log_phi: FloatArray
    t: FloatArray


def _halving(
    prob: _Scaled, a: FloatArray, hh: FloatArray, z: FloatArray, log_phi: FloatArray, ll_i: FloatArray, step: FloatArray, idx: NDArray[np.intp]
) -> _Iterate:
    """Step halving along ``step`` until ℓ does not decrease (30 halvings at most); ``ll`` −inf
    where no point was accepted."""
    k = a.shape[1]
    out = _Iterate(np.full(len(idx), -np.inf), a.copy(), hh.copy(), z.copy(), log_phi.copy(), np.ones(len(idx)))
    todo = np.ones(len(idx), dtype=bool)
    for _ in range(30):
        sub = np.nonzero(todo)[0]
        cand_h = hh[sub] + out.t[sub] * step[sub, k]
        cand_alpha = a[sub] + out.t[sub, None] * step[sub, :k]
        ok_h = cand_h > 0.0
        cand_ll, cand_z, cand_lp = prob.loglik(cand_alpha, np.where(ok_h, cand_h, 1.0), idx[sub])
        cand_ll = np.where(ok_h, cand_ll, -np.inf)
        better = cand_ll >= ll_i[sub] - 1e-12 * np.abs(ll_i[sub])
        won = sub[better]
        out.ll[won], out.h[won], out.alpha[won] = cand_ll[better], cand_h[better], cand_alpha[better]
        out.z[won], out.log_phi[won] = cand_z[better], cand_lp[better]
        todo[won] = False
        if not todo.any():
            break
        out.t[todo] *= 0.5
    return out


def fit_linear(
    y: ArrayLike,
    censored: ArrayLike,
    X: ArrayLike,
    offset: ArrayLike = 0.0,
    scale: ArrayLike = 1.0,
    iterations: int = 60,
    tol: float = 1e-9,
) -> LinearFit:
    r"""Maximum-likelihood fit of μ_i = o_i + X_i β, σ_i = k_i σ to censored samples, batched.

    Dividing by k_i, ỹ_i = (y_i − o_i)/k_i follows N(X̃_i β, σ²), X̃ = X/k, censored below
    c̃_i = (c_i − o_i)/k_i. In Olsen's parameters α = β/σ, h = 1/σ the log-likelihood

    .. math::
        \ell = \sum_{\text{det}} \big[\ln h - \tfrac12 (h\tilde y_i - \tilde X_i\alpha)^2\big]
             + \sum_{\text{cens}} \ln\Phi(h\tilde c_i - \tilde X_i\alpha) + \text{const}

    is concave; Newton's method with step halving climbs it from the least-squares start. The
    detected samples enter through their sufficient statistics, so an iteration costs only the
    censored samples, and only the batch elements not yet converged.

    Args:
        y: (..., n) detected power, or the threshold of a censored sample (dB).
        censored: (n,) bool (the same samples are censored in every batch element).
        X: (..., n, k) regressors (k may be 0: σ alone is fitted).
        offset: o, (..., n) dB, known part of the mean.
        scale: k_i > 0, (..., n), known relative standard deviations (e.g. NLOS/LOS).
        iterations: Newton iterations at most. tol: stop when every relative step is below it.

    Returns:
        The :class:`LinearFit` (batch shape: the broadcast leading shape). Where every sample
        is censored the likelihood has no maximum (it tends to 0 as the mean goes to −∞): the
        fit then stops at the iteration cap with ``converged`` False.
    """
    X = np.asarray(X, dtype=float)
    cens = np.asarray(censored, dtype=bool)
    if cens.shape != (X.shape[-2],):
        raise ValueError(f"fit_linear: expected censored of shape ({X.shape[-2]},), found {cens.shape}")
    prob, batch = _scaled_problem(y, cens, X, offset, scale)
    alpha, h = _least_squares_start(prob)
    idx = np.arange(len(h))
    ll, z, log_phi = prob.loglik(alpha, h, idx)
    converged = np.zeros(len(h), dtype=bool)
    for _ in range(iterations):
        a, hh = alpha[idx], h[idx]
        step = _newton_step(prob, a, hh, z, log_phi, idx)
        new = _halving(prob, a, hh, z, log_phi, ll[idx], step, idx)
        moved = np.isfinite(new.ll)
        rel = np.abs(new.t[:, None] * step) / (np.abs(np.concatenate([a, hh[:, None]], axis=-1)) + 1e-12)
        alpha[idx[moved]] = new.alpha[moved]
        h[idx[moved]] = new.h[moved]
        ll[idx[moved]] = new.ll[moved]
        done = ~moved | (rel.max(-1, initial=0.0) < tol)
        converged[idx[done]] = True
        keep = ~done
        idx, z, log_phi = idx[keep], new.z[keep], new.log_phi[keep]
        if not len(idx):
            break
    sigma = 1.0 / h
    return LinearFit(
        beta=(alpha * sigma[:, None]).reshape(batch + (alpha.shape[1],)),
        sigma=sigma.reshape(batch),
        loglik=ll.reshape(batch),
        converged=converged.reshape(batch),
    )


__all__ = ["LinearFit", "expected_information", "fit_linear", "inverse_mills", "loglik_terms"]

"""Closed-form 3 × 3 linear algebra of the estimator (determinant, adjugate, SPD inverse),
batched over leading dimensions, and angle wrapping."""

from __future__ import annotations

import numpy as np

from tests.reference_numpy.estimator.state import BoolArray, FloatArray


# --------------------------------------------------------------------------- small linear algebra
def _det3(a: FloatArray) -> FloatArray:
    return (
        a[..., 0, 0] * (a[..., 1, 1] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 1])
        - a[..., 0, 1] * (a[..., 1, 0] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 0])
        + a[..., 0, 2] * (a[..., 1, 0] * a[..., 2, 1] - a[..., 1, 1] * a[..., 2, 0])
    )


def _adj3(a: FloatArray) -> FloatArray:
    """Adjugate of symmetric 3x3 matrices (..., 3, 3)."""
    c = np.empty_like(a)
    c[..., 0, 0] = a[..., 1, 1] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 1]
    c[..., 0, 1] = a[..., 0, 2] * a[..., 2, 1] - a[..., 0, 1] * a[..., 2, 2]
    c[..., 0, 2] = a[..., 0, 1] * a[..., 1, 2] - a[..., 0, 2] * a[..., 1, 1]
    c[..., 1, 1] = a[..., 0, 0] * a[..., 2, 2] - a[..., 0, 2] * a[..., 2, 0]
    c[..., 1, 2] = a[..., 0, 2] * a[..., 1, 0] - a[..., 0, 0] * a[..., 1, 2]
    c[..., 2, 2] = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
    c[..., 1, 0] = c[..., 0, 1]
    c[..., 2, 0] = c[..., 0, 2]
    c[..., 2, 1] = c[..., 1, 2]
    return c


def _inv3_spd(a: FloatArray) -> tuple[FloatArray, BoolArray]:
    """Inverse of symmetric 3x3 matrices and a flag where it is well defined."""
    det = _det3(a)
    scale = np.maximum(np.einsum("...ii->...", a), 1e-300) ** 3
    ok = np.isfinite(det) & (det > 1e-14 * scale)
    safe = np.where(ok, det, 1.0)
    return _adj3(a) / safe[..., None, None], ok


def _normalised_det(a: FloatArray) -> FloatArray:
    """det(A)/(tr(A)/3)³ of symmetric PSD 3x3 matrices (0 where tr A = 0).

    It lies in [0, 1], equals 1 for A ∝ I, and bounds the conditioning from below:
    det/(tr/3)³ ≤ 27 λ_min λ_mid λ_max/λ_max³ ≤ 27 λ_min/λ_max.
    """
    tr = np.einsum("...ii->...", a) / 3.0
    safe = np.where(tr > 0.0, tr, 1.0)
    return np.where(tr > 0.0, _det3(a) / safe**3, 0.0)

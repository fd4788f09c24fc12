r"""The robust refinement's measurement components outside the fused range/bearing kernel.

The refinement (package doc, step 2; compiled in :mod:`planner.estimator.kernels.robust`)
minimises Σ a ρ(e) over every value of the rows, e = (z − h(p0))/σ. Range and bearing are
fused in the compiled kernel; any other component (:data:`planner.sensing.COMPONENTS` beyond
them, e.g. a test's toy component) supplies its residuals e and their gradients ∂e/∂p0 through
its own :meth:`planner.sensing.SensingComponent.estimator_terms`, which the compiled code calls
back here (:func:`extension_callback`) at every evaluation of a call whose records carry such
values; the robust loss, the sums and the iterations stay compiled.
"""

from __future__ import annotations

import ctypes
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planner.params import Channel
from planner.sensing import BEARING, RANGE, LinkGeometry, SensingComponent

#: Floor (m²) of ρ², keeping the model finite right above or below a drone.
_RHO2_FLOOR_M2: float = 1e-12


def _groups(components: Sequence[SensingComponent], names: tuple[str, ...]) -> list[tuple[SensingComponent, list[int]]]:
    """The components outside the kernel whose every value is among ``names``, each with the
    columns of its values."""
    return [
        (c, [names.index(n) for n in c.value_names])
        for c in components
        if c.name not in (RANGE.name, BEARING.name) and all(n in names for n in c.value_names)
    ]


def extension_terms(
    groups: list[tuple[SensingComponent, list[int]]],
    x: NDArray[np.float64],
    positions: NDArray[np.float64],
    values: NDArray[np.float64],
    channel: Channel,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Normalised residuals e (K, X) and gradients ∂e/∂x (K, X, 3), m⁻¹, of the values (K, X)
    of rows taken at ``positions`` (K, 3), m, ENU, for a source at x (3,); 0 in the columns of
    no component in ``groups``."""
    r = x - positions
    rho2 = np.maximum(r[:, 0] * r[:, 0] + r[:, 1] * r[:, 1], _RHO2_FLOOR_M2)
    d2 = rho2 + r[:, 2] * r[:, 2]
    geom = LinkGeometry(r, rho2, d2, np.sqrt(d2))
    e = np.zeros(values.shape)
    de = np.zeros(values.shape + (3,))
    for component, cols in groups:
        e_c, de_c = component.estimator_terms(tuple(values[:, j] for j in cols), geom, channel)
        e[:, cols] = e_c
        de[:, cols] = de_c
    return e, de


def extension_callback(
    components: Sequence[SensingComponent], names: tuple[str, ...], channel: Channel
) -> tuple[NDArray[np.bool_], Any, list[BaseException]]:
    """For values named ``names``: which belong to a component of ``components`` outside the
    kernel (X,), the compiled refinement's callback computing their terms
    (:func:`extension_terms`), and the list where it leaves an exception it met (re-raised by
    the update: an exception cannot cross the compiled code)."""
    from planner.estimator.kernels import extension  # the compiler, on first use

    groups = _groups(components, names)
    used = np.zeros(len(names), dtype=bool)
    for _, cols in groups:
        used[cols] = True
    errors: list[BaseException] = []
    if not groups:
        return used, extension.NO_EXTENSION, errors

    def terms(address: int, K: int, X: int) -> float:
        try:
            size = 3 + 3 * K + 5 * K * X
            buf = np.ctypeslib.as_array((ctypes.c_double * size).from_address(address))
            positions = buf[3 : 3 + 3 * K].reshape(3, K).T
            values = buf[3 + 3 * K : 3 + 3 * K + K * X].reshape(K, X)
            e, de = extension_terms(groups, buf[:3].copy(), positions, values, channel)
            buf[3 + 3 * K + K * X : 3 + 3 * K + 2 * K * X] = e.ravel()
            buf[3 + 3 * K + 2 * K * X :] = de.ravel()
            return 0.0
        except Exception as exc:
            errors.append(exc)
            return float("nan")

    return used, extension.Callback(terms), errors

"""The paper's observation model (eqs. 3-5): ranging and bearing estimates from RSS.

For drone j and source p0 (mission ENU frame, metres, radians):

.. math::
    \\hat d_j = d_j + n_{r,j},\\quad n_{r,j}\\sim\\mathcal N(0, \\sigma_{r,0}^2 d_j^{\\gamma}),
    \\quad \\sigma_{r,0} = \\tfrac{\\ln 10}{10}\\,\\tfrac{\\sigma_{sh}}{\\gamma}
    \\qquad\\text{(eqs. 3, 5)}

    \\hat\\alpha_j = p_j(\\alpha_j + n_{b,j}) + \\bar p_j\\,\\omega_j,\\quad
    n_{b,j}\\sim\\mathcal N(0, \\sigma_{b,0}^2 I_2)\\qquad\\text{(eq. 3)}

with p_j = 1 in line of sight. σ_sh/γ takes its LOS or NLOS value from the link. The NLOS
bearing outlier ω_j (multipath) is drawn uniformly: azimuth on [-π, π), elevation on
[-π/2, π/2] (the paper does not give its law; see docs/paper-notes.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner.geometry import line_of_sight, ranges_angles
from planner.params import Channel
from planner.randomness import MEASUREMENT_DRAWS
from planner.sensing import BEARING, RANGE

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Observation:
    """Measurements of N drones (leading dims broadcast).

    Attributes:
        range_m: estimated distance d̂ (m), shape (..., N); NaN where the drone does not range.
        azimuth_rad: estimated azimuth φ̂ (rad), NaN where the drone has no bearing sensor.
        elevation_rad: estimated elevation θ̂ (rad), NaN where no bearing.
        los: True where the link was line of sight when measured, shape (..., N).
    """

    range_m: FloatArray
    azimuth_rad: FloatArray
    elevation_rad: FloatArray
    los: NDArray[np.bool_]


def ranging_std(d: ArrayLike, los: ArrayLike, channel: Channel) -> FloatArray:
    """σ_r = σ_r0 d^(γ/2) of eq. 5 (m), with σ_r0 for LOS or NLOS per link."""
    return RANGE.std_m(d, los, channel)


def observe_from_uniforms(
    source: ArrayLike,
    positions: ArrayLike,
    ranging: ArrayLike,
    bearing: ArrayLike,
    los: ArrayLike,
    channel: Channel,
    uniforms: ArrayLike,
) -> Observation:
    """Measurements of eq. 3 from five uniform variates per drone (deterministic).

    Args:
        source: true source p0, shape (..., 3), m, ENU.
        positions: true drone positions, shape (..., N, 3), m, ENU.
        ranging, bearing: sensing roles κ_j, β_j, boolean (..., N) or (N,).
        los: link state p_j, boolean (..., N).
        channel: the RSS channel.
        uniforms: shape (..., N, 5) in [0, 1): range noise, azimuth noise, elevation noise
            (through the normal quantile), then the outlier azimuth and elevation.

    Returns:
        The :class:`Observation`.
    """
    u = np.asarray(uniforms, dtype=float)
    d, phi, theta = ranges_angles(source, positions)
    los_b = np.asarray(los, dtype=bool)
    rng_mask = np.broadcast_to(np.asarray(ranging, dtype=bool), d.shape)
    brg_mask = np.broadcast_to(np.asarray(bearing, dtype=bool), d.shape)
    # Each component draws its variates from the uniforms it owns (planner.sensing); the
    # normal quantiles are kept finite (Generator.random() can return exactly 0).
    d_hat = RANGE.simulate(d, los_b, channel, u)
    az, el = BEARING.simulate(phi, theta, los_b, channel, u)
    nan = np.nan
    return Observation(
        range_m=np.where(rng_mask, d_hat, nan),
        azimuth_rad=np.where(brg_mask, az, nan),
        elevation_rad=np.where(brg_mask, el, nan),
        los=np.broadcast_to(los_b, d.shape).copy(),
    )


def observe(
    source: ArrayLike,
    positions: ArrayLike,
    ranging: ArrayLike,
    bearing: ArrayLike,
    boxes_min: ArrayLike,
    boxes_max: ArrayLike,
    channel: Channel,
    rng: np.random.Generator,
) -> Observation:
    """Draw the measurements of eq. 3 with LOS/NLOS from the obstacles.

    Draws ``positions.shape[:-1] + (5,)`` uniforms from ``rng`` (five per drone, in drone
    order), so one drone measured each step consumes its stream exactly as the in-process
    simulator does (see :mod:`planner.randomness`).

    Args:
        source: (..., 3) m, ENU. positions: (..., N, 3) m, ENU.
        ranging, bearing: boolean (N,) or (..., N): κ_j and β_j.
        boxes_min, boxes_max: obstacles, (B, 3) m, ENU.
        channel: RSS channel. rng: the drone's measurement generator.
    """
    p = np.asarray(positions, dtype=float)
    los = line_of_sight(p, source, boxes_min, boxes_max)
    uniforms = rng.random(p.shape[:-1] + (MEASUREMENT_DRAWS,))
    return observe_from_uniforms(source, p, ranging, bearing, los, channel, uniforms)

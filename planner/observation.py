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

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner.geometry import line_of_sight, ranges_angles
from planner.params import Channel
from planner.sensing import COMPONENTS, RANGE, SensingComponent, component_masks, measurement_draws

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Observation:
    """Measurements of N drones (leading dims broadcast).

    Attributes:
        values: every component's measured values by value name
            (:attr:`planner.sensing.SensingComponent.value_names`), each of shape (..., N);
            NaN where the drone does not have the component (read-only mapping).
        los: True where the link was line of sight when measured, shape (..., N).
    """

    values: Mapping[str, FloatArray]
    los: NDArray[np.bool_]

    @property
    def range_m(self) -> FloatArray:
        """Estimated distance d̂ (m), (..., N); NaN where the drone does not range."""
        return self.values["range_m"]

    @property
    def azimuth_rad(self) -> FloatArray:
        """Estimated azimuth φ̂ (rad), (..., N); NaN where the drone has no bearing sensor."""
        return self.values["azimuth_rad"]

    @property
    def elevation_rad(self) -> FloatArray:
        """Estimated elevation θ̂ (rad), (..., N); NaN where no bearing."""
        return self.values["elevation_rad"]


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
    extra_masks: Mapping[str, ArrayLike] | None = None,
    components: Sequence[SensingComponent] = COMPONENTS,
) -> Observation:
    """Measurements of eq. 3 from five uniform variates per drone (deterministic).

    Args:
        source: true source p0, shape (..., 3), m, ENU.
        positions: true drone positions, shape (..., N, 3), m, ENU.
        ranging, bearing: sensing roles κ_j, β_j, boolean (..., N) or (N,).
        los: link state p_j, boolean (..., N).
        channel: the RSS channel.
        uniforms: shape (..., N, U) in [0, 1), U = :func:`planner.sensing.measurement_draws`
            (5 for the registry): range noise, azimuth noise, elevation noise (through the
            normal quantile), then the outlier azimuth and elevation.
        extra_masks: masks (..., N) of the components other than range and bearing, by name.
        components: the measurement components (:data:`planner.sensing.COMPONENTS`).

    Returns:
        The :class:`Observation`.
    """
    u = np.asarray(uniforms, dtype=float)
    d, phi, theta = ranges_angles(source, positions)
    los_b = np.asarray(los, dtype=bool)
    values: dict[str, FloatArray] = {}
    for component, mask in zip(components, component_masks(ranging, bearing, extra_masks, components), strict=True):
        # Each component draws its variates from the uniform columns it owns
        # (planner.sensing); the normal quantiles are kept finite (Generator.random() can
        # return exactly 0).
        has = np.asarray(mask, dtype=bool)
        if has.shape != d.shape:
            has = np.broadcast_to(has, d.shape)
        drawn = component.simulate_values(d, phi, theta, los_b, channel, u)
        for name, value in zip(component.value_names, drawn, strict=True):
            values[name] = np.where(has, value, np.nan)
    return Observation(values=MappingProxyType(values), los=(los_b if los_b.shape == d.shape else np.broadcast_to(los_b, d.shape)).copy())


def observe(
    source: ArrayLike,
    positions: ArrayLike,
    ranging: ArrayLike,
    bearing: ArrayLike,
    boxes_min: ArrayLike,
    boxes_max: ArrayLike,
    channel: Channel,
    rng: np.random.Generator,
    extra_masks: Mapping[str, ArrayLike] | None = None,
    components: Sequence[SensingComponent] = COMPONENTS,
) -> Observation:
    """Draw the measurements of eq. 3 with LOS/NLOS from the obstacles.

    Draws ``positions.shape[:-1] + (U,)`` uniforms from ``rng`` (U =
    :func:`planner.sensing.measurement_draws`, five for the registry, per drone in drone order), so one drone measured each step consumes its stream exactly as the in-process
    simulator does (see :mod:`planner.randomness`).

    Args:
        source: (..., 3) m, ENU. positions: (..., N, 3) m, ENU.
        ranging, bearing: boolean (N,) or (..., N): κ_j and β_j.
        boxes_min, boxes_max: obstacles, (B, 3) m, ENU.
        channel: RSS channel. rng: the drone's measurement generator.
        extra_masks, components: see :func:`observe_from_uniforms`.
    """
    p = np.asarray(positions, dtype=float)
    los = line_of_sight(p, source, boxes_min, boxes_max)
    uniforms = rng.random(p.shape[:-1] + (measurement_draws(components),))
    return observe_from_uniforms(source, p, ranging, bearing, los, channel, uniforms, extra_masks, components)

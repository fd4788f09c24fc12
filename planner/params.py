"""Parameter objects of the math core: the radio channel, the safety and kinematic limits.

All values are SI and radians, per the conventions of ``docs/architecture.md``; the mission
loader converts the YAML's degrees and per-second speeds into these.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: Constraint activation rule. ``"safe"`` (default) activates a constraint with a margin that
#: covers one step of motion of both parties and filters the kinematically limited step so no
#: safety distance is ever crossed; ``"paper"`` is the paper's literal rule (eqs. 15-17:
#: a constraint enters the projection only once it is already violated).
Activation = Literal["safe", "paper"]

#: Design criterion of eq. (6): ``"A"`` = tr(J^-1), ``"D"`` = -ln det J.
Criterion = Literal["A", "D"]

LN10_OVER_10: float = math.log(10.0) / 10.0


@dataclass(frozen=True)
class Channel:
    """RSS channel of the observation model (paper eqs. 3-5).

    Attributes:
        gamma: path-loss exponent γ (dimensionless).
        sigma_ratio_los: σ_sh/γ in line of sight (paper: 1.7).
        sigma_ratio_nlos: σ_sh/γ in non line of sight (paper: 3.2).
        sigma_bearing_rad: bearing standard deviation σ_b,0 in radians (paper: 10°).
    """

    gamma: float = 2.0
    sigma_ratio_los: float = 1.7
    sigma_ratio_nlos: float = 3.2
    sigma_bearing_rad: float = math.radians(10.0)

    def __post_init__(self) -> None:
        for name in ("gamma", "sigma_ratio_los", "sigma_ratio_nlos", "sigma_bearing_rad"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"Channel.{name} must be a finite positive number, found {value!r}")

    @property
    def sigma_r0_los(self) -> float:
        """Ranging std at d0 = 1 m in LOS, σ_r0 = (ln10/10)(σ_sh/γ) (eq. 5), metres."""
        return LN10_OVER_10 * self.sigma_ratio_los

    @property
    def sigma_r0_nlos(self) -> float:
        """Ranging std at d0 = 1 m in NLOS, σ_r0 = (ln10/10)(σ_sh/γ) (eq. 5), metres."""
        return LN10_OVER_10 * self.sigma_ratio_nlos

    @cached_property
    def kernel_array(self) -> NDArray[np.float64]:
        """The channel as the compiled kernels take it (:func:`planner.kernels.channel_array`):
        (γ, σ_r0,LOS², σ_r0,NLOS², σ_b²), m² and rad²."""
        from planner.kernels import channel_array  # imported here: a vehicle process uses Channel without numba

        return channel_array(self.gamma, self.sigma_r0_los, self.sigma_r0_nlos, self.sigma_bearing_rad)

    def sigma_r0(self, los: ArrayLike) -> NDArray[np.float64]:
        """σ_r0 of each link (eq. 5), metres: the LOS value where ``los`` (bool, any shape),
        the NLOS value elsewhere. The ranging std at distance d is σ_r0 d^(γ/2)."""
        return np.where(np.asarray(los, dtype=bool), self.sigma_r0_los, self.sigma_r0_nlos)


@dataclass(frozen=True)
class Limits:
    """Safety distances and kinematic limits of problem (7), in per-step units.

    Attributes:
        d_uav_m: anti-collision distance d_U* between drones (m).
        d_source_m: keep-out distance d_S* from the source (m).
        d_obstacle_m: distance d_O* from any obstacle surface (m).
        step_min_m: v_min·Δt, minimum displacement per step (m).
        step_max_m: v_max·Δt, maximum displacement per step (m).
        heading_change_max_rad: φ_max, maximum change of heading Ψ per step (rad).
        tilt_change_max_rad: θ_max, maximum change of tilt Θ per step (rad).
        z_min_m, z_max_m: altitude box of the mission frame (m, ENU up).
        activation: constraint activation rule, see :data:`Activation`.
    """

    d_uav_m: float = 1.0
    d_source_m: float = 50.0
    d_obstacle_m: float = 5.0
    step_min_m: float = 0.5
    step_max_m: float = 1.0
    heading_change_max_rad: float = math.radians(50.0)
    tilt_change_max_rad: float = math.radians(50.0)
    z_min_m: float = 2.0
    z_max_m: float = 25.0
    activation: Activation = "safe"

    def __post_init__(self) -> None:
        if not 0.0 <= self.step_min_m <= self.step_max_m:
            raise ValueError(f"Limits: expected 0 <= step_min_m <= step_max_m, found {self.step_min_m} and {self.step_max_m}")
        if not self.z_min_m <= self.z_max_m:
            raise ValueError(f"Limits: expected z_min_m <= z_max_m, found {self.z_min_m} and {self.z_max_m}")
        if self.activation not in ("safe", "paper"):
            raise ValueError(f"Limits.activation: expected 'safe' or 'paper', found {self.activation!r}")

    @cached_property
    def turn_buffer_m(self) -> float:
        """Worst approach (m) of a drone turning away from a head-on course.

        s_max Σ_k max(0, cos(k α)) with α = min(φ_max, θ_max): the distance a drone still
        closes on a surface (or a peer) while its heading swings away at the maximum turn
        rate, at full speed (the safety filter keeps the step closest to the desired one,
        which is usually at v_max). Used by :func:`planner.control.control_step`.
        """
        alpha = min(self.heading_change_max_rad, self.tilt_change_max_rad)
        total = 0.0
        k = 1
        while alpha > 0.0 and k * alpha < 0.5 * math.pi:
            total += math.cos(k * alpha)
            k += 1
        return self.step_max_m * total

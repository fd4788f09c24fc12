"""The source's power offset and what it does to the paper's ranges (eqs. 3, 5), in the
units of :mod:`planner.radio.unknown_power`: b = 0 is the reference power the drones assume; a
source ΔP dB stronger has b = −ΔP ln 10/(10γ) and ranges that read e^b times the true distance.
Plain numpy (a payload process imports it)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

#: ln 10/10: nepers of amplitude per dB times 2 (10 log10 x = ln x / (ln 10/10)).
LN10_OVER_10: float = math.log(10.0) / 10.0


def offset_of_power_db(power_offset_db: float, gamma: float) -> float:
    """b of a source whose reference power is ``power_offset_db`` dB above the assumed one:
    b = −ΔP ln 10/(10γ) (its ranges read e^b times the true distance)."""
    return -float(power_offset_db) * LN10_OVER_10 / float(gamma)


def power_db_of_offset(b: NDArray[np.float64] | float, gamma: float) -> NDArray[np.float64]:
    """ΔP (dB) of power offsets b: the source's reference power above the assumed one,
    ΔP = −10γ b/ln 10 (the inverse of :func:`offset_of_power_db`)."""
    return -np.asarray(b, dtype=float) * (float(gamma) / LN10_OVER_10)


def offset_ranges(range_m: NDArray[np.float64], distance_m: NDArray[np.float64], b: float, gamma: float) -> NDArray[np.float64]:
    """The ranges of a source of power offset b from ranges d̂ drawn at offset 0 (eqs. 3, 5):
    d̂ = d + σ_r0 d^{γ/2} z becomes s + σ_r0 s^{γ/2} z with s = e^b d, i.e.
    e^b d + e^{bγ/2} (d̂ − d) (the same noise draw z). NaN ranges stay NaN. Metres."""
    if b == 0.0:
        return range_m
    d = np.asarray(distance_m, dtype=float)
    return math.exp(b) * d + math.exp(0.5 * b * gamma) * (np.asarray(range_m, dtype=float) - d)


__all__ = ["offset_of_power_db", "offset_ranges", "power_db_of_offset"]

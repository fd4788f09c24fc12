"""Observation model (eqs. 3-5): statistics over many draws, and determinism of the streams."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from planner import Channel, line_of_sight, observe, observe_from_uniforms, ranging_std
from planner.randomness import MEASUREMENT_DRAWS, MEASUREMENT_STREAM, measurement_rng, presampled_uniforms

CH = Channel(gamma=2.4, sigma_ratio_los=1.7, sigma_ratio_nlos=3.2, sigma_bearing_rad=math.radians(10.0))
M = 40000


def _draw(rng, positions, ranging, bearing, los, src=np.array([0.0, 0.0, 10.0])):
    n = len(positions)
    u = rng.random((M, n, MEASUREMENT_DRAWS))
    return observe_from_uniforms(src, positions, ranging, bearing, los, CH, u)


def test_ranging_std_formula():
    # σ_r0 = ln10/10 · σ_sh/γ (eq. 5), σ_r = σ_r0 d^(γ/2), written out by hand.
    d = np.array([1.0, 10.0, 100.0])
    np.testing.assert_allclose(ranging_std(d, True, CH), math.log(10) / 10 * 1.7 * d**1.2, rtol=1e-14)
    np.testing.assert_allclose(ranging_std(d, False, CH), math.log(10) / 10 * 3.2 * d**1.2, rtol=1e-14)


@pytest.mark.parametrize("los", [True, False])
def test_range_error_statistics(rng, los):
    src = np.array([0.0, 0.0, 10.0])
    positions = np.array([[3.0, 4.0, 10.0], [30.0, -40.0, 10.0], [-60.0, 80.0, 0.0]])  # d = 5, 50, ~100.5
    obs = _draw(rng, positions, [True] * 3, [False] * 3, [los] * 3, src)
    d = np.linalg.norm(src - positions, axis=1)
    err = obs.range_m - d
    sigma0 = math.log(10) / 10 * (1.7 if los else 3.2)
    expected_var = sigma0**2 * d**CH.gamma
    var = err.var(axis=0)
    # The sample variance of M normals has relative std sqrt(2/M) ~ 0.7 %: 4 % is > 5 sigma.
    np.testing.assert_allclose(var, expected_var, rtol=0.04)
    assert (np.abs(err.mean(axis=0)) < 5 * np.sqrt(expected_var / M)).all()
    for j in range(3):
        assert stats.kstest(err[:, j] / math.sqrt(expected_var[j]), "norm").pvalue > 1e-3
    assert np.isnan(obs.azimuth_rad).all() and np.isnan(obs.elevation_rad).all()


def test_bearing_error_statistics_in_los(rng):
    src = np.array([0.0, 0.0, 10.0])
    # One drone whose azimuth is near ±π (tests the wrap), one ordinary.
    positions = np.array([[50.0, 0.1, 5.0], [-20.0, -30.0, 20.0]])
    obs = _draw(rng, positions, [False, False], [True, True], [True, True], src)
    r = src - positions
    phi = np.arctan2(r[:, 1], r[:, 0])
    theta = np.arctan2(r[:, 2], np.hypot(r[:, 0], r[:, 1]))
    e_az = np.angle(np.exp(1j * (obs.azimuth_rad - phi)))
    e_el = obs.elevation_rad - theta
    sb = CH.sigma_bearing_rad
    np.testing.assert_allclose(e_az.std(axis=0), sb, rtol=0.03)
    np.testing.assert_allclose(e_el.std(axis=0), sb, rtol=0.03)
    assert (np.abs(obs.azimuth_rad) <= math.pi).all()
    for j in range(2):
        assert stats.kstest(e_az[:, j] / sb, "norm").pvalue > 1e-3
        assert stats.kstest(e_el[:, j] / sb, "norm").pvalue > 1e-3
    assert abs(np.corrcoef(e_az[:, 1], e_el[:, 1])[0, 1]) < 0.03
    assert np.isnan(obs.range_m).all()


def test_nlos_bearing_is_a_uniform_outlier(rng):
    positions = np.array([[50.0, 0.0, 5.0]])
    obs = _draw(rng, positions, [True], [True], [False])
    az, el = obs.azimuth_rad[:, 0], obs.elevation_rad[:, 0]
    assert stats.kstest(az, stats.uniform(-math.pi, 2 * math.pi).cdf).pvalue > 1e-3
    assert stats.kstest(el, stats.uniform(-math.pi / 2, math.pi).cdf).pvalue > 1e-3
    # Independent of the true direction: same law for a drone on the other side.
    other = _draw(rng, -positions, [True], [True], [False])
    assert stats.ks_2samp(az, other.azimuth_rad[:, 0]).pvalue > 1e-3
    # The NLOS range is still unbiased, with the NLOS variance.
    d = np.linalg.norm(positions[0] - [0, 0, 10])
    np.testing.assert_allclose(obs.range_m.var(), (math.log(10) / 10 * 3.2) ** 2 * d**CH.gamma, rtol=0.04)


def test_observe_per_step_equals_presampled(rng):
    """A payload drawing per step from its own stream equals the simulator's presampled block."""
    seed, trials, drones, steps = 1234, 2, 4, 6
    src = np.array([0.0, 100.0, 10.0])
    bmin, bmax = np.array([[-5.0, 40.0, 0.0]]), np.array([[5.0, 60.0, 30.0]])
    pos = rng.uniform([-30, 0, 2], [30, 80, 25], (steps, trials, drones, 3))
    pos[:, :, 0] = [0.0, 0.0, 10.0]  # drone 0 behind the obstacle: NLOS
    ranging = np.array([True, False, True, True])
    bearing = np.array([False, True, True, True])
    uni = presampled_uniforms(seed, trials, drones, steps, MEASUREMENT_STREAM, MEASUREMENT_DRAWS)
    assert uni.shape == (steps, trials, drones, MEASUREMENT_DRAWS)
    for m in range(trials):
        for i in range(drones):
            g = measurement_rng(seed, m, i)
            for k in range(steps):
                one = observe(src, pos[k, m, i][None], ranging[i : i + 1], bearing[i : i + 1], bmin, bmax, CH, g)
                los = line_of_sight(pos[k, m], src, bmin, bmax)
                block = observe_from_uniforms(src, pos[k, m], ranging, bearing, los, CH, uni[k, m])
                for f in ("range_m", "azimuth_rad", "elevation_rad", "los"):
                    np.testing.assert_array_equal(getattr(one, f)[0], getattr(block, f)[i], err_msg=f"{f} k={k} m={m} i={i}")
    assert not line_of_sight(pos[0, 0, :1], src, bmin, bmax)[0]
    # Different trials and drones get different streams.
    assert not np.allclose(uni[:, 0, 0], uni[:, 1, 0]) and not np.allclose(uni[:, 0, 0], uni[:, 0, 1])


def test_observe_is_deterministic_for_a_seed():
    src = np.array([0.0, 100.0, 10.0])
    pos = np.array([[10.0, 20.0, 5.0], [-10.0, 30.0, 8.0]])
    box = np.zeros((0, 3))
    a = observe(src, pos, [True, True], [True, False], box, box, CH, measurement_rng(7, 0, 1))
    b = observe(src, pos, [True, True], [True, False], box, box, CH, measurement_rng(7, 0, 1))
    c = observe(src, pos, [True, True], [True, False], box, box, CH, measurement_rng(7, 1, 1))
    np.testing.assert_array_equal(a.range_m, b.range_m)
    assert not np.array_equal(a.range_m, c.range_m)


def test_zero_uniform_gives_finite_measurement():
    obs = observe_from_uniforms([0, 0, 10.0], [[10.0, 0, 10.0]], [True], [True], [True], CH, np.zeros((1, 5)))
    assert np.isfinite(obs.range_m).all() and np.isfinite(obs.azimuth_rad).all() and np.isfinite(obs.elevation_rad).all()

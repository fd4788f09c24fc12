"""Simulated RSS payload: the paper's observation model at the vehicle's true position, with the
per-drone noise stream; expectations computed here from eqs. 3-5 and the uniform variates."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import ndtri

from planner.params import Channel
from planner.randomness import measurement_rng
from vehicle_sim.config import VehicleConfig
from vehicle_sim.payload import Measurement, Payload, PayloadWorld, roles_to_flags

from tests.vehicle_sim.memlink import memory_vehicle

CH = Channel(gamma=2.0, sigma_ratio_los=1.7, sigma_ratio_nlos=3.2, sigma_bearing_rad=math.radians(10))


def world(**kw) -> PayloadWorld:
    base = dict(
        source_position_m=(0.0, 0.0, 2.0),
        source_velocity_mps=(0.5, -0.25, 0.0),
        boxes_min_m=(),
        boxes_max_m=(),
        channel=CH,
        seed=17,
    )
    base.update(kw)
    return PayloadWorld(**base)


def expected_los(src, pos, u):
    """Eq. 3 in LOS from the five uniforms: d + σ_r0 d^(γ/2) z0, φ + σ_b z1, θ + σ_b z2, with
    φ, θ the direction of the source seen from the drone (paper Fig. 1)."""
    diff = np.asarray(src) - np.asarray(pos)
    d = float(np.linalg.norm(diff))
    s_r0 = math.log(10) / 10 * CH.sigma_ratio_los
    z = ndtri(np.clip(u[:3], 1e-300, None))
    rng_m = d + s_r0 * d ** (CH.gamma / 2) * z[0]
    az = math.atan2(diff[1], diff[0]) + CH.sigma_bearing_rad * z[1]
    az = math.atan2(math.sin(az), math.cos(az))
    el = math.asin(diff[2] / d) + CH.sigma_bearing_rad * z[2]
    return rng_m, az, el


def test_joint_measurement_matches_eq3_with_the_drone_stream_and_moving_source():
    w = world()
    pay = Payload(w, drone=3, sysid=4, ranging=True, bearing=True)
    u = measurement_rng(17, 0, 3).random((6, 5))
    pos = np.array([40.0, 120.0, 10.0])
    for step in (0, 1, 5):  # step 5 skips 2..4: their draws are consumed
        t = step * 1.0
        m = pay.measure(pos, step, t)
        src = np.array([0.0, 0.0, 2.0]) + t * np.array([0.5, -0.25, 0.0])
        r, az, el = expected_los(src, pos, u[step])
        assert m.los and m.step == step and m.sysid == 4 and m.drone == 3
        assert m.range_m == pytest.approx(r, rel=1e-12)
        assert m.azimuth_rad == pytest.approx(az, abs=1e-12)
        assert m.elevation_rad == pytest.approx(el, abs=1e-12)
    with pytest.raises(ValueError, match="already measured"):
        pay.measure(pos, 5, 5.0)


def test_roles_mask_the_missing_sensor_and_nlos_behind_a_box():
    w = world(source_velocity_mps=(0.0, 0.0, 0.0), boxes_min_m=((-10.0, 40.0, 0.0),), boxes_max_m=((10.0, 60.0, 30.0),))
    ranging = Payload(w, drone=0, ranging=True, bearing=False)
    bearing = Payload(w, drone=1, ranging=False, bearing=True)
    behind = np.array([0.0, 100.0, 10.0])  # the box sits between the drone and the source
    m_r = ranging.measure(behind, 0, 0.0)
    m_b = bearing.measure(behind, 0, 0.0)
    assert m_r.azimuth_rad is None and m_r.elevation_rad is None and m_r.range_m is not None
    assert m_b.range_m is None and m_b.azimuth_rad is not None
    assert not m_r.los and not m_b.los
    # NLOS ranging uses σ_sh/γ = 3.2: check against the uniforms of drone 0, step 0
    u = measurement_rng(17, 0, 0).random(5)
    d = float(np.linalg.norm(behind - np.array([0.0, 0.0, 2.0])))
    s_r0 = math.log(10) / 10 * 3.2
    assert m_r.range_m == pytest.approx(d + s_r0 * d * ndtri(u[0]), rel=1e-12)
    # NLOS bearing is the uniform outlier
    u1 = measurement_rng(17, 0, 1).random(5)
    assert m_b.azimuth_rad == pytest.approx(-math.pi + 2 * math.pi * u1[3])
    assert m_b.elevation_rad == pytest.approx(-math.pi / 2 + math.pi * u1[4])


def test_same_seed_same_record_and_json_round_trip():
    a = Payload(world(), drone=2).measure([10.0, 20.0, 5.0], 0, 0.0)
    b = Payload(world(), drone=2).measure([10.0, 20.0, 5.0], 0, 0.0)
    c = Payload(world(seed=18), drone=2).measure([10.0, 20.0, 5.0], 0, 0.0)
    assert a == b and a != c
    assert Measurement.from_json(a.to_json()) == a
    with pytest.raises(ValueError, match="schema"):
        Measurement.from_json(b'{"schema": 9}')
    with pytest.raises(ValueError, match="bad or missing field"):
        Measurement.from_json(b'{"schema": 1, "drone": 0}')


def test_vehicle_measures_at_its_true_position():
    v, _ = memory_vehicle(VehicleConfig(airborne=True, start_enu_m=(3.0, 4.0, 12.0), position_noise_m=5.0))
    v.payload = Payload(world(), drone=0)
    v.advance_to(2.0)
    m = v.measure(2)
    assert m.position_enu_m == (3.0, 4.0, 12.0)  # truth, not the noisy reported position
    assert m.t_s == 2.0


def test_roles_to_flags_and_bad_inputs():
    assert roles_to_flags("joint") == (True, True)
    with pytest.raises(ValueError, match="role"):
        roles_to_flags("sonar")
    with pytest.raises(ValueError, match="ranging, bearing or both"):
        Payload(world(), drone=0, ranging=False, bearing=False)
    with pytest.raises(ValueError, match="non-finite"):
        Payload(world(), drone=0).measure([np.nan, 0, 0], 0, 0.0)

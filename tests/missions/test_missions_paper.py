"""The paper's case-study missions (section V): they load, carry the paper's numbers, start on
the paper's ellipse, and the chosen buildings give the geometry docs/case-study-scenario.md
promises (checked with an independent sampling reference and, when present, planner.geometry)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from missions.loader import load_mission
from missions.schema import Ellipse, Mission
from planner.params import Channel, Limits

PAPER = Path(__file__).resolve().parents[2] / "missions" / "paper"
NAMES = ("ranging_los", "ranging_nlos", "bearing", "joint", "heterogeneous", "dynamic_source")


@pytest.fixture(scope="module", params=NAMES)
def mission(request: pytest.FixtureRequest) -> Mission:
    return load_mission(PAPER / f"{request.param}.yaml")


def test_every_paper_mission_file_is_listed() -> None:
    assert sorted(p.stem for p in PAPER.glob("*.yaml")) == sorted(NAMES)


def test_section_v_numbers(mission: Mission) -> None:
    assert mission.drones.count == 10
    assert mission.trials == 100
    assert mission.steps == 550
    assert mission.dt_s == 1.0
    assert mission.criterion == "A"
    c = mission.constraints
    assert (c.speed_min_mps, c.speed_max_mps) == (0.5, 1.0)
    assert (c.heading_change_max_deg, c.tilt_change_max_deg) == (50.0, 50.0)
    assert (c.d_uav_m, c.d_source_m, c.d_obstacle_m) == (1.0, 50.0, 5.0)
    assert (c.z_min_m, c.z_max_m) == (2.0, 25.0)
    ch = mission.channel
    assert (ch.sigma_ratio_los, ch.sigma_ratio_nlos, ch.sigma_bearing_deg) == (1.7, 3.2, 10.0)
    assert (mission.comms.d_hop_m, mission.comms.h_max) == (100.0, 1)
    e = mission.drones.start.ellipse
    assert e is not None and e.center_m == (0.0, 150.0, 8.0)
    assert (e.radius_x_m, e.radius_z_m, e.phase_deg) == (20.0, 5.0, 0.0)
    assert mission.source.position_m == (0.0, 0.0, 2.0)


def test_planner_parameters_in_si_and_radians(mission: Mission) -> None:
    limits = mission.limits()
    assert isinstance(limits, Limits)
    assert limits.step_min_m == pytest.approx(0.5) and limits.step_max_m == pytest.approx(1.0)
    assert limits.heading_change_max_rad == pytest.approx(50 * math.pi / 180)
    assert limits.tilt_change_max_rad == pytest.approx(50 * math.pi / 180)
    channel = mission.channel.to_planner()
    assert isinstance(channel, Channel)
    assert channel.sigma_bearing_rad == pytest.approx(math.pi / 18)
    assert channel.gamma == 2.0


def test_speeds_scale_with_dt() -> None:
    m = load_mission(PAPER / "joint.yaml", {"dt_s": 0.5})
    limits = m.limits()
    assert (limits.step_min_m, limits.step_max_m) == (0.25, 0.5)
    # turn limits are per step: they do not scale with dt
    assert limits.heading_change_max_rad == pytest.approx(math.radians(50))


@pytest.mark.parametrize(
    ("name", "ranging", "bearing"),
    [
        ("ranging_los", range(1, 11), ()),
        ("ranging_nlos", range(1, 11), ()),
        ("dynamic_source", range(1, 11), ()),
        ("bearing", (), range(1, 11)),
        ("joint", range(1, 11), range(1, 11)),
        ("heterogeneous", (1, 4, 7, 10, 3, 6, 9), (2, 5, 8, 3, 6, 9)),
    ],
)
def test_roles_and_masks(name: str, ranging: tuple[int, ...], bearing: tuple[int, ...]) -> None:
    m = load_mission(PAPER / f"{name}.yaml")
    expected_r = np.isin(np.arange(1, 11), list(ranging))
    expected_b = np.isin(np.arange(1, 11), list(bearing))
    np.testing.assert_array_equal(m.drones.ranging_mask(), expected_r)
    np.testing.assert_array_equal(m.drones.bearing_mask(), expected_b)
    assert m.drones.ranging_mask().dtype == bool and m.drones.ranging_mask().shape == (10,)


def test_heterogeneous_sets_match_the_paper() -> None:
    roles = load_mission(PAPER / "heterogeneous.yaml").drones.roles
    by_role = {r: {i + 1 for i, x in enumerate(roles) if x == r} for r in ("ranging", "bearing", "joint")}
    assert by_role == {"ranging": {1, 4, 7, 10}, "bearing": {2, 5, 8}, "joint": {3, 6, 9}}


def test_obstacles_per_configuration() -> None:
    assert load_mission(PAPER / "ranging_los.yaml").obstacles == ()
    mins, maxs = load_mission(PAPER / "ranging_los.yaml").obstacle_bounds()
    assert mins.shape == (0, 3) and maxs.shape == (0, 3) and mins.dtype == float
    for name in ("ranging_nlos", "bearing", "joint", "heterogeneous", "dynamic_source"):
        mins, maxs = load_mission(PAPER / f"{name}.yaml").obstacle_bounds()
        assert mins.shape == (3, 3) and np.all(mins < maxs)


def test_only_dynamic_source_moves() -> None:
    for name in NAMES:
        m = load_mission(PAPER / f"{name}.yaml")
        assert m.source.is_static == (name != "dynamic_source")
    m = load_mission(PAPER / "dynamic_source.yaml")
    np.testing.assert_allclose(m.source.position_at(0.0), [0.0, 0.0, 2.0])
    np.testing.assert_allclose(m.source.position_at(550.0), [27.5, 0.0, 2.0])
    np.testing.assert_allclose(m.source.position_at(100.0) - m.source.position_at(99.0), [0.05, 0.0, 0.0])


def test_criterion_d_by_override() -> None:
    m = load_mission(PAPER / "ranging_nlos.yaml", {"criterion": "D"})
    assert m.criterion == "D"
    assert m.model_copy() == m
    assert load_mission(PAPER / "ranging_nlos.yaml").criterion == "A"


# --- ellipse -------------------------------------------------------------------------------


def test_ellipse_against_closed_form() -> None:
    m = load_mission(PAPER / "ranging_los.yaml")
    p = m.drones.start_positions_m()
    assert p.shape == (10, 3)
    for i in range(10):  # drone i+1 at angle 36 i degrees from +x towards +z
        a = math.radians(36.0 * i)
        assert p[i] == pytest.approx([20.0 * math.cos(a), 150.0, 8.0 + 5.0 * math.sin(a)], abs=1e-12)
    # drone 1 at the east end; on the ellipse (x/rx)^2 + ((z-8)/rz)^2 = 1; y constant
    assert p[0] == pytest.approx([20.0, 150.0, 8.0])
    np.testing.assert_allclose((p[:, 0] / 20.0) ** 2 + ((p[:, 2] - 8.0) / 5.0) ** 2, 1.0)
    np.testing.assert_allclose(p[:, 1], 150.0)
    # drones 3 and 4 are the highest (72 and 108 degrees), within the altitude box
    assert set(np.argsort(p[:, 2])[-2:]) == {2, 3}
    assert p[:, 2].min() >= 2.0 and p[:, 2].max() <= 25.0


@pytest.mark.parametrize("count", [1, 2, 3, 7, 10, 50])
@pytest.mark.parametrize("phase_deg", [0.0, 90.0, -45.0])
def test_ellipse_generator_general(count: int, phase_deg: float) -> None:
    e = Ellipse(center_m=(1.0, -2.0, 10.0), radius_x_m=7.0, radius_z_m=3.0, phase_deg=phase_deg)
    p = e.positions_m(count)
    assert p.shape == (count, 3)
    angles = np.arctan2((p[:, 2] - 10.0) / 3.0, (p[:, 0] - 1.0) / 7.0)
    steps = np.mod(np.diff(np.concatenate([angles, angles[:1] + 2 * np.pi])), 2 * np.pi)
    if count > 1:
        np.testing.assert_allclose(steps, 2 * np.pi / count, atol=1e-9)
    assert math.isclose(math.remainder(angles[0] - math.radians(phase_deg), 2 * math.pi), 0.0, abs_tol=1e-9)
    np.testing.assert_allclose(p[:, 1], -2.0)


def test_start_positions_is_a_fresh_array() -> None:
    m = load_mission(PAPER / "joint.yaml")
    a = m.drones.start_positions_m()
    a[:] = 0.0
    assert m.drones.start_positions_m()[0, 0] == 20.0


# --- the scenario: independent geometry reference ------------------------------------------


def _segment_blocked(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray, samples: int = 4001) -> bool:
    """Reference: sample the segment densely and test each point against the box."""
    t = np.linspace(0.0, 1.0, samples)[:, None]
    pts = a + t * (b - a)
    return bool(np.any(np.all((pts > lo) & (pts < hi), axis=1)))


def _point_box_distance(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    """Reference: Euclidean distance from an outside point to a box (clamp)."""
    return float(np.linalg.norm(p - np.clip(p, lo, hi)))


def _scenario() -> tuple[Mission, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    m = load_mission(PAPER / "ranging_nlos.yaml")
    mins, maxs = m.obstacle_bounds()
    return m, m.drones.start_positions_m(), m.source.position_at(0.0), mins, maxs


def test_scenario_starts_keep_clear_of_buildings() -> None:
    m, starts, _src, mins, maxs = _scenario()
    margin = 10.0
    for p in starts:
        for lo, hi in zip(mins, maxs):
            assert _point_box_distance(p, lo, hi) >= m.constraints.d_obstacle_m + margin


def test_scenario_buildings_are_taller_than_the_altitude_box() -> None:
    m, _starts, _src, mins, maxs = _scenario()
    assert np.all(maxs[:, 2] > m.constraints.z_max_m) and np.all(mins[:, 2] <= 0.0)


def test_scenario_start_links_mix_los_and_nlos() -> None:
    _m, starts, src, mins, maxs = _scenario()
    blocked = np.array([any(_segment_blocked(p, src, lo, hi) for lo, hi in zip(mins, maxs)) for p in starts])
    # documented in docs/case-study-scenario.md: drones 1, 2, 5, 6, 7, 10 NLOS; 3, 4, 8, 9 LOS
    np.testing.assert_array_equal(np.flatnonzero(blocked) + 1, [1, 2, 5, 6, 7, 10])
    assert blocked.any() and (~blocked).any()


def test_scenario_nlos_on_the_way_and_on_the_keep_out_circle() -> None:
    """Half-way points and points on the d_S* circle also see mixed LOS/NLOS."""
    m, starts, src, mins, maxs = _scenario()
    def blocked(p: np.ndarray) -> bool:
        return any(_segment_blocked(p, src, lo, hi) for lo, hi in zip(mins, maxs))
    # straight south at 10 m altitude, x = -20 .. 20 m, y = 120 m: some links blocked by B1/B2
    row = [blocked(np.array([x, 120.0, 10.0])) for x in np.linspace(-20, 20, 9)]
    assert any(row) and not all(row)
    # on the keep-out circle (radius 55 m, z = 10 m): B3 shadows the north-west sector
    ring = [blocked(src + np.array([55 * math.cos(a), 55 * math.sin(a), 8.0])) for a in np.radians(np.arange(0, 360, 5))]
    assert any(ring) and not all(ring)
    nw = blocked(src + np.array([-55 * math.cos(math.radians(45)), 55 * math.sin(math.radians(45)), 8.0]))
    assert nw


def test_scenario_source_distance_and_b3_inside_keep_out() -> None:
    m, starts, src, mins, maxs = _scenario()
    assert np.all(np.linalg.norm(starts - src, axis=1) > 145.0)
    # B3's nearest point is 22.4 m from the source: inside the 50 m keep-out disc, it never blocks
    # a drone's path but shadows links from the north-west.
    assert _point_box_distance(src, mins[2], maxs[2]) == pytest.approx(math.hypot(10.0, 20.0) - 0.0, abs=0.01)


def test_scenario_against_planner_geometry() -> None:
    geometry = pytest.importorskip("planner.geometry")
    if not hasattr(geometry, "line_of_sight") or not hasattr(geometry, "distance_to_boxes"):
        pytest.skip("planner.geometry has no line_of_sight/distance_to_boxes yet")
    m, starts, src, mins, maxs = _scenario()
    los = np.asarray(geometry.line_of_sight(starts, src, mins, maxs))
    np.testing.assert_array_equal(np.flatnonzero(~los) + 1, [1, 2, 5, 6, 7, 10])
    d = np.asarray(geometry.distance_to_boxes(starts, mins, maxs))
    assert d.shape == (10,) and np.all(d >= m.constraints.d_obstacle_m + 10.0)

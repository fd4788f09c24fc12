"""The paper's case-study missions (section V): they load, carry the paper's numbers, start on
the paper's ellipse, and the chosen buildings give the geometry docs/case-study-scenario.md
promises (checked with an independent sampling reference and against planner.geometry)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from missions.format.loader import load_mission
from missions.format.schema import Ellipse, Mission
from planner import geometry
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
    d = np.array([[_point_box_distance(p, lo, hi) for lo, hi in zip(mins, maxs)] for p in starts])
    assert np.all(d >= m.constraints.d_obstacle_m + 25.0)
    # closed form: B1 (x -40..-10, y up to 115, z 0..30) is the nearest building of every start,
    # 35 m north of its face, plus the x offset for the starts east of x = -10
    x = starts[:, 0]
    np.testing.assert_allclose(d.min(axis=1), np.hypot(np.maximum(0.0, x + 10.0), 35.0), atol=1e-9)
    np.testing.assert_array_equal(d.argmin(axis=1), 0)
    assert d.min() == pytest.approx(35.0)


def test_scenario_buildings_are_taller_than_the_altitude_box() -> None:
    m, _starts, _src, mins, maxs = _scenario()
    assert np.all(maxs[:, 2] > m.constraints.z_max_m) and np.all(mins[:, 2] <= 0.0)


def _blocked_by(p: np.ndarray, src: np.ndarray, mins: np.ndarray, maxs: np.ndarray) -> list[int]:
    return [b for b, (lo, hi) in enumerate(zip(mins, maxs)) if _segment_blocked(p, src, lo, hi)]


def test_scenario_start_links_mix_los_and_nlos() -> None:
    _m, starts, src, mins, maxs = _scenario()
    by = [_blocked_by(p, src, mins, maxs) for p in starts]
    # documented in docs/case-study-scenario.md: drone 1 NLOS through B2, drones 5, 6, 7
    # through B1; 2, 3, 4, 8, 9, 10 LOS
    assert by == [[1], [], [], [], [0], [0], [0], [], [], []]


def _sector_blocked_at_y120(x: float) -> bool:
    """Closed form at y = 120 m: shadow edges are the lines from the source through B1's corner
    (-10, 115), B2's corners (10, 90) and (35, 70); west of B1 B3's sector continues the shadow."""
    return x <= 120.0 * -10.0 / 115.0 or 120.0 * 10.0 / 90.0 <= x <= 120.0 * 35.0 / 70.0


def test_scenario_nlos_on_the_way() -> None:
    """Points between the formation and the circle see mixed LOS/NLOS; the lane between B1 and
    B2 is LOS, the outer routes around them are shadowed down to a closed-form y."""
    m, _starts, src, mins, maxs = _scenario()
    def blocked(p: np.ndarray) -> bool:
        return bool(_blocked_by(p, src, mins, maxs))
    xs = np.arange(-62.5, 70.0, 5.0)  # avoids the shadow edges by >= 0.8 m
    row = [blocked(np.array([x, 120.0, 10.0])) for x in xs]
    assert row == [_sector_blocked_at_y120(x) for x in xs]
    assert any(row) and not all(row)
    # B1 ends at x = -10, B2 starts at x = 10: a 20 m gap
    assert mins[1, 0] - maxs[0, 0] == pytest.approx(20.0)
    ys = np.arange(1.25, 150.0, 2.5)  # never on a shadow edge (y = 30, 80)
    d_o = m.constraints.d_obstacle_m
    # central lane x = 0, down to the keep-out circle: LOS all the way, clear of every building
    lane = [np.array([0.0, y, 10.0]) for y in ys if y > 50.0]
    assert not any(blocked(p) for p in lane)
    assert all(min(_point_box_distance(p, lo, hi) for lo, hi in zip(mins, maxs)) >= d_o for p in lane)
    # east route x = 40 (d_O* off B2's east face): NLOS by B2 while y > 40 * 70 / 35 = 80
    east = [blocked(np.array([40.0, y, 10.0])) for y in ys]
    assert east == [bool(y > 80.0) for y in ys]
    # west route x = -45 (d_O* off B1's west face): NLOS (B1, then B3) while y > 45 * 12 / 18 = 30
    west = [blocked(np.array([-45.0, y, 10.0])) for y in ys]
    assert west == [bool(y > 30.0) for y in ys]


@pytest.mark.parametrize("radius", [50.0, 55.0])
@pytest.mark.parametrize("z", [2.0, 10.0, 25.0])
def test_scenario_b3_shadows_a_north_west_arc(radius: float, z: float) -> None:
    """On the keep-out circle only B3 blocks, over azimuths atan2(24, -8) .. atan2(12, -18)
    (108.4 .. 146.3 deg seen from the source), at every flight altitude."""
    _m, _starts, src, mins, maxs = _scenario()
    lo_az, hi_az = math.degrees(math.atan2(24.0, -8.0)), math.degrees(math.atan2(12.0, -18.0))
    assert (lo_az, hi_az) == (pytest.approx(108.43, abs=0.01), pytest.approx(146.31, abs=0.01))
    for az in np.arange(0.0, 360.0, 1.0):  # integer degrees: >= 0.3 deg from both edges
        a = math.radians(az)
        p = np.array([src[0] + radius * math.cos(a), src[1] + radius * math.sin(a), z])
        assert _blocked_by(p, src, mins, maxs) == ([2] if lo_az < az < hi_az else []), az


def test_scenario_source_distance_and_b3_inside_keep_out() -> None:
    m, starts, src, mins, maxs = _scenario()
    assert np.all(np.linalg.norm(starts - src, axis=1) > 145.0)
    d_s, d_o = m.constraints.d_source_m, m.constraints.d_obstacle_m
    # B3's nearest point (-8, 12) is 14.4 m from the source, its farthest corner (-18, 24) 30 m
    # horizontally: even at the safe rule's activation distance (d_O* + 0.5 v_max dt + turn
    # buffer + 2 v_max dt, about 8 m) it stays > 10 m inside the keep-out disc, so it never
    # blocks a path or narrows the circle.
    limits = m.limits()
    activation = d_o + 2.5 * limits.step_max_m + limits.turn_buffer_m
    assert 7.5 <= activation <= 9.0
    assert _point_box_distance(src, mins[2], maxs[2]) == pytest.approx(math.hypot(8.0, 12.0), abs=1e-9)
    corners = np.array([[x, y] for x in (mins[2, 0], maxs[2, 0]) for y in (mins[2, 1], maxs[2, 1])])
    far = np.linalg.norm(corners - src[:2], axis=1).max()
    assert far == pytest.approx(30.0) and far + activation < d_s - 10.0
    # B2 (nearest corner (10, 70)) and B1 (nearest corner (-10, 95)) stay well outside the circle
    assert _point_box_distance(src, mins[1], maxs[1]) == pytest.approx(math.hypot(10.0, 70.0), abs=1e-9)
    assert _point_box_distance(src, mins[0], maxs[0]) == pytest.approx(math.hypot(10.0, 95.0), abs=1e-9)
    assert math.hypot(10.0, 70.0) - d_s > 20.0


def test_scenario_dynamic_source_path_clear_of_buildings() -> None:
    m = load_mission(PAPER / "dynamic_source.yaml")
    mins, maxs = m.obstacle_bounds()
    path = [m.source.position_at(t) for t in np.linspace(0.0, m.steps * m.dt_s, 111)]
    d = min(_point_box_distance(p, lo, hi) for p in path for lo, hi in zip(mins, maxs))
    assert d == pytest.approx(math.hypot(8.0, 12.0), abs=1e-9)  # at t = 0, to B3's corner (-8, 12)


def test_scenario_against_planner_geometry() -> None:
    m, starts, src, mins, maxs = _scenario()
    los = np.asarray(geometry.line_of_sight(starts, src, mins, maxs))
    np.testing.assert_array_equal(np.flatnonzero(~los) + 1, [1, 5, 6, 7])
    d = np.asarray(geometry.distance_to_boxes(starts, mins, maxs))
    assert d.shape == (10,) and np.all(d >= m.constraints.d_obstacle_m + 25.0)
    np.testing.assert_allclose(d, np.hypot(np.maximum(0.0, starts[:, 0] + 10.0), 35.0), atol=1e-9)
    # the shadow arc of B3 on the circle and the y = 120 m row agree with the sampling reference
    az = np.radians(np.arange(0.0, 360.0, 1.0))
    ring = np.stack([50.0 * np.cos(az), 50.0 * np.sin(az), np.full_like(az, 8.0)], axis=-1) + src
    ring_ref = [bool(_blocked_by(p, src, mins, maxs)) for p in ring]
    np.testing.assert_array_equal(~np.asarray(geometry.line_of_sight(ring, src, mins, maxs)), ring_ref)
    xs = np.arange(-62.5, 70.0, 5.0)
    row = np.stack([xs, np.full_like(xs, 120.0), np.full_like(xs, 10.0)], axis=-1)
    np.testing.assert_array_equal(~np.asarray(geometry.line_of_sight(row, src, mins, maxs)), [_sector_blocked_at_y120(x) for x in xs])

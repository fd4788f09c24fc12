"""The baseline navigation policies (planner/policies.py) in the in-process simulator, each on a
reduced mission against a closed form or an obvious property: static never moves, orbit keeps
its radius and spacing, random walks under the safety rules, centralized equals the planner
when the planner's view has no latency and reaches everyone."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from comms.errors import UsageError
from missions.cli.main import main
from missions.format.loader import MissionError, load_mission, parse_overrides
from missions.launch.launcher import _check_options
from missions.study.simulator import SAFETY_FAMILIES, RunSpec, simulate
from planner.policies import ORBIT_MARGIN_STEPS, POLICIES, random_walk_direction


def _run(policy: str, sets: list[str], trials: int, steps: int, oracle: bool = False, mission: str = "paper/joint") -> object:
    m = load_mission(mission, parse_overrides([f"policy={policy}", *sets]))
    return simulate(RunSpec(m, "A", trials, steps), oracle_estimate=oracle)


def test_static_never_moves() -> None:
    """Every drone of every trial at its start at every step; holding is below v_min, so every
    drone-step counts in the speed family and in no other."""
    r = _run("static", [], 3, 30)
    start = load_mission("paper/joint").drones.start_positions_m()
    assert np.array_equal(r.positions_m, np.broadcast_to(start, r.positions_m.shape))
    v = r.violations()
    assert v["speed"] == 3 * 30 * 10 and all(v[f] == 0 for f in SAFETY_FAMILIES if f != "speed")
    assert np.isfinite(r.peb_m).all() and r.estimate_error_m[-1].mean() < r.estimate_error_m[0].mean()  # the estimators still run


def test_orbit_keeps_its_radius_and_spacing() -> None:
    """With the true source and no building: after the approach every drone is on the
    horizontal circle of radius d_S* + 3 v_max Δt about the source (within 0.3 m), at its start
    altitude, the drones 360°/N apart."""
    sets = ["obstacles=[]", "drones.count=5", "drones.start.ellipse.center_m=[0,80,8]", "drones.start.ellipse.radius_x_m=10"]
    r = _run("orbit", sets, 1, 360, oracle=True)
    m = r.spec.mission
    radius = m.constraints.d_source_m + ORBIT_MARGIN_STEPS * m.constraints.speed_max_mps * m.dt_s
    src = np.asarray(m.source.position_m)
    circling = r.positions_m[200:, 0]  # (K', N, 3): every drone on its circle by step 200 ...
    d = np.hypot(circling[..., 0] - src[0], circling[..., 1] - src[1])
    assert np.abs(d - radius).max() < 0.3, (d.min(), d.max())
    z0 = m.drones.start_positions_m()[:, 2]
    assert np.abs(circling[..., 2] - np.maximum(z0, m.constraints.z_min_m)).max() < 0.5
    late = r.positions_m[340:, 0]  # ... and on its slot by step 340
    angles = np.sort(np.degrees(np.arctan2(late[-1, :, 1] - src[1], late[-1, :, 0] - src[0])) % 360.0)
    gaps = np.diff(np.append(angles, angles[0] + 360.0))
    assert np.abs(gaps - 72.0).max() < 1.0, gaps
    assert all(v == 0 for v in r.violations().values())


def test_random_walks_at_top_speed_under_the_safety_rules() -> None:
    """The paper's joint swarm with buildings: no violation in any family, steps at v_max unless
    the filter shortened them, a walk that turns (not a straight line), deterministic for the
    seed and different between trials."""
    r = _run("random", [], 2, 120)
    assert all(v == 0 for v in r.violations().values()), r.violations()
    u = np.diff(r.positions_m, axis=0)
    length = np.linalg.norm(u, axis=-1)
    assert np.median(length) == pytest.approx(1.0, abs=1e-9)
    straightness = np.linalg.norm(u.sum(0), axis=-1) / length.sum(0)
    assert straightness.max() < 0.9
    again = _run("random", [], 2, 120)
    assert np.array_equal(again.positions_m, r.positions_m)
    assert not np.array_equal(r.positions_m[:, 0], r.positions_m[:, 1])


def test_random_directions_are_uniform_on_the_sphere() -> None:
    """Closed form: unit length; the mean of each coordinate 0 and of its square 1/3."""
    u = np.random.default_rng(3).random((200_000, 2))
    d = random_walk_direction(u)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(d.mean(0), 0.0, atol=0.01)
    np.testing.assert_allclose((d * d).mean(0), 1.0 / 3.0, atol=0.01)


def test_centralized_equals_the_planner_without_latency_or_hop_limit() -> None:
    """A radio range that reaches everyone in one hop: the planner's records are of the current
    step (one hop, no latency), so its run equals the centralized one to 1e-9 m. With a short
    range (a row's neighbours only) the two differ: the centralized view is not the planner's."""
    far = ["comms.d_hop_m=100000"]
    a, b = _run("fim", far, 2, 40), _run("centralized", far, 2, 40)
    assert np.abs(a.positions_m - b.positions_m).max() <= 1e-9
    assert np.abs(a.estimates_m - b.estimates_m).max() <= 1e-9
    assert np.array_equal(a.peb_m, b.peb_m) or np.abs(a.peb_m - b.peb_m).max() <= 1e-9
    near = ["comms.d_hop_m=6", "drones.count=6", "drones.start.rows.spacing_m=5"]
    c, d = _run("fim", near, 1, 15), _run("centralized", near, 1, 15)
    assert np.abs(c.positions_m - d.positions_m).max() > 1e-3
    assert (c.record_ages >= 0).sum() < (d.record_ages >= 0).sum()


def test_a_policy_is_a_mission_key_and_an_option(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(MissionError, match=r"policy: expected 'fim', 'static', 'orbit', 'random' or 'centralized', found 'circle'"):
        load_mission("paper/joint", {"policy": "circle"})
    base = ["montecarlo", "paper/joint", "--trials", "1", "--steps", "2", "--no-figures"]
    assert main([*base, "--policy", "fim,circle", "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "--policy: expected policies among fim, static, orbit, random, centralized (or all), found 'circle'" in err and err.count("\n") == 1
    assert main([*base, "--policy", "all", "--out", str(tmp_path / "all")]) == 0
    assert sorted(p.name for p in (tmp_path / "all" / "runs").iterdir()) == sorted(
        "paper_joint_A" + ("" if p == "fim" else f"_{p}") for p in POLICIES
    )


def test_launch_flies_the_planner_only() -> None:
    with pytest.raises(UsageError, match="policy: 'orbit' is a baseline of fimnav montecarlo and fimnav sweep"):
        _check_options(load_mission("paper/joint", {"policy": "orbit"}), 10, "continue", False, 1.0)

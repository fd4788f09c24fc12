"""planner.placement: the optimal placement of a swarm against a closed form and against the
independent L-BFGS-B reference of tests/simulator/test_simulator.py; its constraints, its LOS
and its determinism. Few starts each: the whole file runs in a few seconds."""

from __future__ import annotations

import math

import numpy as np
import pytest

from planner.fim import fisher_information
from planner.geometry import distance_to_boxes, line_of_sight
from planner.params import Channel, Limits
from planner.placement import FEASIBILITY_TOL_M, PlacementBounds, optimal_placement, placement_bounds
from tests.simulator.conftest import paper_mission


def _mission_optimum(name: str, rule: str = "filter", buildings: bool = True, starts: int = 2, seed: int = 0, criterion: str = "A"):
    m = paper_mission(name)
    bmin, bmax = m.obstacle_bounds() if buildings else (np.zeros((0, 3)), np.zeros((0, 3)))
    return optimal_placement(
        m.source.position_m, m.drones.ranging_mask(), m.drones.bearing_mask(), m.channel.to_planner(),
        placement_bounds(m.limits(), rule), bmin, bmax, criterion, starts=starts, seed=seed,
    ), m


@pytest.mark.parametrize("criterion", ["A", "D"])
@pytest.mark.parametrize("n", [4, 6])
def test_ranging_only_regular_arrangement_closed_form(n: int, criterion: str) -> None:
    """N ranging drones in LOS at distance ≥ R, no altitude limit: J = A_r(R) Σ a_j a_jᵀ with
    unit a_j, tr Σ a aᵀ = N, so tr J⁻¹ ≥ 9/(N A_r) and det J ≤ (N A_r/3)³, both with equality
    for a tight frame Σ a aᵀ = (N/3) I (a regular tetrahedron, an octahedron): the optimal PEB
    is sqrt(9/(N A_r(R))), A_r(d) = 1/(σ_r0² d^γ) + γ²/(2 d²) (eq. 12), for A and D alike."""
    ch = Channel(gamma=2.5)
    R = 30.0
    bounds = PlacementBounds(source_m=R, uav_m=1.0, obstacle_m=0.0, z_min_m=-1e3, z_max_m=1e3)
    src = np.array([5.0, -3.0, 10.0])
    p = optimal_placement(src, np.ones(n, bool), np.zeros(n, bool), ch, bounds, criterion=criterion, starts=2, seed=3)
    a_r = 1.0 / (ch.sigma_r0_los**2 * R**ch.gamma) + ch.gamma**2 / (2.0 * R * R)
    assert p.peb_m == pytest.approx(math.sqrt(9.0 / (n * a_r)), rel=1e-5)
    np.testing.assert_allclose(p.distances_m, R, atol=1e-6)
    if criterion == "D":
        assert p.cost == pytest.approx(-3.0 * math.log(n * a_r / 3.0), rel=1e-7)
    u = (p.positions_m - src) / R
    np.testing.assert_allclose(u.T @ u, (n / 3.0) * np.eye(3), atol=1e-3)


# The heterogeneous case takes 20 s: in the slow set, to keep the default run under 5 minutes.
@pytest.mark.parametrize("name", ["joint", pytest.param("heterogeneous", marks=pytest.mark.slow)])
def test_agrees_with_the_independent_reference(name: str) -> None:
    """In LOS (no buildings) at distance ≥ d_S* in the altitude box (rule "none"), the product's
    optimum is the L-BFGS-B reference's (test_simulator.py, azimuth and altitude on the d_S*
    sphere, no inter-drone distance) within 0.5 % (docs/case-study.md: 5.21 m, 6.67 m)."""
    from tests.simulator.test_simulator import _optimal_peb_at_keepout

    p, m = _mission_optimum(name, rule="none", buildings=False)
    ref = _optimal_peb_at_keepout(name, starts=2)
    assert p.peb_m == pytest.approx(ref, rel=5e-3)
    assert p.los.all()
    assert {"joint": 5.21, "heterogeneous": 6.67}[name] == pytest.approx(p.peb_m, abs=0.01)


def test_constraints_hold_and_the_reported_peb_is_the_placement_s() -> None:
    """With buildings and the default rule's distances: every distance checked here from the
    returned positions (its own code), the LOS flags are the slab test's, the PEB is
    sqrt(tr J⁻¹) of those positions, and no drone is left in a shadow (NLOS only costs)."""
    p, m = _mission_optimum("heterogeneous")
    b = p.bounds
    lim = m.limits()
    assert b.source_m == pytest.approx(lim.d_source_m + 1.5 + lim.turn_buffer_m)
    pos = p.positions_m
    src = np.asarray(m.source.position_m)
    bmin, bmax = m.obstacle_bounds()
    tol = FEASIBILITY_TOL_M
    assert (np.linalg.norm(pos - src, axis=-1) >= b.source_m - tol).all()
    pair = np.linalg.norm(pos[:, None] - pos[None], axis=-1)[np.triu_indices(len(pos), 1)]
    assert (pair >= b.uav_m - tol).all()
    assert (distance_to_boxes(pos, bmin, bmax) >= b.obstacle_m - tol).all()
    assert ((pos[:, 2] >= b.z_min_m - tol) & (pos[:, 2] <= b.z_max_m + tol)).all()
    assert min(p.margins_m.values()) >= -tol
    los = line_of_sight(pos, src, bmin, bmax)
    np.testing.assert_array_equal(p.los, los)
    assert los.all()
    J = fisher_information(src, pos, m.drones.ranging_mask(), m.drones.bearing_mask(), los, m.channel.to_planner())
    assert p.peb_m == pytest.approx(math.sqrt(np.trace(np.linalg.inv(J))), rel=1e-12)
    # The rule's margins cost accuracy: the optimum at d_S* + 2.14 m is above the bare one.
    assert p.peb_m > 6.67


def test_a_shadowed_placement_is_worse_and_avoided() -> None:
    """A wall 20 m from a source blocks half the azimuths: bearing-only drones all end in LOS,
    and the same placement counted with its links NLOS would be singular (no bearing)."""
    ch = Channel()
    src = np.array([0.0, 0.0, 2.0])
    bmin, bmax = np.array([[-100.0, 20.0, 0.0]]), np.array([[100.0, 25.0, 60.0]])
    bounds = PlacementBounds(source_m=50.0, uav_m=1.0, obstacle_m=5.0, z_min_m=2.0, z_max_m=25.0)
    n = 5
    p = optimal_placement(src, np.zeros(n, bool), np.ones(n, bool), ch, bounds, bmin, bmax, starts=2, seed=1)
    assert p.los.all()
    assert (p.positions_m[:, 1] < 20.0).all()
    # Without the wall the swarm could use every azimuth: its optimum is no worse.
    free = optimal_placement(src, np.zeros(n, bool), np.ones(n, bool), ch, bounds, starts=2, seed=1)
    assert free.peb_m <= p.peb_m * (1.0 + 1e-6)


def test_deterministic_for_a_seed() -> None:
    a, _ = _mission_optimum("ranging_los", starts=2, seed=5)
    b, _ = _mission_optimum("ranging_los", starts=2, seed=5)
    c, _ = _mission_optimum("ranging_los", starts=2, seed=6)
    np.testing.assert_array_equal(a.positions_m, b.positions_m)
    np.testing.assert_array_equal(a.start_costs, b.start_costs)
    assert a.peb_m == b.peb_m
    assert not np.array_equal(a.positions_m, c.positions_m)
    assert c.peb_m == pytest.approx(a.peb_m, rel=1e-4)  # the same optimum from other starts


def test_placement_bounds_follow_the_rule() -> None:
    lim = Limits()  # the paper's section V values
    b = lim.turn_buffer_m
    f = placement_bounds(lim)
    assert (f.source_m, f.uav_m, f.obstacle_m, f.z_min_m, f.z_max_m) == pytest.approx((51.5 + b, 2.0 + 2 * b, 5.5 + b, 2.0, 25.0))
    assert placement_bounds(lim, oracle_estimate=True).source_m == pytest.approx(50.0 + b)
    h = placement_bounds(lim, "hold")
    assert (h.source_m, h.z_min_m, h.z_max_m) == pytest.approx((53.5 + b, 4.0 + b, 23.0 - b))
    # The true source, static: one step of the drone's own motion, and one level step's climb
    # at the tilt change limit inside each face; moving: the estimate's margins.
    climb = math.sin(math.radians(50.0))
    ho = placement_bounds(lim, "hold", oracle_estimate=True)
    assert (ho.source_m, ho.z_min_m, ho.z_max_m) == pytest.approx((51.0 + b, 2.0 + climb, 25.0 - climb))
    hm = placement_bounds(lim, "hold", oracle_estimate=True, source_slow=False)
    assert (hm.source_m, hm.z_min_m, hm.z_max_m) == pytest.approx((52.0 + b, 4.0 + b, 23.0 - b))
    n = placement_bounds(lim, "none")
    assert (n.source_m, n.uav_m, n.obstacle_m, n.z_min_m, n.z_max_m) == (50.0, 1.0, 5.0, 2.0, 25.0)
    paper = Limits(activation="paper")
    assert placement_bounds(paper, "hold").source_m == 51.5
    with pytest.raises(ValueError):
        placement_bounds(lim, "other")  # type: ignore[arg-type]


def test_bad_arguments() -> None:
    bounds = PlacementBounds(50.0, 1.0, 5.0, 2.0, 25.0)
    with pytest.raises(ValueError):
        optimal_placement(np.zeros(3), np.ones(3, bool), np.ones(2, bool), Channel(), bounds)
    with pytest.raises(ValueError):
        optimal_placement(np.zeros(3), np.ones(3, bool), np.ones(3, bool), Channel(), bounds, starts=0)
    with pytest.raises(ValueError):
        PlacementBounds(50.0, 1.0, 5.0, 25.0, 2.0)

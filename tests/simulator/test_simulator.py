"""The in-process simulator against the paper's findings (reduced trials and steps), against
independent references (hop counts from scipy, per-trial runs) and for determinism.

Full-size figures (100 trials x 550 steps) are in docs/case-study.md.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse.csgraph import shortest_path

from missions.study.simulator import RunSpec, simulate
from tests.simulator.conftest import paper_mission


def _tail_median(values: np.ndarray, n: int = 30) -> float:
    return float(np.median(values[-n:]))


def test_same_seed_same_records() -> None:
    m = paper_mission("heterogeneous")
    a = simulate(RunSpec(m, "A", 2, 40))
    b = simulate(RunSpec(m, "A", 2, 40))
    np.testing.assert_array_equal(a.positions_m, b.positions_m)
    np.testing.assert_array_equal(a.estimates_m, b.estimates_m)
    np.testing.assert_array_equal(a.peb_m, b.peb_m)
    for name in a.margins_m:
        np.testing.assert_array_equal(a.margins_m[name], b.margins_m[name])


def test_other_seed_other_noise() -> None:
    a = simulate(RunSpec(paper_mission("heterogeneous"), "A", 1, 20))
    b = simulate(RunSpec(paper_mission("heterogeneous", seed=7), "A", 1, 20))
    assert not np.array_equal(a.estimates_m, b.estimates_m)


@pytest.mark.parametrize("memory_cells", [0, 256])
def test_trial_does_not_depend_on_batch_size(memory_cells: int) -> None:
    """Trial m draws from its own streams: trial 0 alone equals trial 0 of a batch of 3, also
    with the range memory (whose cell sums must not depend on how many cells the batch's other
    trials occupy)."""
    m = paper_mission("ranging_nlos", **{"estimator.range_memory_cells": memory_cells})
    one = simulate(RunSpec(m, "D", 1, 30))
    three = simulate(RunSpec(m, "D", 3, 30))
    np.testing.assert_allclose(one.positions_m[:, 0], three.positions_m[:, 0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(one.estimates_m[:, 0], three.estimates_m[:, 0], rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", ["ranging_los", "joint", "heterogeneous"])
def test_peb_decreases(reduced_run, name: str) -> None:
    """Paper Fig. 3: the mean PEB falls over the steps (here to below half its start)."""
    stats = reduced_run(name, "A", 3, 300).peb_stats()
    start = stats["mean"][0]
    end = _tail_median(stats["mean"])
    assert np.isfinite(start) and np.isfinite(end)
    assert end < 0.5 * start, f"{name}: PEB {start:.1f} m at k=0, {end:.1f} m at the end"


def _optimal_peb_at_keepout(name: str, starts: int = 6) -> float:
    """The smallest PEB (eq. 18, all ten records, LOS) any placement of the mission's ten
    drones at distance ≥ d_S* from the source can have: every FIM term shrinks with distance, so
    the optimum has every drone at d_S*; its azimuths and altitudes (z_min..z_max) are optimised
    by L-BFGS-B from several random starts (an independent reference: no planner involved)."""
    from scipy.optimize import minimize

    from planner.fim import fisher_information

    m = paper_mission(name)
    ch = m.channel.to_planner()
    rng_m, brg_m = m.drones.ranging_mask(), m.drones.bearing_mask()
    src = np.asarray(m.source.position_m, dtype=float)
    d_s, n = m.constraints.d_source_m, m.drones.count
    lim = m.limits()

    def trace_inv(x: np.ndarray) -> float:
        z = x[n:]
        rho = np.sqrt(np.maximum(d_s**2 - (z - src[2]) ** 2, 0.0))
        p = np.stack([src[0] + rho * np.cos(x[:n]), src[1] + rho * np.sin(x[:n]), z], -1)
        J = fisher_information(src, p, rng_m, brg_m, np.ones(n, dtype=bool), ch)
        return float(np.trace(np.linalg.inv(J)))

    gen = np.random.default_rng(0)
    best = np.inf
    for _ in range(starts):
        x0 = np.concatenate([gen.uniform(0.0, 2.0 * np.pi, n), gen.uniform(lim.z_min_m, lim.z_max_m, n)])
        r = minimize(trace_inv, x0, method="L-BFGS-B", bounds=[(None, None)] * n + [(lim.z_min_m, lim.z_max_m)] * n)
        best = min(best, r.fun)
    return float(np.sqrt(best))


def test_heterogeneous_close_to_joint(reduced_run) -> None:
    """Paper Sec. V: with heterogeneous UAVs "the performance in terms of localization accuracy
    is similar to that obtainable with UAVs acquiring both ranging and bearing information".

    The paper gives no number for "similar"; this test measures it against what the sensors
    allow. Six of the heterogeneous swarm's ten drones sense bearings (ten in the joint swarm):
    at k = 0, same positions, its PEB is already 1.21x the joint swarm's, and even its best
    placement at d_S* has a PEB 1.28x the best joint placement's (computed here; the ratio
    depends on σ_b = 10°, σ_sh/γ = 1.7 in LOS, d_S* = 50 m, N = 10 and the 6-of-10 bearing
    mix, and barely on γ). The simulated heterogeneous/joint ratio may exceed that optimum by
    at most 5 % (the full run gives 1.28 over its second half, docs/case-study.md): both swarms
    end near their optimal placements, with no drone left in a building's shadow."""
    het = reduced_run("heterogeneous", "A", 3, 300).peb_stats()["mean"]
    joint = reduced_run("joint", "A", 3, 300).peb_stats()["mean"]
    ratio = float(np.median(het[150:] / joint[150:]))
    best = _optimal_peb_at_keepout("heterogeneous") / _optimal_peb_at_keepout("joint")
    assert best > 1.25, f"the optimum ratio {best:.3f}, expected 1.28 with the section V parameters (docs/case-study.md)"
    assert ratio <= 1.05 * best, f"heterogeneous / joint PEB {ratio:.3f}, optimal placements {best:.3f}"
    assert het[0] / joint[0] == pytest.approx(1.21, abs=0.02)


def test_a_optimality_beats_d_with_obstacles(reduced_run) -> None:
    """Paper Sec. V: in NLOS (buildings), A-optimality gives a PEB no higher than D for most of
    the steps (ranging swarm; for bearing, joint and heterogeneous swarms the two criteria end
    within a few per cent of each other, docs/case-study.md)."""
    a = reduced_run("ranging_nlos", "A", 3, 300).peb_stats()["mean"]
    d = reduced_run("ranging_nlos", "D", 3, 300).peb_stats()["mean"]
    assert np.mean(a <= d) > 0.5, f"A <= D on {np.mean(a <= d):.0%} of the steps"


def test_bearing_only_survives_singular_fim(tmp_path) -> None:
    """Bearing-only with buildings: J becomes singular (every bearing NLOS) and the drones keep
    moving (random-perturbation fallback), with no NaN anywhere.

    From the paper's ellipse the planning FIM's predicted LOS (docs/control.md) now keeps the
    swarm out of a fully shadowed view (no singular step in 10 trials × 300 steps), so the swarm
    starts here with every drone in B1's shadow, 130 m north of the source."""
    start = [[x, 130.0, z] for z in (5.0, 15.0) for x in (-30.0, -26.5, -23.0, -19.5, -16.0)]
    import yaml

    from missions.format.loader import load_mission
    from tests.simulator.conftest import PAPER

    doc = yaml.safe_load((PAPER / "bearing.yaml").read_text())
    doc["drones"]["start"] = {"positions_m": start}
    (tmp_path / "shadowed.yaml").write_text(yaml.safe_dump(doc))
    r = simulate(RunSpec(load_mission(tmp_path / "shadowed.yaml"), "A", 3, 300))
    stats = r.peb_stats()
    assert np.isinf(r.peb_m[0]).all(), "expected every view singular at k = 0"
    assert stats["singular_fraction"].max() > 0.0, "expected singular FIMs in the bearing-only case"
    assert r.singular_fallback.any()
    assert np.isfinite(r.positions_m).all() and np.isfinite(r.estimates_m).all()
    speed = np.linalg.norm(np.diff(r.positions_m, axis=0), axis=-1)
    limits = r.spec.mission.limits()
    assert speed.min() >= limits.step_min_m - 1e-9
    # While singular, the drones still move at least v_min per step.
    moving = speed[r.singular_fallback]
    assert moving.size and moving.min() >= limits.step_min_m - 1e-9


@pytest.mark.parametrize("name", ["ranging_nlos", "joint", "heterogeneous", "bearing", "dynamic_source"])
def test_safe_rule_has_no_violation(reduced_run, name: str) -> None:
    """The default constraint rule keeps every safety distance and limit (true positions)."""
    r = reduced_run(name, "A", 3, 300)
    assert r.spec.mission.constraints.activation == "safe"
    assert r.violations() == {k: 0 for k in r.margins_m}, r.violations()


def test_record_ages_follow_hop_counts() -> None:
    """With a small d_hop, drone i holds peer j's record of step max(saved, k − h_ij + 1) when
    h_ij <= h_max (hop counts recomputed here with scipy), else keeps the record it saved."""
    m = paper_mission("ranging_los", **{"comms.d_hop_m": 12.0, "comms.h_max": 3})
    r = simulate(RunSpec(m, "A", 1, 25))
    saved_prev = np.full((10, 10), -1)
    late = False
    for k in range(25):
        p = r.positions_m[k, 0]
        adj = np.linalg.norm(p[:, None] - p[None], axis=-1) <= 12.0
        hops = shortest_path(adj.astype(float), unweighted=True, directed=False)
        ell = np.where(hops <= 3, k - np.maximum(hops, 1) + 1, -1).astype(int)  # own record: step k
        saved = np.maximum(saved_prev, ell)
        expected_age = np.where(saved >= 0, k - saved, -1)
        np.testing.assert_array_equal(r.record_ages[k, 0], expected_age)
        late |= bool((expected_age > 0).any())
        saved_prev = saved
    assert late, "the geometry should make some records late"

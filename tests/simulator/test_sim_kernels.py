"""The simulator's bookkeeping kernels (planner/sim_kernels.py) against the numpy functions they
stand in for: the same values, bit for bit (the simulator's runs must not change with them).

Cases are built to hit the edges: drones exactly d_hop apart (integer coordinates, so the
squared distances are exact), cut links, a hop limit, links that graze a box's face or run
parallel to a slab, records never received (step −1).
"""

from __future__ import annotations

import numpy as np
import pytest

from missions.study.simulator import _gather
from planner import sim_kernels
from planner.geometry import line_of_sight
from planner.network import hop_counts, update_saved_steps


def _grid_positions(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Integer positions on a small grid: many pairs at exactly the hop radius."""
    return rng.integers(0, 4, size=shape + (3,)).astype(float) * 10.0


@pytest.mark.parametrize("seed", range(6))
def test_hop_counts_and_saved_steps_equal_numpy(seed: int) -> None:
    rng = np.random.default_rng(seed)
    M, N = 7, 9
    pos = _grid_positions(rng, (M, N))
    blocked = rng.random((N, N)) < 0.2
    blocked = blocked | blocked.T
    deepest = 0
    for d_hop in (10.0, 20.0, 30.0):
        for max_hops, cut in ((None, None), (2, None), (3, blocked), (None, blocked)):
            ref = hop_counts(pos, d_hop, max_hops=max_hops, blocked=cut)
            got = np.empty((M, N, N), dtype=np.int64)
            sim_kernels.hop_counts(
                pos, d_hop, -1 if max_hops is None else max_hops, np.zeros((N, N), bool) if cut is None else cut, cut is not None, got
            )
            np.testing.assert_array_equal(got, ref)
            deepest = max(deepest, int(ref.max()))
            saved = rng.integers(-1, 12, size=(M, N, N)).astype(np.int64)
            for h_max in (1, 2, 4):
                want = update_saved_steps(saved, ref, 12, h_max)
                mine = saved.copy()
                sim_kernels.update_saved_steps(mine, got, 12, h_max)
                np.testing.assert_array_equal(mine, want)
    assert deepest >= 3  # multi-hop paths are exercised


@pytest.mark.parametrize("seed", range(6))
def test_line_of_sight_equals_numpy(seed: int) -> None:
    rng = np.random.default_rng(seed)
    bmin = rng.integers(-3, 3, size=(4, 3)).astype(float) * 10.0
    bmax = bmin + rng.integers(1, 4, size=(4, 3)).astype(float) * 10.0
    # Points on the grid of the boxes' corners: links along faces, parallel to slabs, through edges.
    pts = rng.integers(-5, 6, size=(400, 3)).astype(float) * 10.0
    pts[:100] += rng.normal(0.0, 3.0, size=(100, 3))
    for src in (np.array([0.0, 0.0, 0.0]), np.array([10.0, -20.0, 30.0]), rng.normal(0.0, 30.0, 3)):
        ref = line_of_sight(pts, src, bmin, bmax)
        got = np.empty(len(pts), dtype=bool)
        sim_kernels.line_of_sight(pts, src, bmin, bmax, got)
        np.testing.assert_array_equal(got, ref)
        assert ref.any() and not ref.all()
    none = np.empty(len(pts), dtype=bool)
    sim_kernels.line_of_sight(pts, src, np.zeros((0, 3)), np.zeros((0, 3)), none)
    assert none.all()


def test_gathers_equal_numpy() -> None:
    rng = np.random.default_rng(3)
    K, M, N = 12, 5, 6
    positions = rng.normal(size=(K + 1, M, N, 3))
    rec_los = rng.random((K, M, N)) < 0.5
    rec = [rng.normal(size=(K, M, N)) for _ in range(3)]
    saved = rng.integers(-1, K, size=(M, N, N)).astype(np.int64)
    used = rng.integers(-1, K, size=(M, N, N)).astype(np.int64)
    k = K - 1

    view_pos, view_los = np.empty((M, N, N, 3)), np.empty((M, N, N), dtype=bool)
    have, ages = np.empty((M, N, N), dtype=bool), np.empty((M, N, N), dtype=np.int16)
    sim_kernels.gather_view(positions, rec_los, saved, k, view_pos, view_los, have, ages)
    np.testing.assert_array_equal(view_pos, _gather(positions, saved))
    np.testing.assert_array_equal(view_los, _gather(rec_los, saved))
    np.testing.assert_array_equal(have, saved >= 0)
    np.testing.assert_array_equal(ages, np.where(saved >= 0, k - saved, -1))

    new = saved > used
    outs = (np.empty((M, N, N, 3)), np.empty((M, N, N)), np.empty((M, N, N)), np.empty((M, N, N)), np.empty((M, N, N), dtype=bool))
    mine = used.copy()
    sim_kernels.gather_new_records(saved, mine, view_pos, view_los, *rec, *outs)
    np.testing.assert_array_equal(mine, saved)
    np.testing.assert_array_equal(outs[0], np.where(new[..., None], view_pos, np.nan))
    for got, values in zip(outs[1:4], rec, strict=True):
        np.testing.assert_array_equal(got, np.where(new, _gather(values, saved), np.nan))
    np.testing.assert_array_equal(outs[4], view_los & new)
    assert new.any() and not new.all()


def test_nearest_peer_distance_equals_numpy() -> None:
    rng = np.random.default_rng(4)
    p = rng.normal(0.0, 50.0, size=(5, 4, 7, 3))
    diff = p[..., :, None, :] - p[..., None, :, :]
    dist = np.sqrt((diff * diff).sum(-1))
    dist[..., np.eye(7, dtype=bool)] = np.inf
    got = np.empty(p.shape[:-1])
    sim_kernels.nearest_peer_distance(p, got)
    np.testing.assert_array_equal(got, dist.min(-1))
    alone = np.empty((2, 3, 1))
    sim_kernels.nearest_peer_distance(p[:2, :3, :1].copy(), alone)
    assert np.isinf(alone).all()


def test_position_error_bounds_match_the_eigenvalue_checked_peb() -> None:
    """The cofactor PEB where J is provably well conditioned equals planner.fim's (LU inverse,
    eigenvalue health check) to 1e-12 relative; every other J is left to planner.fim, and
    the simulator's PEB agrees everywhere, singular views included."""
    from missions.study.simulator import _position_error_bound
    from planner.fim import position_error_bound

    rng = np.random.default_rng(5)
    B = 3000
    Q = np.linalg.qr(rng.normal(size=(B, 3, 3)))[0]
    lam = 10.0 ** rng.uniform(-1.0, 2.0, size=(B, 3))
    lam[: B // 2, 0] *= 10.0 ** rng.uniform(-16.0, -1.0, size=B // 2)
    lam[:200, 0] = 0.0  # rank-deficient
    J = np.ascontiguousarray(Q @ (lam[..., None] * np.swapaxes(Q, -1, -2)))
    J = 0.5 * (J + np.swapaxes(J, -1, -2))
    J[-3, 1, 1] = np.nan
    J[-2, 0, 0] = np.inf
    J[-1] = 0.0
    want = position_error_bound(J)[0]
    peb, checked = np.full(B, -1.0), np.empty(B, dtype=bool)
    sim_kernels.position_error_bounds(J, peb, checked)
    fast = ~checked
    assert 0.2 * B < fast.sum() < 0.9 * B  # both branches taken
    np.testing.assert_allclose(peb[fast], want[fast], rtol=1e-12, atol=0.0)
    rcond = lam.min(-1) / lam.max(-1)
    assert (rcond[fast] > sim_kernels.WELL_CONDITIONED_BOUND).all()  # the bound never lets a bad J through
    assert checked[-3:].all() and checked[:200].all()
    got = _position_error_bound(J.reshape(60, 50, 3, 3))
    assert got.shape == (60, 50)
    np.testing.assert_array_equal(np.isinf(got.reshape(-1)), np.isinf(want))
    np.testing.assert_array_equal(got.reshape(-1)[checked], want[checked])
    assert np.isinf(want).sum() > 200


def test_same_views_finds_the_first_drone_with_the_same_records() -> None:
    rng = np.random.default_rng(6)
    M, N = 40, 8
    saved = rng.integers(3, 6, size=(M, N, N)).astype(np.int64)
    saved[:, :, :5] = 4  # rows differ in their last three columns only: many repeats
    first = np.empty((M, N), dtype=np.int64)
    sim_kernels.same_views(saved, first)
    for m in range(M):
        for i in range(N):
            want = next(r for r in range(N) if np.array_equal(saved[m, r], saved[m, i]))
            assert first[m, i] == want
    assert (first != np.arange(N)).any() and (first == np.arange(N)).any()


def test_late_records_equal_the_numpy_gather() -> None:
    """The compiled late-record gather of the simulator against its numpy function."""
    from types import SimpleNamespace

    from missions.study.simulator import _Simulation, _with_late_records
    from planner import estimator as est

    rng = np.random.default_rng(7)
    W, K, M, N = 4, 9, 6, 5
    late = np.where(rng.random((W, M, N, N)) < 0.15, rng.integers(0, K, size=(W, M, N, N)), -1).astype(np.int64)
    late[:, 0] = -1  # a trial without late records
    rec = (
        rng.normal(size=(K + 1, M, N, 3)),
        rng.normal(size=(K, M, N)),
        rng.normal(size=(K, M, N)),
        rng.normal(size=(K, M, N)),
        rng.random((K, M, N)) < 0.5,
    )
    meas = est.Measurements(
        rng.normal(size=(M, N, N, 3)), rng.normal(size=(M, N, N)), rng.normal(size=(M, N, N)), rng.normal(size=(M, N, N)), rng.random((M, N, N)) < 0.5
    )
    want = _with_late_records(meas, late, *rec, {})
    fake = SimpleNamespace(faults=SimpleNamespace(late_steps=late), positions=rec[0], rec_range=rec[1], rec_az=rec[2], rec_el=rec[3], rec_los=rec[4])
    got = _Simulation._with_late_records(fake, meas)  # type: ignore[arg-type]
    assert got.range_m.shape[-1] > N  # late records were appended
    for name in ("positions_m", "range_m", "azimuth_rad", "elevation_rad", "los"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    none = SimpleNamespace(
        faults=SimpleNamespace(late_steps=np.full_like(late, -1)), positions=rec[0], rec_range=rec[1], rec_az=rec[2], rec_el=rec[3], rec_los=rec[4]
    )
    assert _Simulation._with_late_records(none, meas) is meas  # type: ignore[arg-type]

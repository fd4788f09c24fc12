"""The source keep-out a drone plans with, step to step (planner.agent.followable_keepout_m) and
while it loiters (planner.agent.plan).

An uncertain estimate (3σ ≥ d_S*, the keep-out's inflation capped) wanders by metres a step;
its keep-out's boundary may advance on a drone by at most the turn buffer b per step, the most
the safety filter assumes of a moving constraint. A trusted estimate's keep-out is never
limited. A loitering drone keeps no keep-out about the estimate it does not trust where it is
inside it and its own ranges contradict it, and keeps it otherwise.

References: closed forms of the distances (the margin |x − ĉ| − r̃ recomputed here from the
positions), and the rule's own statement of which radius applies where.
"""

from __future__ import annotations

import numpy as np
import pytest

from planner import Limits
from planner.agent import OWN_RANGE_WINDOW, SOURCE_INFLATION_MIN_M, followable_keepout_m, own_ranges, plan, source_keepout_m
from planner.params import Channel
from tests.planner.stepping import drone_state, planner_config, step_scene

LIM = Limits()  # the paper's: d_S* = 50 m, 0.5-1 m/step, 50° per step
CHANNEL = Channel(gamma=2.0, sigma_ratio_los=1.7, sigma_ratio_nlos=3.2, sigma_bearing_rad=np.radians(10.0))
UNCERTAIN_SIGMA_M = 30.0  # 3σ = 90 m ≥ d_S*: the keep-out is capped at 2 d_S*
TRUSTED_SIGMA_M = 5.0


def _margin(x: np.ndarray, centre: np.ndarray, radius: float) -> float:
    return float(np.linalg.norm(x - centre)) - radius


def test_an_uncertain_estimate_jumping_at_a_drone_advances_its_keep_out_by_b_a_step() -> None:
    """A still drone 101 m from an uncertain estimate that jumps 6 m toward it and stays: the
    margin shrinks by b on the first step, and by b on each later step until the keep-out is
    the estimate's own (100 m), never below the floor d_S* + 1.5 m."""
    b = LIM.turn_buffer_m
    x = np.array([101.0, 0.0, 20.0])
    before, after = np.array([0.0, 0.0, 20.0]), np.array([6.0, 0.0, 20.0])
    r = float(source_keepout_m(LIM, UNCERTAIN_SIGMA_M))
    assert r == pytest.approx(2.0 * LIM.d_source_m)
    last_c, last_r = before, r
    margins = [_margin(x, before, r)]
    for _ in range(20):
        r_t = float(followable_keepout_m(LIM, x, after, r, UNCERTAIN_SIGMA_M, last_c, last_r))
        assert LIM.d_source_m + SOURCE_INFLATION_MIN_M <= r_t <= r
        margins.append(_margin(x, after, r_t))
        last_c, last_r = after, r_t
    drops = -np.diff(margins)
    k_full = int(np.ceil(6.0 / b))  # steps until the 6 m jump is taken up at b a step
    np.testing.assert_allclose(drops[: k_full - 1], b, atol=1e-9)
    assert margins[-1] == pytest.approx(_margin(x, after, r))  # the estimate's own keep-out in the end
    assert drops.sum() == pytest.approx(6.0)


def test_the_floor_and_the_cases_left_unchanged() -> None:
    """A jump deeper than the inflation stops at d_S* + 1.5 m; a trusted estimate, a keep-out
    new this step (−inf before), no keep-out now, and no last step keep the radius as it is."""
    x = np.array([60.0, 0.0, 20.0])
    r = float(source_keepout_m(LIM, UNCERTAIN_SIGMA_M))
    far, near = np.array([-200.0, 0.0, 20.0]), np.array([0.0, 0.0, 20.0])
    floor = LIM.d_source_m + SOURCE_INFLATION_MIN_M
    assert float(followable_keepout_m(LIM, x, near, r, UNCERTAIN_SIGMA_M, far, r)) == pytest.approx(floor)
    r_trusted = float(source_keepout_m(LIM, TRUSTED_SIGMA_M))
    assert float(followable_keepout_m(LIM, x, near, r_trusted, TRUSTED_SIGMA_M, far, r_trusted)) == r_trusted
    assert float(followable_keepout_m(LIM, x, near, r, UNCERTAIN_SIGMA_M, far, -np.inf)) == r
    assert float(followable_keepout_m(LIM, x, near, -np.inf, UNCERTAIN_SIGMA_M, far, r)) == -np.inf
    assert float(followable_keepout_m(LIM, x, near, r, UNCERTAIN_SIGMA_M, None, None)) == r
    # An estimate moving away, or a drone flying away, is not limited: the radius is r.
    assert float(followable_keepout_m(LIM, x, far, r, UNCERTAIN_SIGMA_M, near, r)) == r


def test_batched_rows_are_limited_one_by_one(rng: np.random.Generator) -> None:
    """(M, N) batch against the one-drone call, row by row."""
    x = rng.uniform(-150.0, 150.0, (4, 5, 3))
    c, last_c = rng.uniform(-10.0, 10.0, (4, 5, 3)), rng.uniform(-10.0, 10.0, (4, 5, 3))
    sigma = rng.choice([TRUSTED_SIGMA_M, UNCERTAIN_SIGMA_M], (4, 5))
    r = source_keepout_m(LIM, sigma)
    last_r = r - rng.uniform(0.0, 5.0, r.shape)
    out = followable_keepout_m(LIM, x, c, r, sigma, last_c, last_r)
    for i in np.ndindex(r.shape):
        assert out[i] == followable_keepout_m(LIM, x[i], c[i], r[i], sigma[i], last_c[i], last_r[i])


def _keepout_while_loitering(distance_to_estimate_m: float, sigma_m: float, loitering: bool | None = None) -> tuple[float, bool]:
    """The keep-out and loiter of a lone ranging drone's planning step whose own last ranges
    (ten, LOS) are all 40 m: the source within reach."""
    x = np.array([0.0, 0.0, 20.0])
    p_hat = x + np.array([distance_to_estimate_m, 0.0, 0.0])
    scene = step_scene(0, x[None], [True], estimate_m=p_hat, information=np.eye(3) / sigma_m**2, own_range_m=40.0)
    state = drone_state(1, previous_step_m=[1.0, 0.0, 0.0], ranges_m=np.full(OWN_RANGE_WINDOW - 1, 40.0), loitering=bool(loitering))
    r = plan(planner_config([True], [False], LIM, channel=CHANNEL), scene, state)
    return float(r.keepout_m), bool(r.loiter)


def test_a_loitering_drone_drops_only_a_contradicted_keep_out_and_only_from_inside() -> None:
    """Own ranges at 40 m put the source within reach: the drone loiters by an uncertain
    estimate (3σ ≥ d_S*) or one its ranges contradict (a source 75 m or more away is, at
    z < −2.5; 42 m is not). Where the ranges contradict the estimate and the drone is inside the
    keep-out about it, it keeps none (fleeing it has no known direction away from the source);
    outside it, or by an uncertain estimate the ranges do not contradict (a moving source's, a
    drone's best guess), it keeps it."""
    capped = pytest.approx(2.0 * LIM.d_source_m)
    assert _keepout_while_loitering(90.0, UNCERTAIN_SIGMA_M) == (-np.inf, True)  # contradicted, inside 100 m
    assert _keepout_while_loitering(142.0, UNCERTAIN_SIGMA_M) == (capped, True)  # contradicted, outside
    assert _keepout_while_loitering(42.0, UNCERTAIN_SIGMA_M) == (capped, True)  # uncertain, not contradicted
    certain = float(source_keepout_m(LIM, 10.0))  # 3σ = 30 m < d_S*: 80 m
    assert _keepout_while_loitering(75.0, 10.0) == (-np.inf, True)  # contradicted, inside
    assert _keepout_while_loitering(140.0, 10.0) == (pytest.approx(certain), True)  # contradicted, outside


def test_the_keep_out_is_dropped_at_the_entry_threshold_not_the_loiters_hysteresis() -> None:
    """Ranges at 40 m against a converged estimate (σ = 10 m, keep-out 80 m) 53.2 m away:
    z = (40/53.2 − 1)/r = −2 (closed form, r = 0.1238 for ten LOS ranges, γ = 2). A drone that
    loitered at the last step goes on loitering (held contradicted down to z = −1) but keeps
    the keep-out (dropped only below z = −2.5); one that did not loiter does not start."""
    own = own_ranges(np.full(OWN_RANGE_WINDOW, 40.0), np.ones(OWN_RANGE_WINDOW, bool), CHANNEL)
    d = 40.0 / (1.0 - 2.0 * float(own.relative_sd(1.0)))
    assert d == pytest.approx(53.2, abs=0.1)
    certain = pytest.approx(float(source_keepout_m(LIM, 10.0)))
    assert _keepout_while_loitering(d, 10.0, loitering=True) == (certain, True)
    assert _keepout_while_loitering(d, 10.0, loitering=False) == (certain, False)
    # At z = −3 both the loiter and the drop apply.
    d3 = 40.0 / (1.0 - 3.0 * float(own.relative_sd(1.0)))
    assert _keepout_while_loitering(d3, 10.0, loitering=True) == (-np.inf, True)

"""A ranging drone's own ranges as second evidence of its distance to the source.

The keep-out about the estimate, d_S* + min(3σ, d_S*) (planner.agent.source_keepout_m), misses
the true d_S* sphere when the estimate is wrong along the drone's own line of sight by more than
that inflation. The recorded case: drone 9 of trial 39 of ``missions/paper/ranging_nlos.yaml``
with A-optimality (the last source violations of the paper missions at 100 trials; estimates,
information and positions of steps 290-345 of the closed loop). At step 299 the estimator's
global re-check moves its estimate from 29 m to 60 m off; from then to step 340 the error is
almost all along the line from the drone (the source 50-58 m nearer the drone than the
estimate), with a largest σ of 29-40 m (so the keep-out is capped at 2 d_S* = 100 m) and a σ of
only 6-11 m along that line. Its own ranges, however, measure its distance to the source
directly: planner.agent.own_ranges combines the last ones (a lower bound on the distance, and a
test of the estimate's distance against them), and planner.agent.must_loiter makes the drone
loiter in place (planner.agent.loiter_gradient) where they put the source within reach and the
estimate gives no direction to trust (docs/control.md).

References are independent of the implementation: the normal law (scipy) for the bound's
coverage, measured distances for "does not approach", the true source for safety.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from planner import FimStatus, Limits
from planner.agent import (
    OWN_RANGE_CONTRADICTION_SIGMAS,
    OWN_RANGE_RELEASE_SIGMAS,
    OWN_RANGE_WINDOW,
    contradicted,
    estimate_sigma_m,
    loiter_gradient,
    must_loiter,
    own_ranges,
    source_keepout_m,
)
from planner.control import source_activation_margin_m
from planner.params import Channel
from tests.planner.stepping import control_step_of

DATA = Path(__file__).parent / "data" / "ranging_nlos_A_trial39_drone9.npz"
CHANNEL = Channel(gamma=2.0, sigma_ratio_los=1.7, sigma_ratio_nlos=3.2, sigma_bearing_rad=np.radians(10.0))
LIM = Limits()  # the paper's: d_S* = 50 m, 0.5-1 m/step, 50° per step
NO_BOX = np.zeros((0, 3))


def _relative_sigma(los: np.ndarray) -> np.ndarray:
    """σ_r / d of eq. 5 with γ = 2: (ln 10 / 10)(σ_sh/γ), written out (not the channel's property)."""
    return math.log(10.0) / 10.0 * np.where(los, 1.7, 3.2)


@pytest.mark.parametrize("k", [1.0, 2.0])
def test_lower_bound_coverage_is_the_normal_tail(rng: np.random.Generator, k: float) -> None:
    """Ranges of eq. 3-5 (γ = 2) at a known distance, mixed LOS/NLOS: the bound exceeds the
    true distance with probability Φ(−k)."""
    n, w = 40_000, OWN_RANGE_WINDOW
    d = rng.uniform(20.0, 200.0, (n, 1))
    los = rng.random((n, w)) < 0.5
    r = d + _relative_sigma(los) * d * rng.standard_normal((n, w))
    lb = own_ranges(r, los, CHANNEL).lower_bound_m(k)
    p = stats.norm.sf(k)
    frac = np.mean(lb > d[:, 0])
    assert abs(frac - p) < 4.0 * math.sqrt(p * (1.0 - p) / n), (frac, p)


def test_lower_bound_missing_ranges() -> None:
    """NaN ranges are left out; no range at all gives no bound (+inf); one range is checked by hand."""
    los = np.array([True, False, True])
    r = np.array([100.0, np.nan, 100.0])
    s = math.log(10.0) / 10.0 * 1.7
    expected = 100.0 / (1.0 + 2.0 * s / math.sqrt(2.0))
    assert own_ranges(r, los, CHANNEL).lower_bound_m() == pytest.approx(expected, rel=1e-12)
    assert own_ranges(np.full((2, 3), np.nan), np.ones((2, 3), bool), CHANNEL).lower_bound_m().tolist() == [np.inf, np.inf]
    assert own_ranges(np.zeros((4, 0)), np.zeros((4, 0), bool), CHANNEL).lower_bound_m().shape == (4,)


def test_contradiction_test_false_alarm_and_power(rng: np.random.Generator) -> None:
    """Ranges of eq. 3-5 (γ = 2) at a known distance d: an estimate at d is called contradicted
    with probability Φ(−k) (k = 2.5, the one-sided normal tail, scipy); one at 2 d almost always
    (the power of the test for ten LOS ranges, closed form: with d̄ = d (1 + r n),
    z = (d̄/2d − 1)/r = n/2 − 1/(2r), so P(z < −k) = Φ(1/r − 2k), r the relative standard
    deviation of d̄)."""
    n, w = 200_000, OWN_RANGE_WINDOW
    d = rng.uniform(20.0, 200.0, n)
    los = np.ones((n, w), dtype=bool)
    r = d[:, None] + _relative_sigma(los) * d[:, None] * rng.standard_normal((n, w))
    own = own_ranges(r, los, CHANNEL)
    k = OWN_RANGE_CONTRADICTION_SIGMAS
    assert k == 2.5
    p = stats.norm.sf(k)
    frac = float(np.mean(own.contradicts(d)))
    assert abs(frac - p) < 5.0 * math.sqrt(p * (1.0 - p) / n), (frac, p)
    rel = float(_relative_sigma(np.array(True))) / math.sqrt(w)  # about d; the same about 2 d (γ = 2)
    power = stats.norm.cdf(1.0 / rel - 2.0 * k)
    frac2 = float(np.mean(own.contradicts(2.0 * d)))
    assert abs(frac2 - power) < 5.0 * math.sqrt(power * (1.0 - power) / n) + 1e-3, (frac2, power)
    none = own_ranges(np.full((3, w), np.nan), np.ones((3, w), bool), CHANNEL)
    assert not none.contradicts(np.full(3, 10.0)).any() and np.all(np.isinf(none.lower_bound_m()))


def test_must_loiter_values() -> None:
    """Closed form: loiter where the own bound is below d_S* + a (a = 2 v_max Δt + b) and the
    estimate is not observable, or 3σ ≥ d_S*, or contradicted by the ranges; never otherwise."""
    a = 2.0 * LIM.step_max_m + LIM.turn_buffer_m
    assert source_activation_margin_m(LIM) == pytest.approx(a)
    w = OWN_RANGE_WINDOW
    # Ten LOS ranges all at 40 m (bound < d_S* + a) or all at 90 m (bound > d_S* + a).
    near, far = np.full(w, 40.0), np.full(w, 90.0)
    los = np.ones(w, bool)
    cases = [  # (ranges, σ, observable, distance to the estimate, loiter?)
        (near, 20.0, True, 42.0, True),  # uncertain (3σ = 60 ≥ 50)
        (near, 10.0, True, 42.0, False),  # certain, consistent with the ranges
        (near, 10.0, True, 140.0, True),  # certain, but the ranges put the source nearer
        (near, 10.0, False, 42.0, True),  # not observable
        (far, 20.0, True, 140.0, False),  # the ranges say clear
        (far, 10.0, False, 200.0, False),
    ]
    for ranges, sigma, obs, dist, expected in cases:
        own = own_ranges(ranges, los, CHANNEL)
        assert bool(must_loiter(LIM, sigma, obs, dist, own)) is expected, (ranges[0], sigma, obs, dist)
    assert own_ranges(near, los, CHANNEL).lower_bound_m() < LIM.d_source_m + a < own_ranges(far, los, CHANNEL).lower_bound_m()


def test_a_loitering_drone_stays_in_place(rng: np.random.Generator) -> None:
    """From any heading and tilt, thirty steps of eq. 14 down the loiter gradient under eq. 2's
    limits: the drone turns at φ_max and stays within the circle of one step's chord, of radius
    v_max Δt / (2 sin(φ_max/2)) (closed form), plus the steps its tilt takes to level."""
    n = 300
    p = np.stack((rng.uniform(-50, 50, n), rng.uniform(-50, 50, n), np.full(n, 12.0)), axis=-1)
    prev = rng.standard_normal((n, 3))
    prev[:, 2] *= 0.2
    prev *= (LIM.step_max_m / np.linalg.norm(prev, axis=-1))[:, None]
    start = p.copy()
    reach = np.zeros(n)
    for _ in range(30):
        r = control_step_of(p, prev, loiter_gradient(prev), np.zeros(n, np.int8), np.zeros((n, 0, 3)), np.zeros((n, 0), bool),
                         np.zeros((n, 0)), np.full((n, 3), 1e4), np.full(n, 50.0), NO_BOX, NO_BOX, LIM, rng.random((n, 2)))
        prev, p = r.displacement, r.next_position
        reach = np.maximum(reach, np.linalg.norm(p - start, axis=-1))
    radius = LIM.step_max_m / (2.0 * math.sin(LIM.heading_change_max_rad / 2.0))
    assert np.all(reach <= 2.0 * radius + 2.0 * LIM.step_max_m), reach.max()
    # Level after the first steps: no climb or descent while loitering.
    assert np.all(np.abs(prev[:, 2]) < 1e-9)
    # Without the loiter the same cost-free drones would fly away: a straight gradient goes 30 m.
    assert reach.max() < 0.2 * 30.0 * LIM.step_max_m


def _replay(rule_on: bool, seed: int, start_step: int = 325) -> float:
    """The recorded drone alone from ``start_step`` on: its recorded estimates and σ, a cost that
    pulls it straight at the estimate (the worst case), its own ranges drawn (NLOS, eq. 3-5) at
    the recorded positions before ``start_step`` and at the positions it flies to from then on.
    Returns the smallest distance to the true source (m)."""
    data = np.load(DATA)
    src = data["source_m"]
    est, info, steps = data["estimate_m"], data["information"], data["steps"]
    sigma = estimate_sigma_m(info)
    gen = np.random.default_rng(seed)
    first = int(np.flatnonzero(steps == start_step)[0])
    ranges = [float(d + _relative_sigma(np.array(False)) * d * gen.standard_normal()) for d in np.linalg.norm(data["own_position_m"][:first] - src, axis=-1)]
    p = data["own_position_m"][first].copy()
    prev = data["previous_step_m"][first].copy()
    closest = np.inf
    for k in range(first, est.shape[0]):
        d = float(np.linalg.norm(p - src))
        ranges.append(d + float(_relative_sigma(np.array(False))) * d * gen.standard_normal())
        window = np.array(ranges[-OWN_RANGE_WINDOW:])
        keepout = source_keepout_m(LIM, sigma[k])
        grad = (p - est[k]) / np.linalg.norm(p - est[k])
        if rule_on and must_loiter(LIM, sigma[k], True, np.linalg.norm(p - est[k]), own_ranges(window, np.zeros(window.shape, bool), CHANNEL)):
            grad = loiter_gradient(prev)
        r = control_step_of(p, prev, grad, int(FimStatus.OK), np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0), est[k],
                         keepout, NO_BOX, NO_BOX, LIM, np.array([0.5, 0.5]))
        prev = r.displacement
        p = r.next_position
        closest = min(closest, float(np.linalg.norm(p - src)))
    return closest


def test_recorded_case_estimate_misses_what_the_own_ranges_see() -> None:
    """The recording is the failure: at its closest steps the true source is nearer than the
    keep-out inflation allows, along the drone's own line of sight."""
    data = np.load(DATA)
    src, est, p = data["source_m"], data["estimate_m"], data["own_position_m"]
    sigma = estimate_sigma_m(data["information"])
    u = (p - est) / np.linalg.norm(p - est, axis=-1, keepdims=True)
    along = np.einsum("ki,ki->k", src - est, u)
    inflation = source_keepout_m(LIM, sigma) - LIM.d_source_m
    sigma_along = np.sqrt(np.einsum("ki,kij,kj->k", u, np.linalg.inv(data["information"]), u))
    gross = (data["steps"] >= 299) & (data["steps"] <= 340)
    assert data["true_margin_m"][gross].min() < 0.0
    assert np.all(along[gross] > inflation[gross])  # the error along the line exceeds the inflation
    assert np.all(sigma[gross] < 41.0) and np.all(along[gross] > 4.0 * sigma_along[gross])


def test_recorded_case_own_ranges_keep_the_drone_out() -> None:
    """Replayed in closed loop: without the loiter the drone enters the true d_S* sphere; with it,
    for every noise draw, it stops outside."""
    assert _replay(False, 0) < LIM.d_source_m
    closest = [_replay(True, seed) for seed in range(12)]
    assert min(closest) >= LIM.d_source_m, closest


def _creep(hysteresis: bool, seed: int, steps: int = 400) -> float:
    """A drone pulled straight at the true source (the worst cost) from 70 m, its estimate 100 m
    off on the far side with σ = 45 m (never trusted: 3σ ≥ d_S*), its own ranges NLOS (eq. 3-5,
    drawn at its true distance). Returns its smallest distance to the source (m)."""
    gen = np.random.default_rng(seed)
    src = np.array([0.0, 0.0, 2.0])
    est = np.array([-100.0, 0.0, 2.0])
    p = np.array([70.0, 0.0, 12.0])
    prev = np.array([-LIM.step_max_m, 0.0, 0.0])
    ranges: list[float] = []
    loitering = False
    closest = np.inf
    for _ in range(steps):
        d = float(np.linalg.norm(p - src))
        ranges.append(d + float(_relative_sigma(np.array(False))) * d * gen.standard_normal())
        window = np.array(ranges[-OWN_RANGE_WINDOW:])
        own = own_ranges(window, np.zeros(window.shape, bool), CHANNEL)
        loiter = bool(must_loiter(LIM, 45.0, True, np.linalg.norm(p - est), own, loitering if hysteresis else None))
        grad = loiter_gradient(prev) if loiter else (p - src) / d
        r = control_step_of(p, prev, grad, int(FimStatus.OK), np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0), est,
                         source_keepout_m(LIM, 45.0), NO_BOX, NO_BOX, LIM, np.array([0.5, 0.5]))
        prev, p, loitering = r.displacement, r.next_position, loiter
        closest = min(closest, float(np.linalg.norm(p - src)))
    return closest


def test_a_loitering_drone_does_not_creep_in_on_noisy_ranges() -> None:
    """Synthetic truth, closed loop: resuming the cost as soon as the noisy bound rises above
    d_S* + a, the drone creeps in a step at a time and crosses d_S* for some noise draws; with
    the hysteresis (resume only at 1.5 (d_S* + a) or a trusted estimate) it stays outside for
    every draw."""
    without = [_creep(False, seed) for seed in range(8)]
    assert min(without) < LIM.d_source_m, without
    held = [_creep(True, seed) for seed in range(8)]
    assert min(held) > LIM.d_source_m, held


def test_must_loiter_hysteresis_values() -> None:
    """Closed form of the hysteresis: a drone loitering at the last step goes on while the
    estimate is untrusted and the bound is below 1.5 (d_S* + a); it stops at a trusted estimate
    or beyond that bound; a drone not loitering starts only below d_S* + a."""
    a = source_activation_margin_m(LIM)
    near = LIM.d_source_m + a
    los = np.ones(OWN_RANGE_WINDOW, bool)

    def bound_of(mean: float) -> tuple[object, float]:
        own = own_ranges(np.full(OWN_RANGE_WINDOW, mean), los, CHANNEL)
        return own, float(own.lower_bound_m())

    mid, mid_lb = bound_of(85.0)  # bound between d_S* + a and 1.5 (d_S* + a)
    clear, clear_lb = bound_of(160.0)
    assert near < mid_lb < 1.5 * near < clear_lb
    assert bool(must_loiter(LIM, 20.0, True, 100.0, mid, True))  # untrusted, still within 1.5×: stays
    assert not bool(must_loiter(LIM, 20.0, True, 100.0, mid, False))  # not loitering: does not start
    assert not bool(must_loiter(LIM, 20.0, True, 100.0, mid, None))
    assert not bool(must_loiter(LIM, 10.0, True, 85.0, mid, True))  # trusted again: resumes
    assert not bool(must_loiter(LIM, 20.0, True, 160.0, clear, True))  # clear by its own ranges


def test_the_contradiction_has_hysteresis() -> None:
    """Closed form: ten LOS ranges all at d̄ against an estimate at d give z = (d̄/d − 1)/r(d)
    (r(d) from eq. 5's σ at d, γ = 2); the estimate is contradicted below z = −2.5, and for a
    drone loitering at the last step below z = −1 (:func:`contradicted`), so a drone whose
    ranges put the source between 1 and 2.5 σ nearer goes on loitering but does not start."""
    los = np.ones(OWN_RANGE_WINDOW, bool)
    own = own_ranges(np.full(OWN_RANGE_WINDOW, 40.0), los, CHANNEL)
    r1 = float(own.relative_sd(1.0))  # r(d) = r(1) d^(1 - γ/2): the same at every d for γ = 2
    assert float(own.relative_sd(50.0)) == pytest.approx(r1)
    for z, start, stay in ((-3.0, True, True), (-2.0, False, True), (-0.5, False, False)):
        d = 40.0 / (1.0 + z * r1)  # the estimate's distance that gives z
        assert bool(contradicted(own, d)) is start, z
        assert bool(contradicted(own, d, False)) is start, z
        assert bool(contradicted(own, d, True)) is stay, z
        # σ = 10 m (3σ < d_S*): trusted but for the ranges; the bound (40 m ranges) is below d_S* + a.
        assert bool(must_loiter(LIM, 10.0, True, d, own, False)) is start, z
        assert bool(must_loiter(LIM, 10.0, True, d, own, True)) is stay, z
    assert OWN_RANGE_CONTRADICTION_SIGMAS == 2.5 and OWN_RANGE_RELEASE_SIGMAS == 1.0

"""Control law (eqs. 7, 14-17): kinematic limits, descent, projection, singular fallback, and
closed-loop safety.

References are geometric, not the implementation's formulas: speeds, heading and tilt changes
are measured from the displacement with atan2; the projection property is "no component into
an active constraint"; safety is checked by simulating a few drones pushed into each other,
into an obstacle, towards the source and out of the altitude box, and measuring every distance
at every step.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from comms.faults import FaultBuffer, FaultModel
from planner import FimStatus, Limits, distance_to_boxes, hop_counts, update_saved_steps
from planner.network import NEVER
from tests.planner.stepping import control_step_of

LIM = Limits()  # the paper's case study: d_U*=1, d_S*=50, d_O*=5, 0.5-1 m/step, 50°, z in [2, 25]
NO_BOX = np.zeros((0, 3))
FAR_SOURCE = np.array([0.0, 1e5, 10.0])


def heading(u: np.ndarray) -> float:
    return math.atan2(u[1], u[0])


def tilt(u: np.ndarray) -> float:
    return math.atan2(u[2], math.hypot(u[0], u[1]))


def wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def unit(az: float, el: float) -> np.ndarray:
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def one_step(
    p,
    prev,
    grad,
    *,
    status=FimStatus.OK,
    peers=None,
    age=None,
    source=FAR_SOURCE,
    keepout=None,
    boxes=(NO_BOX, NO_BOX),
    limits=LIM,
    uniforms=(0.5, 0.5),
    xi=None,
    perturbation_rad=math.radians(20.0),
):
    peers = np.zeros((0, 3)) if peers is None else np.asarray(peers, dtype=float)
    n = peers.shape[0]
    age = np.zeros(n) if age is None else np.asarray(age, dtype=float)
    keepout = limits.d_source_m if keepout is None else keepout
    return control_step_of(
        np.asarray(p, dtype=float), np.asarray(prev, dtype=float), np.asarray(grad, dtype=float), int(status),
        peers, np.ones(n, bool), age, np.asarray(source, dtype=float), keepout, boxes[0], boxes[1], limits,
        np.asarray(uniforms, dtype=float), xi=xi, perturbation_rad=perturbation_rad,
    )


def assert_kinematics(u, prev, limits, eps=1e-9):
    s = float(np.linalg.norm(u))
    assert limits.step_min_m - eps <= s <= limits.step_max_m + eps, s
    if np.linalg.norm(prev) > 0:
        assert abs(tilt(u) - tilt(prev)) <= limits.tilt_change_max_rad + eps
        if math.hypot(u[0], u[1]) > 1e-6 * s and math.hypot(prev[0], prev[1]) > 1e-6 * np.linalg.norm(prev):
            assert abs(wrap(heading(u) - heading(prev))) <= limits.heading_change_max_rad + eps


limits_st = st.builds(
    Limits,
    step_min_m=st.floats(0.1, 0.8),
    step_max_m=st.floats(0.8, 3.0),
    heading_change_max_rad=st.floats(math.radians(10), math.radians(90)),
    tilt_change_max_rad=st.floats(math.radians(10), math.radians(90)),
    activation=st.sampled_from(["safe", "paper"]),
)


# ---------------------------------------------------------------- limits on random inputs


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), limits=limits_st, n_peers=st.integers(0, 5), with_prev=st.booleans(), singular=st.booleans())
def test_step_respects_kinematic_limits_and_altitude_box(seed, limits, n_peers, with_prev, singular):
    rng = np.random.default_rng(seed)
    p = np.array([*rng.uniform(-30, 30, 2), rng.uniform(limits.z_min_m, limits.z_max_m)])
    prev = unit(rng.uniform(-math.pi, math.pi), rng.uniform(-1.3, 1.3)) * rng.uniform(limits.step_min_m, limits.step_max_m)
    prev = prev if with_prev else np.zeros(3)
    grad = rng.normal(size=3) * 10 ** rng.uniform(-6, 3)
    peers = p + rng.uniform(-15, 15, (n_peers, 3))
    src = p + rng.uniform(-80, 80, 3)
    bmin = rng.uniform(-40, 30, (2, 3))
    boxes = (bmin, bmin + rng.uniform(2, 12, (2, 3)))
    r = one_step(
        p, prev, grad * (not singular), status=FimStatus.SINGULAR if singular else FimStatus.OK, peers=peers,
        age=rng.integers(0, 3, n_peers), source=src, boxes=boxes, limits=limits, uniforms=rng.random(2),
    )
    u = r.displacement
    assert np.isfinite(u).all() and np.isfinite(r.next_position).all()
    np.testing.assert_allclose(r.next_position, p + u, atol=1e-12)
    assert bool(r.singular) is singular
    z = r.next_position[2]
    if limits.activation == "paper":
        # The paper clamps z to its box, which may shorten the step: only the box is guaranteed.
        assert limits.z_min_m - 1e-9 <= z <= limits.z_max_m + 1e-9
        assert np.linalg.norm(u) <= limits.step_max_m + 1e-9
    else:
        assert_kinematics(u, prev, limits)
        if not r.infeasible:
            assert limits.z_min_m - 1e-9 <= z <= limits.z_max_m + 1e-9


# ---------------------------------------------------------------- descent without constraints


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), activation=st.sampled_from(["safe", "paper"]), with_prev=st.booleans())
def test_unconstrained_step_is_normalised_steepest_descent(seed, activation, with_prev):
    rng = np.random.default_rng(seed)
    limits = replace(LIM, activation=activation)
    p = np.array([0.0, 0.0, 13.0])
    g_dir = unit(rng.uniform(-math.pi, math.pi), rng.uniform(-1.2, 1.2))
    grad = g_dir * 10 ** rng.uniform(-8, 4)
    prev = np.zeros(3)
    if with_prev:  # a previous direction close enough to -g that no turn limit binds
        d_az, d_el = rng.uniform(-0.8, 0.8) * limits.heading_change_max_rad, rng.uniform(-0.8, 0.8) * limits.tilt_change_max_rad
        assume(abs(tilt(-g_dir) + d_el) < 1.45)
        prev = unit(heading(-g_dir) + d_az, tilt(-g_dir) + d_el) * 0.7
    r = one_step(p, prev, grad, limits=limits)
    u = r.displacement
    assert not r.active.any() and not r.filtered and not r.singular
    assert float(grad @ u) < 0.0  # a descent direction
    # At top speed, along -∇C (normalised ξ).
    np.testing.assert_allclose(u, -limits.step_max_m * g_dir, atol=1e-9)


def test_given_xi_scales_the_gradient_and_speed_is_clamped():
    p, g = np.array([0.0, 0.0, 13.0]), np.array([3.0, -4.0, 0.0])  # |g| = 5
    np.testing.assert_allclose(one_step(p, np.zeros(3), g, xi=0.15).displacement, -0.15 * g, atol=1e-12)
    np.testing.assert_allclose(one_step(p, np.zeros(3), g, xi=0.01).displacement, -LIM.step_min_m * g / 5, atol=1e-12)
    np.testing.assert_allclose(one_step(p, np.zeros(3), g, xi=10.0).displacement, -LIM.step_max_m * g / 5, atol=1e-12)


def test_turn_rate_limit_turns_as_far_as_allowed_towards_the_descent():
    p = np.array([0.0, 0.0, 13.0])
    prev = np.array([1.0, 0.0, 0.0])
    grad = np.array([0.0, -1.0, 0.0])  # wants to go north: a 90° turn
    r = one_step(p, prev, grad)
    assert heading(r.displacement) == pytest.approx(LIM.heading_change_max_rad, abs=1e-9)
    assert float(grad @ r.displacement) < 0.0
    grad_up = np.array([-1.0, 0.0, -1.0]) / math.sqrt(2)  # wants to climb at 45° while flying east: allowed
    assert tilt(one_step(p, prev, grad_up).displacement) == pytest.approx(math.pi / 4, abs=1e-9)
    grad_vertical = np.array([0.0, 0.0, -1.0])  # straight up: a 90° tilt change, limited to 50°
    assert tilt(one_step(p, prev, grad_vertical).displacement) == pytest.approx(LIM.tilt_change_max_rad, abs=1e-9)


# ---------------------------------------------------------------- projection onto active constraints


def _constraint_cases(rng):
    """(name, kwargs for one_step, p, outward unit normal of the active constraint)."""
    p = np.array([0.0, 0.0, 12.0])
    n_peer = unit(rng.uniform(-math.pi, math.pi), rng.uniform(-0.5, 0.5))
    n_src = unit(rng.uniform(-math.pi, math.pi), rng.uniform(-0.3, 0.3))
    box_min, box_max = np.array([[3.0, -10.0, 0.0]]), np.array([[13.0, 10.0, 30.0]])
    return [
        ("uav", dict(peers=[p - 0.8 * n_peer]), n_peer),  # 0.8 m < d_U* = 1 m: violated
        ("source", dict(source=p - 45.0 * n_src, keepout=50.0), n_src),  # 45 m < d_S* = 50 m
        ("obstacle", dict(boxes=(box_min, box_max)), np.array([-1.0, 0.0, 0.0])),  # 3 m < d_O* = 5 m
    ]


@pytest.mark.parametrize("activation", ["paper", "safe"])
def test_active_constraint_gets_no_component_into_it(rng, activation):
    limits = replace(LIM, activation=activation)
    family = {"uav": 0, "source": 1, "obstacle": 2}
    for _ in range(40):
        for name, kw, n in _constraint_cases(rng):
            p = np.array([0.0, 0.0, 12.0])
            grad = n * rng.uniform(0.2, 5.0) + rng.normal(size=3)  # pushes into the constraint
            grad[2] *= 0.2
            r = one_step(p, np.zeros(3), grad, limits=limits, **kw)
            u = r.displacement
            assert r.active[family[name]], name
            assert float(u @ n) >= -1e-9, (name, u @ n)
            if activation == "paper":
                # Eq. 14: the tangential part of u is along -P∇C, P = I - n nᵀ.
                pg = grad - (grad @ n) * n
                tangential = u - (u @ n) * n
                assert np.linalg.norm(np.cross(tangential, pg)) <= 1e-9 * np.linalg.norm(pg) * max(np.linalg.norm(tangential), 1.0)
                assert float(tangential @ pg) <= 0.0


def test_paper_rule_ignores_a_constraint_until_it_is_violated():
    p = np.array([0.0, 0.0, 12.0])
    grad = np.array([-1.0, 0.0, 0.0])  # descent: east, towards the box 5.5 m away
    boxes = (np.array([[5.5, -10.0, 0.0]]), np.array([[15.0, 10.0, 30.0]]))
    paper = one_step(p, np.zeros(3), grad, boxes=boxes, limits=replace(LIM, activation="paper"))
    assert not paper.active.any()
    np.testing.assert_allclose(paper.displacement, [1.0, 0.0, 0.0], atol=1e-12)
    safe = one_step(p, np.zeros(3), grad, boxes=boxes)
    assert safe.active[2]
    assert distance_to_boxes(safe.next_position, *boxes) >= LIM.d_obstacle_m


# ---------------------------------------------------------------- singular fallback


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), activation=st.sampled_from(["safe", "paper"]))
def test_singular_keeps_previous_direction_within_perturbation(seed, activation):
    rng = np.random.default_rng(seed)
    limits = replace(LIM, activation=activation)
    pert = math.radians(rng.uniform(1.0, 40.0))
    prev = unit(rng.uniform(-math.pi, math.pi), rng.uniform(-0.6, 0.6)) * rng.uniform(0.5, 1.0)
    p = np.array([0.0, 0.0, 13.0])
    with np.errstate(all="raise"):
        r = one_step(p, prev, np.zeros(3), status=FimStatus.SINGULAR, limits=limits, uniforms=rng.random(2), perturbation_rad=pert)
    u = r.displacement
    assert r.singular and np.isfinite(u).all()
    assert abs(wrap(heading(u) - heading(prev))) <= min(pert, limits.heading_change_max_rad) + 1e-9
    assert abs(tilt(u) - tilt(prev)) <= min(pert, limits.tilt_change_max_rad) + 1e-9
    assert limits.step_min_m - 1e-9 <= np.linalg.norm(u) <= limits.step_max_m + 1e-9


def test_singular_first_step_and_perturbations_differ():
    p = np.array([0.0, 0.0, 13.0])
    a = one_step(p, np.zeros(3), np.zeros(3), status=FimStatus.SINGULAR, uniforms=(0.1, 0.9))
    b = one_step(p, np.zeros(3), np.zeros(3), status=FimStatus.SINGULAR, uniforms=(0.6, 0.2))
    for r in (a, b):
        assert np.isfinite(r.displacement).all() and np.linalg.norm(r.displacement) == pytest.approx(1.0)
    assert not np.allclose(a.displacement, b.displacement)
    prev = np.array([0.0, 1.0, 0.0])
    c = one_step(p, prev, np.zeros(3), status=FimStatus.SINGULAR, uniforms=(0.5, 0.5))  # zero jitter
    np.testing.assert_allclose(c.displacement, prev, atol=1e-12)


def test_batched_step_equals_loop(rng):
    S, N = 3, 4
    p = np.concatenate([rng.uniform(-20, 20, (S, N, 2)), rng.uniform(4, 20, (S, N, 1))], -1)
    prev = rng.normal(size=(S, N, 3)) * 0.5
    grad = rng.normal(size=(S, N, 3))
    status = rng.integers(0, 3, (S, N))
    peers = np.broadcast_to(p[:, None], (S, N, N, 3)).copy()
    mask = ~np.eye(N, dtype=bool)[None].repeat(S, 0)
    age = rng.integers(0, 2, (S, N, N)).astype(float)
    src = np.array([0.0, 60.0, 10.0])
    boxes = (np.array([[-5.0, 20.0, 0.0]]), np.array([[5.0, 30.0, 20.0]]))
    uni = rng.random((S, N, 2))
    r = control_step_of(p, prev, grad, status, peers, mask, age, src, 50.0, *boxes, LIM, uni)
    for s in range(S):
        for i in range(N):
            one = control_step_of(p[s, i], prev[s, i], grad[s, i], status[s, i], peers[s, i], mask[s, i], age[s, i], src, 50.0, *boxes, LIM, uni[s, i])
            np.testing.assert_allclose(r.next_position[s, i], one.next_position, atol=1e-12)
            np.testing.assert_array_equal(r.active[s, i], one.active)


# ---------------------------------------------------------------- closed-loop safety


def _scenario(scenario: str, rng: np.random.Generator, seeds: int, N: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Start positions (seeds, N, 3), targets, source and boxes of a scenario of :func:`simulate`."""
    src = FAR_SOURCE
    boxes = (NO_BOX, NO_BOX)
    centre = np.array([0.0, 0.0, 12.0])
    ang = np.linspace(0, 2 * np.pi, N, endpoint=False)[None] + rng.uniform(-0.3, 0.3, (seeds, N))
    ring = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], -1)
    if scenario == "head-on":  # everyone attracted to the centre of a 12-20 m ring
        p = centre + ring * rng.uniform(6, 10, (seeds, N, 1))
        target = np.broadcast_to(centre, p.shape)
    elif scenario == "swap":  # everyone attracted to the far side of a 12-20 m ring: they cross at the centre
        p = centre + ring * rng.uniform(6, 10, (seeds, N, 1))
        target = centre - 3.0 * (p - centre)
    elif scenario == "obstacle":  # attracted to the centre of a box, from 12-25 m
        boxes = (np.array([[-4.0, -4.0, 0.0]]), np.array([[4.0, 4.0, 18.0]]))
        p = centre + ring * rng.uniform(16, 30, (seeds, N, 1)) * [1, 1, 0] + [0, 0, 0]
        p[..., 2] = rng.uniform(5, 20, (seeds, N))
        target = np.broadcast_to(np.array([0.0, 0.0, 9.0]), p.shape)
    elif scenario == "source":  # attracted to the source, from 53-60 m, keep-out 50 m
        src = np.array([0.0, 0.0, 10.0])
        p = src + ring * rng.uniform(53, 60, (seeds, N, 1))
        p[..., 2] = rng.uniform(5, 20, (seeds, N))
        target = np.broadcast_to(src, p.shape)
    elif scenario == "altitude":  # half pulled to the sky, half into the ground
        p = centre + ring * rng.uniform(15, 30, (seeds, N, 1))
        p[..., 2] = rng.uniform(4, 23, (seeds, N))
        target = p + np.where(np.arange(N)[:, None] % 2 == 0, [30.0, 0.0, 500.0], [-30.0, 0.0, -500.0])
    else:
        raise ValueError(scenario)
    return p, target, src, boxes


def simulate(
    scenario: str, activation: str, seeds: int, steps: int, d_hop_m: float | None = None, h_max: int = 2, extra_delay_steps: int = 0
) -> dict[str, float]:
    """Drones pushed by a constant attractive gradient (unit vector to a target), all stepping at
    once. Each sees the others' current positions (``d_hop_m=None``) or, through the delayed
    view of planner.network (disk graph of radius d_hop, h_max hops, memory buffer), their
    positions of step ℓ = k − h + 1 with age h − 1. With ``extra_delay_steps`` D > 0 each record
    is also late by a uniform 0..D steps (comms.faults, the injected delay of the fault grid;
    its own seeded stream per seed and receiver), and a peer whose first records have not
    arrived is kept clear of at its start position, aged k (as planner.agent.plan does).
    Returns the worst margin of every safety distance over all steps and seeds (negative =
    violated)."""
    limits = replace(LIM, activation=activation)
    rng = np.random.default_rng([ord(c) for c in scenario + activation] + [int(d_hop_m or 0)])
    N = 4
    p, target, src, boxes = _scenario(scenario, rng, seeds, N)
    prev = np.zeros_like(p)
    trajectory = [p.copy()]
    saved = np.full((seeds, N, N), NEVER)
    eye = np.eye(N, dtype=bool)
    worst = {"uav": np.inf, "source": np.inf, "obstacle": np.inf, "altitude": np.inf}

    def record(q: np.ndarray) -> None:
        diff = q[:, :, None] - q[:, None]
        dist = np.sqrt((diff**2).sum(-1)) + np.where(eye, np.inf, 0.0)
        worst["uav"] = min(worst["uav"], float((dist - limits.d_uav_m).min()))
        worst["source"] = min(worst["source"], float((np.linalg.norm(q - src, axis=-1) - limits.d_source_m).min()))
        if boxes[0].shape[0]:
            worst["obstacle"] = min(worst["obstacle"], float((distance_to_boxes(q, *boxes) - limits.d_obstacle_m).min()))
        worst["altitude"] = min(worst["altitude"], float(np.minimum(q[..., 2] - limits.z_min_m, limits.z_max_m - q[..., 2]).min()))

    record(p)
    assert min(worst.values()) > 0.0, f"{scenario}: the initial state must be safe: {worst}"
    faults = FaultBuffer(FaultModel(0.0, extra_delay_steps), 7, range(seeds), range(N), N, 1) if extra_delay_steps else None
    for k in range(steps):
        if faults is not None:
            # Every peer one hop away, each record late by 0..D steps; a peer not heard of yet
            # is known at its start position (step 0), which every drone knows.
            saved = faults.update(saved, np.broadcast_to(np.where(eye, 0, 1), (seeds, N, N)), k)
            known_step = np.maximum(saved, 0)
        elif d_hop_m is None:
            known_step = np.full((seeds, N, N), k)
        else:
            saved = update_saved_steps(saved, hop_counts(p, d_hop_m), k, h_max)
            known_step = saved
        mask = (known_step >= 0) & ~eye
        hist = np.stack(trajectory)  # (k + 1, seeds, N, 3)
        s_idx = np.arange(seeds)[:, None, None]
        j_idx = np.arange(N)[None, None, :]
        peers = hist[np.maximum(known_step, 0), s_idx, j_idx]  # (seeds, N, N, 3)
        age = np.where(mask, k - known_step, 0).astype(float)
        to_target = p - target  # ∇C of a cost growing away from the target
        grad = to_target / np.linalg.norm(to_target, axis=-1, keepdims=True)
        r = control_step_of(p, prev, grad, np.zeros((seeds, N), np.int8), peers, mask, age, src, limits.d_source_m, *boxes, limits, rng.random((seeds, N, 2)))
        assert np.isfinite(r.next_position).all()
        prev, p = r.displacement, r.next_position
        trajectory.append(p.copy())
        record(p)
    return worst


SCENARIOS = ["head-on", "obstacle", "source", "altitude"]


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_safe_rule_never_violates_a_safety_distance(scenario):
    worst = simulate(scenario, "safe", seeds=25, steps=60)
    assert min(worst.values()) >= -1e-9, worst


@pytest.mark.parametrize("scenario", ["swap", "head-on", "source"])
def test_safe_rule_with_records_up_to_three_steps_late(scenario):
    """Records 0-3 steps late (the fault grid's extra delay): a peer's record q of age a means
    it may be anywhere within (a + 1) v_max Δt of q at the end of the step. The filter must
    keep the lower bound |p − q| − a v_max Δt on the true distance from shrinking, peer by
    peer, not merely keep the drone from approaching the old record: with the latter (fimnav
    before the fix) two of the crossing drones came 0.11 m inside d_U* (seed 97, step 9; the
    fault grid: 0.71 m)."""
    worst = simulate(scenario, "safe", seeds=100, steps=60, extra_delay_steps=3)
    assert min(worst.values()) >= -1e-9, worst


@pytest.mark.parametrize("scenario", ["head-on", "obstacle"])
def test_safe_rule_with_the_delayed_view(scenario):
    """Peers known through the multi-hop delayed view: close peers are current, farther ones
    are one step old, unreachable ones the last saved record."""
    worst = simulate(scenario, "safe", seeds=25, steps=60, d_hop_m=4.0, h_max=2)
    assert min(worst.values()) >= -1e-9, worst


def test_paper_rule_does_violate_safety_distances():
    """The reason for the safe default: activating a constraint only once it is violated (eqs.
    15-17) lets drones cross the safety distances between two steps."""
    violated = {s: {k: v for k, v in simulate(s, "paper", seeds=25, steps=60).items() if v < 0} for s in SCENARIOS}
    assert violated["head-on"].get("uav", 0.0) < 0.0, violated
    assert violated["obstacle"].get("obstacle", 0.0) < 0.0, violated
    assert violated["source"].get("source", 0.0) < 0.0, violated


SOAK_HEAD_ON_XFAIL = pytest.mark.xfail(
    strict=False,
    reason=(
        "known limitation of the safety filter found by this soak: in a 4-drone head-on squeeze the filter can "
        "leave two drones below d_U* ("
        "with the delayed view d_hop = 3 m, h_max = 2: 0.26 m, steps flagged filtered/infeasible with age-0 data "
        "of each other). See docs/paper-notes.md, 'Constraint activation'."
    ),
)


@pytest.mark.slow
@pytest.mark.parametrize("scenario", [pytest.param("head-on", marks=SOAK_HEAD_ON_XFAIL), "obstacle", "source", "altitude"])
def test_safe_rule_soak(scenario):
    for d_hop in (None, 3.0, 8.0):
        worst = simulate(scenario, "safe", seeds=200, steps=150, d_hop_m=d_hop)
        assert min(worst.values()) >= -1e-9, (d_hop, worst)


def test_two_drones_drawn_head_on_where_the_keep_out_meets_the_ceiling_keep_every_distance():
    """Two drones 8 m apart at 24 m, 1 m outside d_S* of a source known exactly (2 m up), first
    flying apart, then both drawn to one point of the keep-out circle under the 25 m ceiling
    (a constant unit gradient, mirror images of each other), each with the other's position of
    now. They meet head-on: outward is the only way out, up to 180° from the heading. A filter
    that looks one step ahead only (each clearance with its own turn-away buffer) took a step
    after which no step kept both the peer and the keep-out: both ended 0.19 m inside d_S* at
    step 9, and 0.06 m from d_U* at step 10. The loiter certificate rejects that step."""
    src = np.array([0.0, 0.0, 2.0])
    r0 = math.sqrt((LIM.d_source_m + 1.0) ** 2 - (24.0 - src[2]) ** 2)
    a = np.radians([85.0, 95.0])
    p = np.stack([r0 * np.cos(a), r0 * np.sin(a), np.full(2, 24.0)], -1)
    prev = np.stack([np.sin(a), -np.cos(a), np.zeros(2)], -1) * [[1.0], [-1.0]]  # along the circle, away from each other
    target = np.array([0.0, 44.0, 25.0])  # the point both are drawn to: inside the keep-out, at the ceiling
    worst_source, worst_uav = np.inf, np.inf
    for _ in range(40):
        to_target = target - p
        grad = -to_target / np.linalg.norm(to_target, axis=-1, keepdims=True)
        r = control_step_of(p, prev, grad, np.full(2, int(FimStatus.OK)), p[::-1, None, :], np.ones((2, 1), bool), np.zeros((2, 1)),
                         np.broadcast_to(src, (2, 3)), np.full(2, LIM.d_source_m), NO_BOX, NO_BOX, LIM, np.full((2, 2), 0.5),
                         source_exact=True)
        prev, p = r.displacement, r.next_position
        worst_source = min(worst_source, float(np.linalg.norm(p - src, axis=-1).min() - LIM.d_source_m))
        worst_uav = min(worst_uav, float(np.linalg.norm(p[0] - p[1]) - LIM.d_uav_m))
        assert (p[:, 2] <= LIM.z_max_m + 1e-9).all()
    print(f"head-on under the ceiling: smallest source margin {worst_source:+.2f} m, inter-drone {worst_uav:+.2f} m")
    assert worst_source >= 0.0 and worst_uav >= 0.0, (worst_source, worst_uav)


def test_the_loiter_path_is_the_minimum_speed_polygon_on_its_circle():
    """planner.control.loiter_path against eq. 2 and a closed form: every step v_min Δt long,
    the heading turning by exactly φ_max per step (left, then right), the tilt back to level at
    θ_max per step; once level, the vertices lie on one circle of radius
    R = v_min Δt / (2 sin(φ_max/2)), on the side of the turn."""
    from planner.control import loiter_path, loiter_radius_m, loiter_steps

    rng = np.random.default_rng(3)
    R = loiter_radius_m(LIM)
    assert R == pytest.approx(0.5 / (2.0 * math.sin(math.radians(25.0))))
    for _ in range(20):
        end = rng.uniform(-50, 50, 3)
        psi, theta = rng.uniform(-math.pi, math.pi), rng.uniform(-0.5 * math.pi, 0.5 * math.pi)
        path = loiter_path(end, psi, theta, LIM)
        assert path.shape == (2, loiter_steps(LIM), 3)
        for side, sign in ((0, 1.0), (1, -1.0)):
            pts = np.vstack([end, path[side]])
            steps = np.diff(pts, axis=0)
            assert np.linalg.norm(steps, axis=-1) == pytest.approx(np.full(len(steps), LIM.step_min_m))
            tilt = np.arcsin(steps[:, 2] / LIM.step_min_m)
            j = np.arange(1, len(steps) + 1)
            assert tilt == pytest.approx(np.sign(theta) * np.maximum(abs(theta) - j * LIM.tilt_change_max_rad, 0.0), abs=1e-9)
            heading = np.arctan2(steps[:, 1], steps[:, 0])
            turn = (np.diff(np.concatenate(([psi], heading))) + math.pi) % (2 * math.pi) - math.pi
            assert turn == pytest.approx(np.full(len(steps), sign * LIM.heading_change_max_rad))
            level = pts[np.argmax(tilt == 0.0) :]  # from the start of the first level step
            assert len(level) >= 8
            # The circle through three level vertices, and every other level vertex on it.
            a, b, c = level[0, :2], level[1, :2], level[2, :2]
            A = 2.0 * np.array([b - a, c - a])
            centre = np.linalg.solve(A, np.array([b @ b - a @ a, c @ c - a @ a]))
            assert np.linalg.norm(level[:, :2] - centre, axis=-1) == pytest.approx(np.full(len(level), R))
            assert np.ptp(level[:, 2]) == pytest.approx(0.0, abs=1e-12)
            # Left of the first level step's heading for a left turn, right for a right one.
            d = b - a
            assert sign * (d[0] * (centre - a)[1] - d[1] * (centre - a)[0]) > 0.0


def test_the_loiters_first_step_is_a_candidate_of_the_envelope():
    """A drone whose last step had a loiter certificate can fly the loiter: its first step, to
    either side, is among the safety filter's candidates for the next step."""
    from planner.control import _envelope_candidates, loiter_path

    rng = np.random.default_rng(4)
    prev = rng.normal(size=(30, 3))
    prev *= rng.uniform(LIM.step_min_m, LIM.step_max_m, (30, 1)) / np.linalg.norm(prev, axis=-1, keepdims=True)
    cand, _ = _envelope_candidates(prev, np.ones(30, bool), LIM)
    psi, theta = np.arctan2(prev[:, 1], prev[:, 0]), np.arctan2(prev[:, 2], np.hypot(prev[:, 0], prev[:, 1]))
    first = loiter_path(np.zeros((30, 3)), psi, theta, LIM)[:, :, 0, :]  # (30, 2, 3)
    gap = np.linalg.norm(cand[:, None, :, :] - first[:, :, None, :], axis=-1).min(-1)
    assert gap.max() < 1e-12


def test_a_drone_pressed_into_the_corner_of_keep_out_building_and_ceiling_keeps_every_distance():
    """One drone per seed near the corner where the source keep-out (a true, static source 2 m
    up), a building and the 25 m ceiling meet, pressed toward it by a gradient 60 % towards the
    corner and 40 % random, 200 seeds × 120 steps. Every clearance is exactly known, so the
    loiter certificate must keep them all. Without it (the one-step filter, commit 3dfa258)
    a drone ended 0.21 m inside d_S*."""
    rng = np.random.default_rng(5)
    seeds, src = 200, np.array([0.0, 0.0, 2.0])
    bmin, bmax = np.array([[6.0, 40.0, 0.0]]), np.array([[16.0, 60.0, 30.0]])
    r0 = math.sqrt((LIM.d_source_m + 2.0) ** 2 - 22.0 ** 2)
    p = np.array([0.0, r0, 24.0]) + rng.uniform(-1.0, 1.0, (seeds, 3)) * [1.0, 0.5, 0.3]
    prev = np.zeros((seeds, 3))
    corner = np.array([5.0, 46.0, 25.0])
    worst = {"source": np.inf, "obstacle": np.inf, "altitude": np.inf}
    for _ in range(120):
        g = rng.normal(size=(seeds, 3))
        toward = (p - corner) / np.linalg.norm(p - corner, axis=-1, keepdims=True)
        grad = 0.6 * toward + 0.4 * g / np.linalg.norm(g, axis=-1, keepdims=True)
        r = control_step_of(p, prev, grad, np.full(seeds, int(FimStatus.OK)), np.zeros((seeds, 1, 3)), np.zeros((seeds, 1), bool),
                         np.zeros((seeds, 1)), np.broadcast_to(src, (seeds, 3)), np.full(seeds, LIM.d_source_m), bmin, bmax, LIM,
                         rng.random((seeds, 2)), source_exact=True)
        prev, p = r.displacement, r.next_position
        worst["source"] = min(worst["source"], float((np.linalg.norm(p - src, axis=-1) - LIM.d_source_m).min()))
        worst["obstacle"] = min(worst["obstacle"], float((distance_to_boxes(p, bmin, bmax) - LIM.d_obstacle_m).min()))
        worst["altitude"] = min(worst["altitude"], float(np.minimum(LIM.z_max_m - p[:, 2], p[:, 2] - LIM.z_min_m).min()))
    print(f"corner of keep-out, building and ceiling: smallest margins {worst}")
    assert min(worst.values()) >= -1e-9, worst


def test_the_compiled_altitude_margin_is_the_former_numpy_expression_at_every_tilt() -> None:
    """The kernels' tilt buffer skips the sine where it is ≤ 0 (x in [−3, 0]): bit-identical to
    the former numpy expression Σ max(0, sin(Θ − k θ_max)) over a dense grid of tilts, those with
    Θ − k θ_max beyond −π (where the sine is positive again) and the edges −3 and 0 included."""
    import numba

    from planner import kernels as K
    from planner.control import kernel_limits
    from tests.reference_numpy.planner.control import _tilt_buffer

    @numba.njit
    def margins(z: np.ndarray, tilt: np.ndarray, lim: np.ndarray) -> np.ndarray:
        out = np.empty(tilt.shape[0])
        for i in range(tilt.shape[0]):
            out[i] = K.altitude_margin(z[i], tilt[i], lim)
        return out

    limits = Limits()
    tmax = limits.tilt_change_max_rad
    edges = np.array([k * tmax + e for k in (1.0, 2.0, 3.0) for e in (0.0, -3.0, -math.pi, 3.0 - 2.0 * math.pi)])
    tilt = np.concatenate((np.linspace(-math.pi, math.pi, 20001), edges, np.nextafter(edges, 10.0), np.nextafter(edges, -10.0)))
    z = np.linspace(limits.z_min_m - 1.0, limits.z_max_m + 1.0, tilt.size)
    expected = np.minimum(limits.z_max_m - z - _tilt_buffer(tilt, limits), z - limits.z_min_m - _tilt_buffer(-tilt, limits))
    np.testing.assert_array_equal(margins(z, tilt, kernel_limits(limits)), expected)

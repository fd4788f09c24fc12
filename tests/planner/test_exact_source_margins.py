"""Where the safe rule holds a drone, about an estimate and about a source known exactly.

References are closed forms of the kinematics, measured on closed-loop trajectories: a drone
pressed against the ceiling is held within v_max Δt sin θ_max of it with a static source known
exactly (one level step's climb) and within 2 v_max Δt + b of it about an estimate; a drone
pressed towards the source is held about d_S* + v_max Δt + b, resp. d_S* + 2 v_max Δt + b,
one step's bounce either way. No step ends outside the box or inside d_S* + b.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from planner import FimStatus, Limits
from planner.control import altitude_activation_margin_m, source_activation_margin_m
from tests.planner.stepping import control_step_of

LIM = Limits()  # the paper's section V values: 0.5-1 m/step, 50° per step, z in [2, 25] m
NO_BOX = np.zeros((0, 3))
SOURCE = np.array([0.0, 0.0, 2.0])


def _fly(p0: np.ndarray, grad_of, exact: bool, steps: int = 120) -> np.ndarray:
    """Positions (steps + 1, 3) of one drone following ``grad_of(p)`` under the safe rule."""
    p, prev, out = p0.astype(float), np.zeros(3), [p0.astype(float)]
    for _ in range(steps):
        r = control_step_of(
            p, prev, grad_of(p), int(FimStatus.OK), np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0),
            SOURCE, LIM.d_source_m, NO_BOX, NO_BOX, LIM, np.array([0.5, 0.5]), source_exact=exact,
        )
        prev, p = np.asarray(r.displacement), np.asarray(r.next_position)
        out.append(p)
    return np.array(out)


def test_margins_are_the_closed_forms() -> None:
    b = LIM.turn_buffer_m
    assert b == pytest.approx(math.cos(math.radians(50.0)))
    assert source_activation_margin_m(LIM) == pytest.approx(2.0 + b)
    assert source_activation_margin_m(LIM, exact=True) == pytest.approx(1.0 + b)
    assert altitude_activation_margin_m(LIM) == pytest.approx(2.0 + b)
    assert altitude_activation_margin_m(LIM, exact_source=True) == pytest.approx(math.sin(math.radians(50.0)))
    paper = Limits(activation="paper")
    assert source_activation_margin_m(paper, exact=True) == altitude_activation_margin_m(paper, exact_source=True) == 0.0


@pytest.mark.parametrize("exact", [True, False])
def test_a_drone_pressed_up_is_held_one_climb_below_the_ceiling(exact: bool) -> None:
    # Cost falls upwards and to the east: the drone climbs while flying level-ish, far from
    # the source (its keep-out never acts).
    path = _fly(np.array([200.0, 0.0, 10.0]), lambda p: np.array([-0.3, 0.0, -1.0]), exact)
    z = path[:, 2]
    assert z.max() <= LIM.z_max_m + 1e-9
    # Held: below the ceiling by at most the margin, and within one level climb of it (the
    # constraint is inactive right at the margin, so the drone climbs again and is brought back).
    held = LIM.z_max_m - z[-40:]
    margin = math.sin(math.radians(50.0)) if exact else 2.0 + LIM.turn_buffer_m
    assert held.max() <= margin + 1e-6
    assert held.min() >= margin - math.sin(math.radians(50.0)) - 1e-6
    assert held.max() >= margin - 1e-3  # it does come back to the margin


@pytest.mark.parametrize("exact", [True, False])
def test_a_drone_pressed_in_is_held_one_own_step_beyond_the_keep_out(exact: bool) -> None:
    # Cost falls towards the source (level): the drone flies in and is held at the margin,
    # circling (v_min > 0) between d_S* + b and d_S* + margin.
    path = _fly(np.array([80.0, 0.0, 12.0]), lambda p: (p - SOURCE) * np.array([1.0, 1.0, 0.0]) / np.linalg.norm(p - SOURCE), exact, steps=200)
    d = np.linalg.norm(path - SOURCE, axis=1)
    b = LIM.turn_buffer_m
    assert d.min() >= LIM.d_source_m + b - 1e-9  # the filter's end-of-step requirement
    margin = (1.0 if exact else 2.0) + b
    tail = d[-60:]
    # It bounces about its margin: brought back to it, then a step in at v_min or more.
    assert tail.max() <= LIM.d_source_m + margin + LIM.step_max_m
    assert np.median(tail) <= LIM.d_source_m + margin
    assert np.median(tail) >= LIM.d_source_m + margin - LIM.step_max_m


def test_the_exact_source_lets_drones_closer_than_the_estimate() -> None:
    inward = lambda p: (p - SOURCE) * np.array([1.0, 1.0, 0.0]) / np.linalg.norm(p - SOURCE)  # noqa: E731
    d = {ex: np.median(np.linalg.norm(_fly(np.array([80.0, 0.0, 12.0]), inward, ex, 200)[-60:] - SOURCE, axis=1)) for ex in (True, False)}
    assert d[False] - d[True] == pytest.approx(LIM.step_max_m, abs=0.25)

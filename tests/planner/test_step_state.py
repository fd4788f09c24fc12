"""One drone's step as plain data (planner.step): the scene and the carried state of
planner.agent.plan, batched or not.

References: the public functions the compiled step is made of (the cost of eq. 6 from
planner.fim's fisher_information and cost_gradient with the predicted line of sight, the
control step of planner.control.control_step), each drone of a batch planned alone, and the
carried state's rules restated here (the window of own ranges, the track, the drift).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from planner import kernels as K
from planner.agent import _scene_cost, plan
from planner.control import ControlScene, control_step
from planner.step import OWN_RANGE_WINDOW, OWN_TRACK_STEPS, DroneState, StepScene
from tests.planner.stepping import planner_config
from tests.support.kernels import jit_only

BOXES = (np.array([[20.0, 30.0, 0.0], [-40.0, 10.0, 0.0]]), np.array([[30.0, 45.0, 18.0], [-30.0, 25.0, 12.0]]))
N = 5


def scenes(rng: np.random.Generator, m: int) -> tuple[StepScene, DroneState]:
    """m trials × N drones around the origin, views of records 0-2 steps old, some LOS flags off,
    estimates a few metres off the source at (0, 0, 2)."""
    pos = rng.uniform([-60.0, -60.0, 4.0], [60.0, 60.0, 22.0], (m, N, 3))
    view = np.broadcast_to(pos[:, None], (m, N, N, 3)) + rng.normal(0.0, 0.5, (m, N, N, 3))
    valid = rng.random((m, N, N)) < 0.9
    idx = np.broadcast_to(np.arange(N), (m, N))
    valid[:, np.arange(N), np.arange(N)] = True
    view[:, np.arange(N), np.arange(N)] = pos
    k = 7
    saved = np.where(valid, k - rng.integers(0, 3, (m, N, N)), -1)
    saved[:, np.arange(N), np.arange(N)] = k
    info = np.broadcast_to(np.diag([0.05, 0.05, 0.01]), (m, N, 3, 3)).copy()
    scene = StepScene(
        k, idx, pos, rng.uniform(30.0, 90.0, (m, N)), rng.random((m, N)) < 0.8, view, valid, rng.random((m, N, N)) < 0.8, saved,
        np.where(np.eye(N, dtype=bool), 0, 1) + np.zeros((m, N, N), int), np.array([0.0, 0.0, 2.0]) + rng.normal(0.0, 3.0, (m, N, 3)),
        info, rng.random((m, N)) < 0.9, rng.random((m, N, 2)),
    )  # fmt: skip
    state = dataclasses.replace(DroneState.initial((m, N), N), previous_step_m=rng.normal(0.0, 0.6, (m, N, 3)))
    return scene, state


def config() -> object:
    return planner_config([True, False, True, True, False], [False, True, True, False, True], boxes=BOXES, start_positions_m=np.zeros((N, 3)))


def test_the_compiled_cost_is_the_public_functions_cost(rng: np.random.Generator) -> None:
    """The whole step's kernel computes the cost of eq. 6 as planner.fim's public functions do
    with the predicted line of sight of planner.agent.own_los_weight (the staged form, also taken
    for components beyond range and bearing)."""
    cfg = config()
    scene, state = scenes(rng, 4)
    fused = plan(cfg, scene, state).cost  # type: ignore[arg-type]
    staged = _scene_cost(cfg, scene, scene.own_mask, np.asarray(scene.estimate_m))  # type: ignore[arg-type]
    assert (fused.status == staged.status).all()
    np.testing.assert_allclose(fused.gradient, staged.gradient, rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(fused.value, staged.value, rtol=1e-12)


def test_a_batch_is_its_drones_planned_one_by_one(rng: np.random.Generator) -> None:
    """(M, N) at once equals each drone alone (no leading dimension), bit for bit: the step and
    every array of the next state."""
    cfg = config()
    scene, state = scenes(rng, 3)
    batch = plan(cfg, scene, state)  # type: ignore[arg-type]
    for i in np.ndindex(scene.batch):
        one = plan(cfg, StepScene(scene.step_index, *(np.asarray(getattr(scene, f.name))[i] for f in dataclasses.fields(scene)[1:-1]), None), DroneState(*(getattr(state, f.name)[i] for f in dataclasses.fields(state))))  # type: ignore[arg-type]  # fmt: skip
        np.testing.assert_array_equal(one.step.next_position, batch.step.next_position[i])
        assert bool(one.step.filtered) == bool(batch.step.filtered[i]) and bool(one.loiter) == bool(batch.loiter[i])
        for f in dataclasses.fields(DroneState):
            np.testing.assert_array_equal(getattr(one.state, f.name), getattr(batch.state, f.name)[i], err_msg=f.name)


@jit_only
def test_read_only_inputs_reuse_the_one_compiled_step(rng: np.random.Generator) -> None:
    """A one-trial run's inputs are read-only broadcast views that look C-contiguous (a (1, N)
    broadcast of arange(N)); numba would compile the step again for them (another array type,
    ~20 s): they are copied to the one type the kernel is compiled for, and plan the same."""
    cfg = config()
    scene, state = scenes(rng, 1)
    ro = {f.name: np.broadcast_to(np.asarray(getattr(scene, f.name)), np.shape(getattr(scene, f.name))) for f in dataclasses.fields(scene)[1:-1]}
    assert not ro["own_index"].flags.writeable and ro["own_index"].flags.c_contiguous
    frozen = DroneState(*(np.broadcast_to(a, a.shape) for a in (getattr(state, f.name) for f in dataclasses.fields(state))))
    a = plan(cfg, scene, state)  # type: ignore[arg-type]
    b = plan(cfg, dataclasses.replace(scene, **ro), frozen)  # type: ignore[arg-type]
    np.testing.assert_array_equal(a.step.next_position, b.step.next_position)
    assert len(K.plan_batch.signatures) == 1, K.plan_batch.signatures


def test_the_control_step_is_control_step_of_the_planned_scene(rng: np.random.Generator) -> None:
    """With its peers' rows, keep-out and gradient, a planned step is control_step's (the same
    compiled control kernel behind both entries)."""
    cfg = planner_config([True, True], [True, True], boxes=BOXES)
    p = np.array([[0.0, 60.0, 10.0], [3.0, 62.0, 10.0]])
    scene = StepScene(0, np.array(0), p[0], np.array(70.0), np.array(True), p, np.ones(2, bool), np.ones(2, bool), np.zeros(2, int), np.array([0, 1]),
                      np.array([0.0, 0.0, 2.0]), np.eye(3) * 100.0, np.array(True), np.array([0.5, 0.5]))  # fmt: skip
    state = dataclasses.replace(DroneState.initial((), 2), previous_step_m=np.array([0.0, -1.0, 0.0]))
    r = plan(cfg, scene, state)  # type: ignore[arg-type]
    mask = np.array([False, True])
    scene_c = ControlScene(p[0], state.previous_step_m, r.cost.gradient, r.cost.status, p, mask, np.zeros(2), scene.estimate_m, r.keepout_m, scene.perturbation_uniforms, None, r.state.drift_m)  # fmt: skip
    c = control_step(scene_c, cfg.limits, *BOXES)
    np.testing.assert_array_equal(c.next_position, r.step.next_position)


def test_the_carried_state_takes_in_the_step() -> None:
    """The own range enters the window (oldest first, W long), the position the track (slot k mod
    T), the last step and keep-out are the step's; a peer's drift is its step between its two
    newest records; the own position at a peer's newest record comes from the track."""
    cfg = planner_config([True, True], [False, False])
    state = DroneState.initial((), 2)
    track = [np.array([0.0, 0.0, 10.0]) + k * np.array([0.8, 0.0, 0.0]) for k in range(12)]
    peer = [np.array([0.0, 30.0, 10.0]) + k * np.array([0.0, -0.5, 0.1]) for k in range(12)]
    for k in range(12):
        late = max(k - 2, 0)  # the peer's record arrives two steps late
        scene = StepScene(k, np.array(0), track[k], np.array(40.0 + k), np.array(k % 2 == 0), np.stack([track[k], peer[late]]), np.ones(2, bool), np.ones(2, bool),
                          np.array([k, late]), np.array([0, 1]), np.array([0.0, 100.0, 2.0]), np.eye(3), np.array(True), np.array([0.5, 0.5]))  # fmt: skip
        r = plan(cfg, scene, state)  # type: ignore[arg-type]
        state = r.state
        np.testing.assert_array_equal(state.previous_step_m, r.step.displacement)
        assert state.keepout_m == r.keepout_m and bool(state.loitering) == bool(r.loiter)
    np.testing.assert_array_equal(state.own_range_m, 40.0 + np.arange(12 - OWN_RANGE_WINDOW, 12))
    assert state.own_range_los.tolist() == [k % 2 == 0 for k in range(12 - OWN_RANGE_WINDOW, 12)]
    np.testing.assert_array_equal(state.track_m[11 % OWN_TRACK_STEPS], track[11])
    np.testing.assert_allclose(state.drift_m[1], [0.0, -0.5, 0.1], atol=1e-12)
    np.testing.assert_array_equal(state.own_then_m[1], track[9])  # the peer's newest record is of step 9
    np.testing.assert_array_equal(state.drift_saved_steps, [11, 9])


def test_the_states_edits() -> None:
    state = DroneState.initial((), 3)
    assert state.batch == () and np.isnan(state.keepout_m) and not state.loitering
    moved = dataclasses.replace(state, previous_step_m=np.array([1.0, 0.0, 0.0]), keepout_m=np.array(80.0))
    assert not moved.without_step().previous_step_m.any() and moved.previous_step_m.any()  # frozen: a new value
    assert np.isnan(moved.without_keepout().keepout_m) and np.isnan(moved.without_keepout().keepout_centre_m).all()
    tracked = state.tracked(70, np.array([1.0, 2.0, 3.0]))
    assert tracked.track_steps[70 % OWN_TRACK_STEPS] == 70 and (state.track_steps == -1).all()
    replayed = state.replayed([(0, np.zeros(3), 41.0, True), (1, np.ones(3), np.nan, False)])
    assert replayed.own_range_m[-2] == 41.0 and np.isnan(replayed.own_range_m[-1]) and replayed.own_range_los[-2:].tolist() == [True, False]
    np.testing.assert_array_equal(replayed.track_m[1], np.ones(3))


def test_a_record_older_than_the_track_takes_the_current_position() -> None:
    """A peer's record more than T − 1 steps late (the track no longer holds its step): the own
    position at that record is taken as the current one."""
    cfg = planner_config([True, True], [False, False])
    state = DroneState.initial((), 2).tracked(1, np.array([-9.0, -9.0, 9.0]))
    now = np.array([5.0, 5.0, 10.0])
    k, saved = OWN_TRACK_STEPS + 1, 1  # step 1's slot now holds step k
    scene = StepScene(k, np.array(0), now, np.array(np.nan), np.array(True), np.stack([now, [0.0, 40.0, 10.0]]), np.ones(2, bool), np.ones(2, bool),
                      np.array([k, saved]), np.array([0, 1]), np.array([0.0, 100.0, 2.0]), np.eye(3), np.array(True), np.array([0.5, 0.5]))  # fmt: skip
    np.testing.assert_array_equal(plan(cfg, scene, state).state.own_then_m[1], now)  # type: ignore[arg-type]

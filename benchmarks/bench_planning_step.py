"""Benchmark: one drone's planning step, compiled (numba), against the numpy planner and scipy's
SLSQP measured in the same run.

One planning step of drone i (the hot path of every planner process and of the simulator):

1. ``fisher_information`` over drone i's view (N drones, mixed roles, LOS flags from the
   records) at the source estimate (eqs. 10-12);
2. ``cost_gradient``: A-optimality cost tr J⁻¹ and its gradient w.r.t. p_i (eqs. 6, 13);
3. ``control_step``: activation, projection (eq. 14), speed / turn-rate limits, altitude box
   and the safety filter (default ``activation="safe"``).

The compiled step is timed in four forms: the three public functions above; the same three
kernels called on arrays prepared once (the public functions' Python argument handling left
out); ``planner.agent.plan``, the whole step as the simulator and the planner node run it (own
link's predicted LOS, FIM, gradient, keep-out, peers by hop count, control step, carried state:
one kernel call); and ``plan`` of BATCH/N copies of drone 0's step in one call, per drone (the
simulator's batch of trials × drones).

Baselines, in the same run and the same process:

* the numpy planner of commit 48f7e03 (the last before the compiled core): its ``planner``
  package is exported with ``git archive`` into a temporary directory, renamed ``planner_np``
  and imported from there (nothing of it is kept in the repository); the same three calls;
* the same one-step problem (problem 7 restricted to drone i's next position) solved by
  ``scipy.optimize.minimize(method="SLSQP")``: minimise the A cost of J with drone i moved to
  p_i + u, over u, subject to v_min·Δt ≤ |u| ≤ v_max·Δt, heading change ≤ φ_max, tilt change ≤
  θ_max, z_min ≤ z ≤ z_max, distance ≥ d_U* to every peer, ≥ d_S* to the source estimate and
  ≥ d_O* to every obstacle. SLSQP gets the analytic cost gradient of planner.fim.cost_gradient
  (compiled) and analytic constraint Jacobians, and starts from the previous step (a feasible
  point); "SLSQP-fd" uses scipy's finite differences. Both are given the same J of the others.

Scene: the paper's case study as fimnav's mission files set it (source and buildings read
from missions/paper/heterogeneous.yaml), the first ten drones on the paper's ellipse centred at
(0, 150, 8) m; for N = 100 and 1000 the others are spread over a 400 m × 200 m area behind
them. Roles cycle ranging / bearing / joint as in the paper's heterogeneous case.

Usage (from the repository root, which must hold commit 48f7e03):
    python benchmarks/bench_planning_step.py            # N = 10, 100, 1000
    python benchmarks/bench_planning_step.py --near-building
    python benchmarks/bench_planning_step.py --sizes 10 --repeats 5000
    python benchmarks/bench_planning_step.py --in-study missions/paper/bearing.yaml  # the kernel inside a study

The machine is shared (2 cores) and noisy: the script reports medians over many repeats
(and the interquartile range), never means.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import importlib
import io
import math
import re
import subprocess
import sys
import tarfile
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any, Callable

import numpy as np
from scipy.optimize import minimize

from missions.format.loader import load_mission
from planner import Channel, FimStatus, Limits, cost, cost_gradient, distance_to_boxes, fisher_information, line_of_sight
from planner import kernels as K
from planner.agent import plan
from planner.config import PlannerConfig
from planner.control import ControlScene, control_step, kernel_limits
from planner.estimator import EstimatorConfig
from planner.geometry import distance_to_boxes_with_gradient
from planner.step import DroneState, StepScene

ROOT = Path(__file__).resolve().parents[1]
#: Drone steps planned in one call (the simulator's batch of trials × drones): BATCH // N copies
#: of drone 0's step (200 at N = 10, as 20 trials of the paper's ten drones).
BATCH = 2000
#: The last commit of the numpy planner (the baseline).
NUMPY_COMMIT = "48f7e03"
MISSION_FILE = ROOT / "missions" / "paper" / "heterogeneous.yaml"
_MISSION = load_mission(MISSION_FILE)
SOURCE = np.array(_MISSION.source.position_m, dtype=float)
BOXES_MIN = np.array([o.min_m for o in _MISSION.obstacles], dtype=float).reshape(-1, 3)
BOXES_MAX = np.array([o.max_m for o in _MISSION.obstacles], dtype=float).reshape(-1, 3)
CHANNEL = Channel(gamma=2.0, sigma_ratio_los=1.7, sigma_ratio_nlos=3.2, sigma_bearing_rad=math.radians(10.0))
LIMITS = Limits()  # paper: d_U*=1, d_S*=50, d_O*=5 m, 0.5-1 m/step, 50°/step, z in [2, 25] m


@dataclass
class Scene:
    positions: np.ndarray  # (N, 3)
    ranging: np.ndarray
    bearing: np.ndarray
    los: np.ndarray
    prev: np.ndarray  # drone 0's previous step (3,)


def make_scene(n: int, seed: int = 0, near_building: bool = False) -> Scene:
    """The scene with n drones; ``near_building`` puts drone 0 6.3 m from building B1 (inside
    the activation margin of d_O* = 5 m) with a peer 3 m away, heading towards both, so the
    projection and the safety filter do real work."""
    rng = np.random.default_rng(seed)
    k = np.arange(min(n, 10))
    ang = 2.0 * np.pi * k / 10
    pos = [np.stack([20.0 * np.cos(ang), np.full(k.shape, 150.0), 8.0 + 5.0 * np.sin(ang)], -1)]
    have = pos[0]
    while sum(len(p) for p in pos) < n:
        cand = np.array([rng.uniform(-200, 200), rng.uniform(110, 310), rng.uniform(4.0, 23.0)])
        allp = np.concatenate(pos)
        if np.min(np.linalg.norm(allp - cand, axis=1)) > 3.0 and distance_to_boxes(cand, BOXES_MIN, BOXES_MAX) > 10.0:
            pos.append(cand[None])
    positions = np.concatenate(pos)[:n]
    del have
    role = np.arange(n) % 3  # 0 ranging, 1 bearing, 2 joint
    ranging = role != 1
    bearing = role != 0
    los = line_of_sight(positions, SOURCE, BOXES_MIN, BOXES_MAX)
    prev = np.array([0.0, -1.0, 0.0])  # flying south, towards the source
    if near_building:
        positions = positions.copy()
        b1_max = BOXES_MAX[0]  # drone 0 6 m east and 2 m north of B1's north-east edge
        positions[0] = [b1_max[0] + 6.0, b1_max[1] + 2.0, 8.0]
        positions[1] = [b1_max[0] + 4.0, b1_max[1] - 0.2, 8.0]  # a peer 3 m away, towards the building
        los = line_of_sight(positions, SOURCE, BOXES_MIN, BOXES_MAX)
        prev = np.array([-0.6, -0.8, 0.0])
    return Scene(positions, ranging, bearing, los, prev)


def planning_step(scene: Scene, src: np.ndarray, mask: np.ndarray, age: np.ndarray, uni: np.ndarray):
    """fimnav (compiled): FIM over the view, cost and gradient, control step (drone 0)."""
    J = fisher_information(src, scene.positions, scene.ranging, scene.bearing, scene.los, CHANNEL)
    cg = cost_gradient(J, src, scene.positions[0], scene.ranging[0], scene.bearing[0], scene.los[0], CHANNEL, "A")
    step = ControlScene(scene.positions[0], scene.prev, cg.gradient, cg.status, scene.positions, mask, age, src, LIMITS.d_source_m, uni)
    return control_step(step, LIMITS, BOXES_MIN, BOXES_MAX)


def kernel_calls(scene: Scene, src: np.ndarray, mask: np.ndarray, age: np.ndarray, uni: np.ndarray) -> Callable[[], object]:
    """The same three steps as :func:`planning_step`, calling the compiled kernels directly on
    arrays prepared once (what the public functions cost without their Python argument handling)."""
    n = len(scene.positions)
    one = (src[None], scene.positions[None], scene.ranging[None], scene.bearing[None], scene.los.astype(float)[None])
    J, out, u, flags = np.zeros((1, 3, 3)), np.empty((1, 14)), np.empty((1, 3)), np.empty((1, 7), dtype=bool)
    own = (scene.positions[0][None], scene.ranging[:1].copy(), scene.bearing[:1].copy(), scene.los[:1].astype(float), np.zeros((1, 3)))
    lim, chan = kernel_limits(LIMITS), CHANNEL.kernel_array
    peers = (scene.positions[None], mask[None], age[None], np.zeros((1, n, 3)), np.full((1, n, 3), np.nan))
    tail = (src[None], np.full(1, LIMITS.d_source_m), uni[None], BOXES_MIN, BOXES_MAX, lim, np.nan, math.radians(20.0), False, u, flags)

    def run() -> None:
        K.fim_batch(*one, chan, J)
        K.cost_gradient_batch(J, src[None], own[0], *own[1:], False, chan, False, out)
        status = out[:, 4].astype(np.int8)
        K.control_batch(own[0], scene.prev[None], out[:, 1:4].copy(), status, *peers, *tail)

    return run


def plan_inputs(scene: Scene, src: np.ndarray, copies: int = 0) -> tuple[PlannerConfig, StepScene, DroneState]:
    """Drone 0's whole planning step as the simulator and the planner node run it
    (:func:`planner.agent.plan`: own link's predicted LOS, FIM, cost gradient, keep-out, peers by
    hop count, control step, carried state), its view the scene's positions of this step, all
    heard directly; ``copies`` > 0: that many copies of it in one call (the simulator's batch)."""
    n = len(scene.positions)
    config = PlannerConfig(
        channel=CHANNEL, limits=LIMITS, criterion="A", component_masks={"range": scene.ranging, "bearing": scene.bearing},
        boxes_min_m=BOXES_MIN, boxes_max_m=BOXES_MAX, d_hop_m=_MISSION.comms.d_hop_m, start_positions_m=None, estimator=EstimatorConfig(),
    )  # fmt: skip
    b = (copies,) if copies else ()
    rep = (lambda a: np.broadcast_to(a, b + np.shape(a)).copy()) if copies else (lambda a: np.asarray(a))
    J = fisher_information(src, scene.positions, scene.ranging, scene.bearing, scene.los, CHANNEL)
    step = StepScene(
        step_index=5, own_index=rep(np.array(0)), own_position_m=rep(scene.positions[0]),
        own_range_m=rep(np.array(np.linalg.norm(scene.positions[0] - SOURCE))), own_los=rep(np.array(bool(scene.los[0]))),
        view_positions_m=rep(scene.positions), view_valid=rep(np.ones(n, bool)), view_los=rep(scene.los),
        saved_steps=rep(np.full(n, 5, dtype=np.int64)), hops=rep(np.ones(n, dtype=np.int64)), estimate_m=rep(src), information=rep(J),
        observable=rep(np.array(True)), perturbation_uniforms=rep(np.array([0.3, 0.7])), lost_contact=rep(np.zeros(n, bool)),
    )  # fmt: skip
    state = DroneState.initial(b, n)
    state = plan(config, step, dataclasses.replace(state, previous_step_m=rep(scene.prev))).state  # a carried state
    return config, step, state


def numpy_planner(commit: str = NUMPY_COMMIT) -> ModuleType:
    """The ``planner`` package of ``commit`` (the numpy planner), exported into a temporary
    directory as ``planner_np`` and imported from there."""
    archive = subprocess.run(["git", "archive", commit, "planner"], cwd=ROOT, capture_output=True, check=True).stdout
    tmp = Path(tempfile.mkdtemp(prefix="fimnav-numpy-planner-"))
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(tmp, filter="data")
    for path in (tmp / "planner").rglob("*.py"):
        path.write_text(re.sub(r"\bplanner\b(?=[ .\"'])", "planner_np", path.read_text(encoding="utf-8")), encoding="utf-8")
    (tmp / "planner").rename(tmp / "planner_np")
    sys.path.insert(0, str(tmp))
    return importlib.import_module("planner_np")


def numpy_planning_step(np_planner: Any, scene: Scene, src: np.ndarray, mask: np.ndarray, age: np.ndarray, uni: np.ndarray, channel: Any, limits: Any):
    """The same step with the numpy planner of :data:`NUMPY_COMMIT`."""
    J = np_planner.fisher_information(src, scene.positions, scene.ranging, scene.bearing, scene.los, channel)
    cg = np_planner.cost_gradient(J, src, scene.positions[0], scene.ranging[0], scene.bearing[0], scene.los[0], channel, "A")
    return np_planner.control_step(
        scene.positions[0], scene.prev, cg.gradient, cg.status, scene.positions, mask, age, src,
        limits.d_source_m, BOXES_MIN, BOXES_MAX, limits, uni,
    )


def slsqp_step(scene: Scene, src: np.ndarray, analytic: bool = True) -> tuple[np.ndarray, bool, int]:
    """The same one-step problem solved by SLSQP; returns (u, success, iterations).

    ``analytic``: SLSQP gets the analytic cost gradient and constraint Jacobians; otherwise it
    estimates them by finite differences (scipy's default, what a quick baseline would do).
    """
    p = scene.positions[0]
    peers = scene.positions[1:]
    J_others = fisher_information(src, peers, scene.ranging[1:], scene.bearing[1:], scene.los[1:], CHANNEL)
    r0, b0, l0 = scene.ranging[0:1], scene.bearing[0:1], scene.los[0:1]
    lim = LIMITS
    prev = scene.prev
    prev_h = prev[:2]
    prev_tilt = math.atan2(prev[2], math.hypot(prev[0], prev[1]))
    cos_h = math.cos(lim.heading_change_max_rad)

    def fim(u: np.ndarray) -> np.ndarray:
        return J_others + fisher_information(src, (p + u)[None], r0, b0, l0, CHANNEL)

    def fun(u: np.ndarray) -> tuple[float, np.ndarray]:
        cg = cost_gradient(fim(u), src, p + u, r0[0], b0[0], l0[0], CHANNEL, "A")
        if cg.status == FimStatus.SINGULAR:
            return 1e30, np.zeros(3)
        return float(cg.value), cg.gradient

    def cons(u: np.ndarray) -> np.ndarray:
        q = p + u
        s2 = u @ u
        uh = u[:2]
        nh = math.hypot(*uh)
        tilt = math.atan2(u[2], nh)
        d_peer = np.sqrt(((q - peers) ** 2).sum(-1))
        return np.concatenate([
            [lim.step_max_m**2 - s2, s2 - lim.step_min_m**2,
             uh @ prev_h - cos_h * nh * math.hypot(*prev_h),
             lim.tilt_change_max_rad - (tilt - prev_tilt), lim.tilt_change_max_rad + (tilt - prev_tilt),
             lim.z_max_m - q[2], q[2] - lim.z_min_m,
             np.linalg.norm(q - src) - lim.d_source_m,
             float(distance_to_boxes(q, BOXES_MIN, BOXES_MAX)) - lim.d_obstacle_m],
            d_peer - lim.d_uav_m,
        ])

    def cons_jac(u: np.ndarray) -> np.ndarray:
        q = p + u
        uh = u[:2]
        nh = max(math.hypot(*uh), 1e-12)
        s2 = u @ u
        # d tilt / du for tilt = atan2(u_z, |u_h|)
        dtilt = np.array([-u[2] * u[0] / nh, -u[2] * u[1] / nh, nh]) / max(s2, 1e-24)
        dh = np.array([prev_h[0] - cos_h * math.hypot(*prev_h) * u[0] / nh, prev_h[1] - cos_h * math.hypot(*prev_h) * u[1] / nh, 0.0])
        ds = (q - src) / np.linalg.norm(q - src)
        _, dob = distance_to_boxes_with_gradient(q, BOXES_MIN, BOXES_MAX)
        diff = q - peers
        dpe = diff / np.sqrt((diff**2).sum(-1))[:, None]
        ez = np.array([0.0, 0.0, 1.0])
        return np.vstack([-2 * u, 2 * u, dh, -dtilt, dtilt, -ez, ez, ds, dob, dpe])

    # Stop when the cost changes by less than 1e-10 of itself: far tighter than the gap between
    # a one-step gradient method and the optimum, loose enough not to chase round-off.
    ftol = 1e-10 * abs(fun(np.zeros(3))[0])
    if analytic:
        res = minimize(fun, prev.copy(), jac=True, method="SLSQP", constraints=[{"type": "ineq", "fun": cons, "jac": cons_jac}], options={"maxiter": 100, "ftol": ftol})
    else:
        res = minimize(lambda u: fun(u)[0], prev.copy(), method="SLSQP", constraints=[{"type": "ineq", "fun": cons}], options={"maxiter": 100, "ftol": ftol})
    return res.x, bool(res.success), int(res.nit)


def a_cost_after(scene: Scene, src: np.ndarray, u: np.ndarray) -> float:
    q = scene.positions.copy()
    q[0] = q[0] + u
    return float(cost(fisher_information(src, q, scene.ranging, scene.bearing, scene.los, CHANNEL), "A")[0])


def plain_violation(scene: Scene, src: np.ndarray, u: np.ndarray) -> float:
    """Largest violation (m) of the plain safety distances and altitude box by p_0 + u (≤ 0 ok)."""
    q = scene.positions[0] + u
    lim = LIMITS
    v = [
        lim.d_uav_m - np.min(np.linalg.norm(scene.positions[1:] - q, axis=1)),
        lim.d_source_m - np.linalg.norm(q - src),
        lim.d_obstacle_m - float(distance_to_boxes(q, BOXES_MIN, BOXES_MAX)),
        lim.z_min_m - q[2],
        q[2] - lim.z_max_m,
        np.linalg.norm(u) - lim.step_max_m,
        lim.step_min_m - np.linalg.norm(u),
    ]
    return float(max(v))


def timeit(fn: Callable[[], object], repeats: int, warmup: int = 20) -> tuple[float, float, float]:
    """Median and quartiles of the wall time of fn() in seconds."""
    for _ in range(warmup):
        fn()
    t = np.empty(repeats)
    gc_was = gc.isenabled()
    gc.disable()
    try:
        for k in range(repeats):
            t0 = time.perf_counter_ns()
            fn()
            t[k] = time.perf_counter_ns() - t0
    finally:
        if gc_was:
            gc.enable()
    q1, med, q3 = np.percentile(t, [25, 50, 75]) * 1e-9
    return med, q1, q3


def measure(n: int, near_building: bool, repeats: int, npl: Any) -> dict[str, Any]:
    """Timings and results of one N (drone 0's step), compiled, numpy and SLSQP, interleaved."""
    # The source estimate is off the truth (as in flight): 3 m east, 2 m north, 1 m up.
    src = SOURCE + np.array([3.0, 2.0, 1.0])
    scene = make_scene(n, near_building=near_building)
    mask = np.ones(n, bool)
    mask[0] = False
    age = np.zeros(n)
    uni = np.array([0.3, 0.7])
    np_channel = npl.Channel(CHANNEL.gamma, CHANNEL.sigma_ratio_los, CHANNEL.sigma_ratio_nlos, CHANNEL.sigma_bearing_rad)
    np_limits = npl.Limits()
    ours = planning_step(scene, src, mask, age, uni)
    theirs = numpy_planning_step(npl, scene, src, mask, age, uni, np_channel, np_limits)
    t_ours = timeit(lambda: planning_step(scene, src, mask, age, uni), repeats)
    t_numpy = timeit(lambda: numpy_planning_step(npl, scene, src, mask, age, uni, np_channel, np_limits), max(30, repeats // 10), warmup=5)
    t_fim = timeit(lambda: fisher_information(src, scene.positions, scene.ranging, scene.bearing, scene.los, CHANNEL), repeats)
    J = fisher_information(src, scene.positions, scene.ranging, scene.bearing, scene.los, CHANNEL)
    t_grad = timeit(lambda: cost_gradient(J, src, scene.positions[0], scene.ranging[0], scene.bearing[0], scene.los[0], CHANNEL, "A"), repeats)
    t_los = timeit(lambda: line_of_sight(scene.positions, src, BOXES_MIN, BOXES_MAX), repeats)
    t_kernels = timeit(kernel_calls(scene, src, mask, age, uni), repeats)
    config, step, state = plan_inputs(scene, src)
    t_plan = timeit(lambda: plan(config, step, state), repeats)
    copies = max(1, BATCH // n)
    config, step, state = plan_inputs(scene, src, copies=copies)
    t_batch = timeit(lambda: plan(config, step, state), max(30, repeats // copies), warmup=3)
    u_slsqp, ok, nit = slsqp_step(scene, src)
    t_slsqp = timeit(lambda: slsqp_step(scene, src), max(30, repeats // 20), warmup=3)
    u_fd, ok_fd, nit_fd = slsqp_step(scene, src, analytic=False)
    t_fd = timeit(lambda: slsqp_step(scene, src, analytic=False), max(30, repeats // 20), warmup=3)
    return dict(
        n=n, ours=t_ours, kernels=t_kernels, plan=t_plan, batch=tuple(t / copies for t in t_batch), numpy=t_numpy, fim=t_fim, grad=t_grad, los=t_los, slsqp=t_slsqp, ok=ok, nit=nit, fd=t_fd, ok_fd=ok_fd, nit_fd=nit_fd,
        agree=float(np.abs(np.asarray(ours.displacement) - np.asarray(theirs.displacement)).max()),
        c0=a_cost_after(scene, src, np.zeros(3)), c_ours=a_cost_after(scene, src, ours.displacement), c_slsqp=a_cost_after(scene, src, u_slsqp),
        c_fd=a_cost_after(scene, src, u_fd), v_ours=plain_violation(scene, src, ours.displacement), v_slsqp=plain_violation(scene, src, u_slsqp),
        active=ours.active, filtered=bool(ours.filtered),
    )  # fmt: skip


def print_times(rows: list[dict[str, Any]], near_building: bool) -> None:
    """The timing tables: medians [interquartile range], µs, and the ratios."""
    us = 1e6
    where = "drone 0 next to a building and a peer (constraints active)" if near_building else "drone 0 in open space"
    print(f"One drone's planning step (A-optimality), {where}; medians [interquartile range]; shared 2-core machine.")
    print(f"numpy: the planner of commit {NUMPY_COMMIT}; SLSQP: analytic gradient + constraint Jacobians; SLSQP-fd: finite differences.")
    print("compiled: fisher_information + cost_gradient + control_step (the public functions). Ratios: the baseline's time /")
    print("the compiled step's. |Δu|: largest difference of the compiled and numpy steps, m.")
    print(
        f"{'N':>5} | {'compiled µs':>20} | {'numpy µs':>18} | {'ratio':>6} | "
        f"{'SLSQP µs':>18} | {'ratio':>6} | {'it':>3} | {'SLSQP-fd µs':>19} | {'ratio':>6} | {'|Δu| m':>8}"
    )
    for r in rows:
        m, a, b = (x * us for x in r["ours"])
        nm, na, nb = (x * us for x in r["numpy"])
        sm, sa, sb = (x * us for x in r["slsqp"])
        fm, fa, fb = (x * us for x in r["fd"])
        print(
            f"{r['n']:>5} | {m:8.1f} [{a:5.1f}-{b:5.1f}] | "
            f"{nm:7.0f} [{na:4.0f}-{nb:4.0f}] | {nm / m:5.0f}× | {sm:7.0f} [{sa:4.0f}-{sb:4.0f}] | {sm / m:5.0f}× | "
            f"{r['nit']:>3}{'' if r['ok'] else '!'} | {fm:7.0f} [{fa:5.0f}-{fb:5.0f}] | {fm / m:5.0f}× | {r['agree']:8.1e}"
        )
    print()
    print("The compiled step's forms, µs (medians [IQR]): the public functions; the same three kernels called on arrays")
    print(f"prepared once; planner.agent.plan (the whole step as simulator and node run it: one kernel call); plan of {BATCH}/N")
    print("copies in one call, per drone (the simulator's batch). (FIM, grad: the public functions; LOS: line_of_sight, numpy,")
    print("not part of the step.) ×SLSQP: SLSQP's median / this form's.")
    print(
        f"{'N':>5} | {'public':>20} | {'kernels':>20} | {'plan':>20} | {'plan, batch/drone':>20} | {'FIM':>6} {'grad':>6} {'LOS':>6} | "
        f"{'×SLSQP: public':>14} {'kernels':>8} {'plan':>6} {'batch':>6}"
    )
    for r in rows:
        forms = [tuple(x * us for x in r[k]) for k in ("ours", "kernels", "plan", "batch")]
        cells = " | ".join(f"{m:8.1f} [{a:5.1f}-{b:5.1f}]" for m, a, b in forms)
        sm = r["slsqp"][0] * us
        ratios = " ".join(f"{sm / f[0]:{w}.0f}×" for f, w in zip(forms, (13, 7, 5, 5)))
        print(f"{r['n']:>5} | {cells} | {r['fim'][0] * us:6.1f} {r['grad'][0] * us:6.1f} {r['los'][0] * us:6.1f} | {ratios}")


def print_costs(rows: list[dict[str, Any]]) -> None:
    """The cost each step reaches, and the plain constraints' largest violation."""
    print("Cost tr(J⁻¹) [m²] after the step (lower is better); largest violation of the plain constraints (m, ≤ 0 = none)")
    print(
        f"{'N':>5} | {'before':>12} | {'fimnav':>12} | {'SLSQP':>12} | {'SLSQP-fd':>12} | {'(fimnav−SLSQP)/(before−SLSQP)':>30} | "
        f"{'viol. fimnav':>12} | {'viol. SLSQP':>11} | fimnav active (uav,src,obs,alt) / filtered"
    )
    for r in rows:
        gain = r["c0"] - r["c_slsqp"]
        rel = (r["c_ours"] - r["c_slsqp"]) / gain if gain != 0 else float("nan")
        print(
            f"{r['n']:>5} | {r['c0']:12.6e} | {r['c_ours']:12.6e} | {r['c_slsqp']:12.6e} | {r['c_fd']:12.6e} | {rel:30.2e} | "
            f"{r['v_ours']:12.3f} | {r['v_slsqp']:11.3f} | {tuple(int(x) for x in r['active'])} / {r['filtered']}"
        )


def in_study(mission: str, criterion: str) -> None:
    """The planning kernel as the in-process simulator calls it: ``fimnav montecarlo MISSION
    --criterion C --jobs 1 --no-figures`` (the mission's trials and steps) with every call of
    :func:`planner.kernels.plan_batch` timed, wall and the thread's CPU; per drone-step."""
    from missions.cli.main import main as fimnav
    from planner.warm import available_cores, compile_aside

    # The kernel as the study calls it: bound to the built module first (the study's own start
    # then leaves the timer in its place, planner.aot.bind).
    compile_aside(available_cores())
    kernel = K.plan_batch
    total = {"wall": 0.0, "cpu": 0.0, "calls": 0, "drone_steps": 0}

    def timed(*args: Any) -> None:
        wall, cpu = time.perf_counter(), time.thread_time()
        kernel(*args)
        total["wall"] += time.perf_counter() - wall
        total["cpu"] += time.thread_time() - cpu
        total["calls"] += 1
        total["drone_steps"] += args[0][1].shape[0]

    K.plan_batch = timed  # planner.agent.plan calls it through the module
    t0 = time.perf_counter()
    try:
        with tempfile.TemporaryDirectory() as out:
            fimnav(["montecarlo", mission, "--criterion", criterion, "--jobs", "1", "--no-figures", "--out", str(Path(out) / "run")])
    finally:
        K.plan_batch = kernel
    if total["calls"] == 0:
        raise SystemExit(f"bench_planning_step: the study made no call of planner.kernels.plan_batch that the timer saw ({mission})")
    n = max(total["drone_steps"], 1)
    print(
        f"{mission} --criterion {criterion}: run {time.perf_counter() - t0:.1f} s wall; plan_batch {total['calls']} calls, "
        f"{total['drone_steps']} drone-steps: {total['wall']:.2f} s wall ({total['wall'] / n * 1e6:.2f} µs per drone-step), "
        f"{total['cpu']:.2f} s CPU ({total['cpu'] / n * 1e6:.2f} µs per drone-step)"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10, 100, 1000])
    ap.add_argument("--repeats", type=int, default=3000, help="repeats of the compiled step (numpy: /10, SLSQP: /20, at least 30)")
    ap.add_argument("--near-building", action="store_true", help="drone 0 next to a building and a peer: constraints active")
    ap.add_argument(
        "--in-study", metavar="MISSION", help="instead: time the planning kernel inside fimnav montecarlo MISSION --jobs 1 (per drone-step)"
    )
    ap.add_argument("--criterion", choices=("A", "D"), default="A", help="--in-study: the design criterion")
    args = ap.parse_args(argv)
    if args.in_study:
        in_study(args.in_study, args.criterion)
        return 0
    npl = numpy_planner()
    rows = [measure(n, args.near_building, args.repeats, npl) for n in args.sizes]
    print_times(rows, args.near_building)
    print()
    print_costs(rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

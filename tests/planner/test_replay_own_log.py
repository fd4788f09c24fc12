"""A restarted planner rebuilds its estimator from its predecessor's step log
(:func:`planner.node.replay_step_logs`, :func:`planner.node.read_step_log`).

Synthetic truth: one ranging drone of a three-drone mission circles a known source at 80 m
for 40 steps, measuring with the paper's channel (seeded noise); its step log is written as the
planner writes it (JSON lines, NaN as null), with a torn last line and a step logged twice (an
earlier rejoin). A fresh estimator knows nothing; the rebuilt one is what the predecessor had
from the same evidence, bit for bit, and is within three of its position error bounds of the
true source.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from missions.format.loader import load_mission
from planner import estimator as est
from planner.node import read_step_log, replay_step_logs
from planner.observation import observe_from_uniforms

SOURCE = np.array([10.0, -20.0, 2.0])
STEPS = 40


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def write_log(path: Path, channel, seed: int = 3) -> list[dict]:
    rng = np.random.default_rng(seed)
    rows = []
    for k in range(STEPS):
        a = 2.0 * math.pi * k / STEPS
        p = SOURCE + np.array([80.0 * math.cos(a), 80.0 * math.sin(a), 18.0 + 4.0 * math.sin(3 * a)])
        obs = observe_from_uniforms(SOURCE, p[None], np.array([True]), np.array([False]), np.array([True]), channel, rng.random((1, 5)))
        rows.append({"step": k, "t_s": float(k), "position_m": p.tolist(),
                     "measurement": {"range_m": _num(float(obs.range_m[0])), "azimuth_rad": _num(float(obs.azimuth_rad[0])),
                                     "elevation_rad": _num(float(obs.elevation_rad[0])), "los": True},
                     "estimate_m": [0.0, 0.0, 0.0]})
    lines = [json.dumps(r) for r in rows]
    lines.insert(10, json.dumps(rows[9] | {"measurement": {"range_m": 1.0, "azimuth_rad": None, "elevation_rad": None, "los": True}}))
    path.write_text("\n".join(lines) + "\n" + '{"step": 40, "t_s": 40.0, "posit')  # killed while writing
    return rows


def test_a_rejoining_planner_rebuilds_its_estimator_from_its_log(tmp_path: Path) -> None:
    mission = load_mission("paper/ranging_los", {"drones.count": 3})
    channel, config = mission.channel.to_planner(), mission.estimator_config()
    rows = write_log(tmp_path / "planner_1.jsonl", channel)
    logged = read_step_log(tmp_path / "planner_1.jsonl")
    assert len(logged) == STEPS + 1  # the duplicate of step 9 kept, the torn line dropped

    fresh = est.initial_state((), config)
    assert not bool(fresh.observable)
    state, done = replay_step_logs(fresh, {0: logged}, 3, STEPS, channel, config)
    assert [d[0] for d in done[0]] == list(range(STEPS))
    assert bool(state.observable)
    # Within 3 of its own position error bounds (one ranging drone: weak in height).
    bound = math.sqrt(float(np.trace(np.linalg.inv(state.information))))
    assert np.linalg.norm(state.estimate_m - SOURCE) < 3.0 * bound, (state.estimate_m, bound)

    # The predecessor: the same evidence, step by step, as the planner fed it.
    ref = est.initial_state((), config)
    for r in rows:
        pos = np.full((3, 3), np.nan)
        pos[0] = r["position_m"]
        rng = np.full(3, np.nan)
        rng[0] = r["measurement"]["range_m"]
        los = np.array([True, False, False])
        ref = est.update(ref, est.Measurements(positions_m=pos, range_m=rng, azimuth_rad=np.full(3, np.nan),
                                               elevation_rad=np.full(3, np.nan), los=los), channel, config)
    np.testing.assert_array_equal(state.estimate_m, ref.estimate_m)

    # Only the steps before the rejoin count.
    part, done = replay_step_logs(est.initial_state((), config), {0: logged}, 3, 12, channel, config)
    assert [d[0] for d in done[0]] == list(range(12))
    # A peer's log next to it adds its records, step by step with the own ones.
    peer = [dict(r, position_m=(np.array(r["position_m"]) * [1.0, -1.0, 1.0]).tolist()) for r in rows]
    both, done = replay_step_logs(est.initial_state((), config), {0: logged, 2: peer}, 3, STEPS, channel, config)
    assert [d[0] for d in done[2]] == list(range(STEPS))
    assert np.linalg.det(both.information) > np.linalg.det(state.information)

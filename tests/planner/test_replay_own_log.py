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


def test_a_rejoining_planner_with_the_power_unknown_rebuilds_the_joint_estimate(tmp_path: Path) -> None:
    """The same with ``source.power: unknown`` and a source 5 dB stronger than nominal (its
    ranges read e^b times the distance, b = −5 ln 10 / (10 γ)): three ranging drones circle it at
    60, 90 and 130 m (unequal distances make the offset observable); the rebuilt joint state
    (position and power offset) is the predecessor's bit for bit, its offset is within 1.5 dB
    of the truth and its position within three of its position error bounds (synthetic truth)."""
    from planner.radio import power_estimator as power
    from planner.radio.power_offset import offset_of_power_db, offset_ranges

    mission = load_mission("paper/ranging_los", {"drones.count": 3, "source.power": "unknown"})
    planner = mission.planner_config("A")
    channel, config = planner.channel, planner.estimator
    b = offset_of_power_db(5.0, channel.gamma)
    rng = np.random.default_rng(5)
    logs: dict[int, list[dict]] = {j: [] for j in range(3)}
    for k in range(STEPS):
        a = 2.0 * math.pi * k / STEPS
        for j, radius in enumerate((60.0, 90.0, 130.0)):
            p = SOURCE + np.array([radius * math.cos(a + j), radius * math.sin(a + j), 16.0 + 3.0 * j])
            obs = observe_from_uniforms(SOURCE, p[None], np.array([True]), np.array([False]), np.array([True]), channel, rng.random((1, 5)))
            r = offset_ranges(obs.range_m, np.array([np.linalg.norm(p - SOURCE)]), b, channel.gamma)
            logs[j].append({"step": k, "t_s": float(k), "position_m": p.tolist(),
                            "measurement": {"range_m": _num(float(r[0])), "azimuth_rad": None, "elevation_rad": None, "los": True},
                            "estimate_m": [0.0, 0.0, 0.0]})  # fmt: skip
    for j, rows in logs.items():
        (tmp_path / f"planner_{j + 1}.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    logged = {j: read_step_log(tmp_path / f"planner_{j + 1}.jsonl") for j in range(3)}

    def update(state, meas):
        return power.update_source(state, meas, planner)

    rebuilt, done = replay_step_logs(power.initial_source_state((), planner), logged, 3, STEPS, channel, config, update=update)
    assert all([d[0] for d in done[j]] == list(range(STEPS)) for j in range(3))
    assert isinstance(rebuilt, power.PowerEstimatorState) and bool(rebuilt.observable)

    ref = power.initial_source_state((), planner)
    for k in range(STEPS):
        pos = np.array([logs[j][k]["position_m"] for j in range(3)])
        ranges = np.array([logs[j][k]["measurement"]["range_m"] for j in range(3)], dtype=float)
        nan3 = np.full(3, np.nan)
        ref = update(ref, est.Measurements(positions_m=pos, range_m=ranges, azimuth_rad=nan3, elevation_rad=nan3, los=np.ones(3, dtype=bool)))
    np.testing.assert_array_equal(rebuilt.estimate_m, ref.estimate_m)
    np.testing.assert_array_equal(rebuilt.offset_db, ref.offset_db)
    assert abs(float(rebuilt.offset_db) - 5.0) < 1.5, float(rebuilt.offset_db)
    # Within 3 of its position error bounds (of J_eq, the power unknown; a ring above the source:
    # weak in height).
    bound = math.sqrt(float(np.trace(np.linalg.inv(rebuilt.information))))
    assert np.linalg.norm(rebuilt.estimate_m - SOURCE) < 3.0 * bound, (rebuilt.estimate_m, bound)

"""The real-time driver's step timing, end to end through the node's injected link, session and
clock (in-memory fakes, tests/node/fakes.py; no sockets, no sleeping): steps begin on the
shared grid of UNIX multiples of dt/speedup; the peers' records are awaited until
``t_k + peer_wait_fraction·dt`` and no longer (a dropped record); a stalled planner skips the
steps it missed; each step streams a trajectory from the drone's position to the planned
one over one step."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from comms import keys
from comms.messages import Done, Message, MessageKind, Record, Status
from missions.format.loader import load_mission
from planner.node import NodeOptions, PlannerNode
from tests.external.helpers import write_mission
from tests.node.fakes import FakeClock, FakeLink, FakeSession

STARTS = [[10.0, 20.0, 8.0], [20.0, 20.0, 8.0]]
SOURCE = np.array([60.0, 90.0, 2.0])  # write_mission's source
STEPS = 6
START_UNIX = 1000.3  # the grid's step 0 is then UNIX 1001 (dt 1 s, speedup 1)
DROPPED = 2  # the peer's record of this step never comes
STALL_BEFORE = 3  # the planner stalls 2.3 s just before this step


def run_node(tmp_path: Path) -> tuple[dict[str, Any], FakeClock, FakeSession, FakeLink, list[tuple[float, Message]]]:
    mission = load_mission(write_mission(tmp_path / "m.yaml", "rtfake", STARTS, STEPS, "hold"))
    clock = FakeClock(START_UNIX)
    published: list[tuple[float, Message]] = []
    session = FakeSession(mission.id, tokens=(keys.alive(mission.id, "planner", 2),), on_publish=lambda key, msg: published.append((clock.unix(), msg)))
    link = FakeLink(np.array(STARTS[0]), wall=clock.wall, follow_stream=True, origin=(45.0, 7.0, 300.0))
    t0 = math.ceil(START_UNIX)
    nan = float("nan")

    def measurement(k: int) -> None:
        t = t0 + k - 0.05
        pos = link.position_m
        meas = Record(1, 10_000 + k, t, tuple(pos), True, False, True, float(np.linalg.norm(pos - SOURCE)), nan, nan)
        session.send(keys.measurement(mission.id, 1), meas, MessageKind.MEASUREMENT)

    def peer_record(k: int) -> None:
        # The peer numbers its steps differently; its time stamp puts the record on our grid.
        pos = np.array(STARTS[1]) + [0.0, 0.5 * k, 0.0]
        rec = Record(2, 500 + k, t0 + k + 0.05, tuple(pos), True, False, True, float(np.linalg.norm(pos - SOURCE)), nan, nan)
        session.send(keys.record(mission.id, 2), rec, MessageKind.RECORD)

    def stall() -> None:
        clock.unix_s += 2.3

    for k in range(STEPS):
        clock.at(t0 + k - 0.05, lambda k=k: measurement(k))
        if k != DROPPED:
            clock.at(t0 + k + 0.1, lambda k=k: peer_record(k))
    clock.at(t0 + STALL_BEFORE - 0.1, stall)
    options = NodeOptions(uav=1, mavlink="fake:1", lockstep=False, speedup=1.0, log_path=tmp_path / "planner_1.jsonl", peer_wait_fraction=0.5)
    node = PlannerNode(mission, options, link_factory=lambda conn, sysid: link, session_factory=lambda settings: session, clock=clock.node_clock())
    summary = node.run()
    return summary, clock, session, link, published


def test_realtime_steps_follow_the_grid_and_the_peer_deadline(tmp_path: Path) -> None:
    summary, _, session, link, published = run_node(tmp_path)
    t0 = math.ceil(START_UNIX)
    flown = [0, 1, 2, 5]  # steps 3 and 4 were missed by the stall
    assert summary["steps"] == len(flown) and summary["late_steps"] == 2 and summary["stale_steps"] == 0
    assert summary["end"]["confirmed"] and summary["flavour"] == "ardupilot"
    # Done(k) goes out as soon as the peer's record of step k is in (0.1 s into the step), at
    # the deadline t_k + 0.5 dt when it never comes, at once when it came during the stall.
    done_at = {m.step: t for t, m in published if isinstance(m, Done)}
    assert sorted(done_at) == [-1, *flown]
    expected_done = {0: t0 + 0.1, 1: t0 + 1.1, 2: t0 + 2.5, 5: t0 + 5.2}
    for k, t in expected_done.items():
        assert done_at[k] == pytest.approx(t, abs=1e-9), k
    # The own records are stamped with the step's start on the grid (UNIX s).
    records = {m.step: m.time_s for _, m in published if isinstance(m, Record) and m.sender == 1}
    assert records == pytest.approx({0: t0, 1: t0 + 1.0, 2: t0 + 2.0, 5: t0 + 5.2}, abs=1e-9)
    # Without the peer's record of step 2 the step plans on its record of step 1.
    saved = {m.step: m.saved_steps for _, m in published if isinstance(m, Status)}
    assert saved[1] == (1, 1) and saved[2] == (2, 1) and saved[5] == (5, 5)
    # The step log's timing says the same.
    rows = {r["step"]: r for r in map(json.loads, (tmp_path / "planner_1.jsonl").read_text().splitlines())}
    assert sorted(rows) == flown
    assert [rows[k]["timing"]["late_s"] for k in flown] == pytest.approx([0.0, 0.0, 0.0, 0.2], abs=1e-6)
    assert [rows[k]["timing"]["wait_peers_s"] for k in flown] == pytest.approx([0.1, 0.1, 0.5, 0.0], abs=1e-6)
    assert all(rows[k]["measurement"]["range_m"] is not None for k in flown)  # fresh measurements


def test_each_step_streams_a_trajectory_to_the_planned_position(tmp_path: Path) -> None:
    _, clock, _, link, published = run_node(tmp_path)
    rows = [json.loads(line) for line in (tmp_path / "planner_1.jsonl").read_text().splitlines()]
    # The streams: the start hold, one trajectory per step flown, the end hold, stopped.
    trajectories = link.streams[1:-2]
    assert len(trajectories) == len(rows)
    dt_wall = 1.0
    offset = clock.unix() - clock.wall()
    done_wall = {m.step: t - offset for t, m in published if isinstance(m, Done)}
    for row, fn in zip(rows, trajectories):
        assert fn is not None
        own, nxt = np.array(row["position_m"]), np.array(row["next_position_m"])
        t_sent = done_wall[row["step"]]  # sent just before Done, at the same simulated time
        p0, v0 = fn(t_sent)
        np.testing.assert_allclose(p0, own, atol=1e-9)
        np.testing.assert_allclose(v0, nxt - own, atol=1e-9)  # u / dt, dt = 1 s
        p_half, _ = fn(t_sent + 0.5 * dt_wall)
        np.testing.assert_allclose(p_half, own + 0.5 * (nxt - own), atol=1e-9)
        p_end, v_end = fn(t_sent + dt_wall)
        np.testing.assert_allclose(p_end, nxt, atol=1e-9)
        np.testing.assert_allclose(v_end, np.zeros(3))

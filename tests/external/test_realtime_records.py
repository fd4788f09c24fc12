"""Real-time bookkeeping of the peers' records inside one planner node (no sockets): a
record is placed on this planner's step grid by its time stamp, and a stale record answers
for its step without refreshing the peer's data."""

from __future__ import annotations

from pathlib import Path

import pytest

from comms.messages import Record
from missions.format.loader import load_mission
from planner.node import NodeError, NodeOptions, PlannerNode
from planner.node.realtime import PeerRecordGrid

from tests.external.helpers import write_mission

ALIVE = {1, 2}


def node(tmp_path: Path, speedup: float = 4.0) -> PeerRecordGrid:
    """The step grid of planner 1 of a two-drone mission, started at UNIX 1e6 s."""
    mission = load_mission(write_mission(tmp_path / "m.yaml", "rec", [[10.0, 20.0, 8.0], [20.0, 20.0, 8.0]], 10, "hold"))
    grid = PlannerNode(mission, NodeOptions(uav=1, mavlink="udpout:127.0.0.1:9", lockstep=False, speedup=speedup)).grid
    grid.t0_unix = 1_000_000.0
    return grid


def record(t: float, stale: bool = False, x: float = 20.0) -> Record:
    nan = float("nan")
    return Record(2, 999, t, (x, 20.0, 8.0), True, False, True, 50.0, nan, nan, stale)


def test_records_are_indexed_by_time_on_the_receivers_grid(tmp_path: Path) -> None:
    n = node(tmp_path)  # dt 1 s at speedup 4: a step every 0.25 s of wall time
    assert n.dt_wall_s == pytest.approx(0.25)
    n.add(record(1_000_000.0 + 3 * 0.25 + 0.02))  # the sender's step 999 is our step 3
    assert n.view.has(2, 3) and not n.view.has(2, 999)
    assert n.missing(3, ALIVE) == [] and n.missing(4, ALIVE) == [2]
    n.add(record(1_000_000.0 - 0.3))  # before our step 0: dropped
    assert not any(n.view.has(2, k) for k in range(-2, 1))


def test_a_stale_record_answers_for_the_step_but_keeps_the_old_data(tmp_path: Path) -> None:
    n = node(tmp_path)
    t0 = n.t0_unix
    assert t0 is not None
    n.add(record(t0 + 1 * 0.25, x=20.0))
    n.add(record(t0 + 2 * 0.25, stale=True, x=20.0))
    assert n.missing(2, ALIVE) == []  # no wait until the deadline for a drone that said so
    assert not n.view.has(2, 2)  # ... but nothing new entered the view
    for k in (1, 2):
        n.view.add(Record(1, k, t0 + k * 0.25, (10.0, 20.0, 8.0), True, False, True, 50.0, float("nan"), float("nan")))
    assert int(n.view.advance(1).saved_steps[1]) == 1
    view = n.view.advance(2)
    assert int(view.saved_steps[1]) == 1  # the saved record of drone 2 is still step 1 (age 1)


def test_options_are_checked(tmp_path: Path) -> None:
    for bad in ({"stream_hz": 3.0}, {"speedup": 0.0}, {"peer_wait_fraction": 1.0}, {"flavour": "inav"}, {"setpoint_frame": "body"}):
        with pytest.raises(NodeError):
            NodeOptions(uav=1, mavlink="udpout:127.0.0.1:9", lockstep=False, **bad)  # type: ignore[arg-type]

"""The one rule when the vehicle link returns, inside the real-time node (in-memory fakes,
tests/node/fakes.py: no sockets, no sleeping; the same path against real processes and a cut
UDP relay is tests/external/test_pilot_rule.py).

The link is lost for three steps and returns:

- the vehicle still in its guided mode: the node flies on, no mode change;
- the vehicle armed in a pilot's mode (a pilot's, a ground station's or a failsafe's change
  during the loss: the node cannot tell them apart): taken over from step 6 ("after link
  loss"), no mode change, no stream, its position published flagged taken over;
- the vehicle taken over by a pilot before the loss and still in the pilot's mode: it stays
  taken over, no mode change (the node once switched such a vehicle back to GUIDED).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from comms import keys
from comms.messages import MessageKind, Record
from missions.format.loader import load_mission
from planner.node import NodeOptions, PlannerNode
from tests.external.helpers import write_mission
from tests.node.fakes import FakeClock, FakeLink, FakeSession

START = [10.0, 20.0, 8.0]
SOURCE = np.array([60.0, 90.0, 2.0])  # write_mission's source
STEPS = 12
START_UNIX = 1000.3  # the node starts here (dt 1 s, speedup 1); its steps begin at UNIX 1002 at the latest
PILOT_AT, LOST_AT, BACK_AT = 1003.5, 1004.5, 1007.5  # UNIX s: a pilot's switch, the link lost, back
GUIDED = {"ardupilot": "GUIDED", "px4": "OFFBOARD"}
PILOT = {"ardupilot": "LOITER", "px4": "POSCTL"}
END_HOLD = {"ardupilot": [], "px4": ["AUTO.LOITER"]}  # the modes the end of mission 'hold' sets


def first_step_after(session: FakeSession, unix_s: float) -> int:
    """The first step of the node's grid (its records' time stamps) that begins after ``unix_s``."""
    times = {r.step: r.time_s for r in session.of_kind(Record) if r.sender == 1}
    return min(k for k, t in times.items() if t > unix_s)


def make_node(tmp_path: Path, flavour: str) -> tuple[PlannerNode, FakeLink, FakeSession, FakeClock]:
    """A real-time node on a fake link armed in the guided mode at its start, with a payload
    measurement every UNIX second."""
    mission = load_mission(write_mission(tmp_path / "m.yaml", "linkfake", [START], STEPS, "hold"))
    clock = FakeClock(START_UNIX)
    session = FakeSession(mission.id)
    link = FakeLink(np.array(START), wall=clock.wall, flavour=flavour, mode=GUIDED[flavour], follow_stream=True, origin=(45.0, 7.0, 300.0))
    t0 = math.ceil(START_UNIX)
    nan = float("nan")

    def measurement(k: int) -> None:
        pos = link.position_m
        meas = Record(1, 10_000 + k, t0 + k - 0.05, tuple(pos), True, False, True, float(np.linalg.norm(pos - SOURCE)), nan, nan)
        session.send(keys.measurement(mission.id, 1), meas, MessageKind.MEASUREMENT)

    for k in range(STEPS + 3):
        clock.at(t0 + k - 0.05, lambda k=k: measurement(k))
    options = NodeOptions(uav=1, mavlink="fake:1", lockstep=False, speedup=1.0, log_path=tmp_path / "planner_1.jsonl")
    node = PlannerNode(mission, options, link_factory=lambda conn, sysid: link, session_factory=lambda settings: session, clock=clock.node_clock())
    return node, link, session, clock


def run_node(tmp_path: Path, flavour: str, back_in: str, pilot_before: bool = False) -> tuple[dict[str, Any], FakeLink, FakeSession, int]:
    """Fly the node through the loss; return its summary, the link, the session and how many
    streams had been installed when the link returned."""
    node, link, session, clock = make_node(tmp_path, flavour)
    at_return: list[int] = []

    def lose() -> None:
        link.lost = True

    def come_back() -> None:
        at_return.append(len(link.streams))
        link.lost = False
        link.heartbeat_in(back_in)  # the first heartbeat after the loss says the mode

    if pilot_before:
        clock.at(PILOT_AT, lambda: link.heartbeat_in(PILOT[flavour]))
    clock.at(LOST_AT, lose)
    clock.at(BACK_AT, come_back)
    summary = node.run()
    return summary, link, session, at_return[0]


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_a_vehicle_still_guided_when_the_link_returns_is_flown_on(tmp_path: Path, flavour: str) -> None:
    summary, link, session, _ = run_node(tmp_path, flavour, GUIDED[flavour])
    assert link.modes_set == END_HOLD[flavour], link.modes_set
    assert summary["taken_over"] == [] and len(summary["link_losses"]) == 1 and summary["end"]["confirmed"], summary
    stale = first_step_after(session, BACK_AT) - first_step_after(session, LOST_AT)
    assert stale == 3 and summary["stale_steps"] == stale and summary["steps"] == STEPS - stale, summary


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_a_vehicle_in_a_pilots_mode_when_the_link_returns_is_taken_over(tmp_path: Path, flavour: str) -> None:
    summary, link, session, n_streams = run_node(tmp_path, flavour, PILOT[flavour])
    assert link.modes_set == [], link.modes_set
    assert all(fn is None for fn in link.streams[n_streams:]), "a setpoint stream after the link returned"
    back = first_step_after(session, BACK_AT)
    assert summary["taken_over"] == [{"step": back, "mode": PILOT[flavour], "reason": "after link loss"}], (back, summary["taken_over"])
    assert summary["taken_over_steps"] == STEPS - back and summary["end"]["confirmed"] is False, summary
    records = {r.step: r for r in session.of_kind(Record) if r.sender == 1}
    assert all(records[k].taken_over and math.isnan(records[k].range_m) for k in range(back, STEPS))
    assert not any(records[k].taken_over for k in range(back))


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_a_vehicle_taken_over_before_the_loss_stays_taken_over(tmp_path: Path, flavour: str) -> None:
    summary, link, session, n_streams = run_node(tmp_path, flavour, PILOT[flavour], pilot_before=True)
    assert link.modes_set == [], link.modes_set
    assert all(fn is None for fn in link.streams[n_streams:]), "a setpoint stream after the link returned"
    taken = first_step_after(session, PILOT_AT)
    assert summary["taken_over"] == [{"step": taken, "mode": PILOT[flavour]}], (taken, summary["taken_over"])
    assert summary["end"]["confirmed"] is False, summary


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_a_pilots_switch_during_the_preflight_waits_is_not_undone(tmp_path: Path, flavour: str) -> None:
    """Armed in the guided mode at the start, so the pre-flight prepares it; a pilot switches
    it during the pre-flight's waits (ArduPilot: the readiness wait; PX4: the setpoint stream
    before OFFBOARD). The node does not switch it back: taken over at start."""
    node, link, session, clock = make_node(tmp_path, flavour)
    ready_at = START_UNIX + 1.0
    link.not_ready = lambda require_gps=True: ["GPS"] if clock.unix() < ready_at else []  # type: ignore[method-assign]
    clock.at(START_UNIX + 0.5, lambda: link.heartbeat_in(PILOT[flavour]))
    summary = node.run()
    assert link.modes_set == [], link.modes_set
    assert [(t["mode"], t.get("at_start")) for t in summary["taken_over"]] == [(PILOT[flavour], "start")], summary["taken_over"]
    assert summary["steps"] == 0 and all(r.taken_over for r in session.of_kind(Record) if r.sender == 1)

"""The one rule and the early stop inside the lockstep node (in-memory fakes, tests/node/fakes.py;
the same paths run against real processes in tests/external/test_pilot_rule.py):

- a heartbeat saying the vehicle left the guided mode that arrives in the middle of a step (after
  the node published its record, while it waits for its peer's) stops that step's setpoint, and
  the node commands nothing more;
- a node started beside a vehicle armed in a pilot's mode changes no mode and sends nothing;
- a node that stops early (a fatal error) tells the vehicle the mission's on_stop, except a
  vehicle a pilot flies.
"""

from __future__ import annotations

from pathlib import Path
import pytest

from comms.messages import Message, Record
from planner.node import NodeError
from tests.node.test_lockstep_node import STEPS, make_node

PILOT = {"ardupilot": "LOITER", "px4": "POSCTL"}
HOLD = {"ardupilot": "LOITER", "px4": "AUTO.LOITER"}


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_a_mode_change_in_the_middle_of_a_step_stops_its_setpoint(tmp_path: Path, flavour: str) -> None:
    node, swarm, _ = make_node(tmp_path, flavour)
    link = swarm.link
    sent_by_step: dict[int, int] = {}
    base = swarm.on_publish

    def on_publish(key: str, msg: Message) -> None:
        if isinstance(msg, Record) and msg.sender == 1 and not msg.taken_over:
            sent_by_step[msg.step] = len(link.setpoints)
            if msg.step == 1:
                link.heartbeat_in(PILOT[flavour])  # the pilot, between the record and the setpoint
        base(key, msg)

    swarm.session.on_publish = on_publish
    summary = node.run()
    assert summary["steps"] == 1 and [t["step"] for t in summary["taken_over"]] == [1], summary
    # No setpoint after the record of step 1 (the step whose setpoint the mode change beat).
    assert len(link.setpoints) == sent_by_step[1], (len(link.setpoints), sent_by_step)
    assert link.modes_set == [] and summary["end"]["confirmed"] is False
    records = swarm.session.of_kind(Record)
    assert [r.step for r in records if r.sender == 1 and r.taken_over] == list(range(2, STEPS))


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_a_node_started_beside_a_pilot_held_vehicle_commands_nothing(tmp_path: Path, flavour: str) -> None:
    node, swarm, _ = make_node(tmp_path, flavour)
    swarm.link.mode = PILOT[flavour]
    summary = node.run()
    assert swarm.link.modes_set == [] and swarm.link.setpoints == [] and not any(swarm.link.streams)
    (take,) = summary["taken_over"]
    assert take == {"step": 0, "mode": PILOT[flavour], "at_start": "start"} and summary["steps"] == 0
    flagged = [r.step for r in swarm.session.of_kind(Record) if r.sender == 1]
    assert flagged == list(range(STEPS)) and all(r.taken_over for r in swarm.session.of_kind(Record) if r.sender == 1)


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
@pytest.mark.parametrize("taken", [False, True], ids=["guided", "taken-over"])
def test_a_node_that_fails_tells_its_vehicle_on_stop(tmp_path: Path, flavour: str, taken: bool) -> None:
    """A fatal error at step 1 (the clock's tick never comes): the vehicle in the guided mode is
    told the mission's on_stop (hold: LOITER / AUTO.LOITER) and confirms; one a pilot flies is
    left alone."""
    node, swarm, _ = make_node(tmp_path, flavour, step_timeout_s=1.0)
    if taken:
        swarm.link.mode = PILOT[flavour]
    step = swarm.step
    swarm.step = lambda k: step(k) if k < 1 else None  # type: ignore[method-assign]
    with pytest.raises(NodeError, match="no clock tick of step 1"):
        node.run()
    assert node.stopped is not None
    if taken:
        assert swarm.link.modes_set == [] and node.stopped["commanded"] is False
    else:
        assert swarm.link.modes_set == [HOLD[flavour]] and node.stopped["confirmed"] is True

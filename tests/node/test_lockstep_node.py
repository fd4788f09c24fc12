"""The planner node in lockstep, end to end through its injected link and session factories
(in-memory fakes, tests/node/fakes.py): a scripted clock, payload and peer answer each ``Done``;
the setpoint of step 0 is checked against :func:`planner.agent.plan` fed the same records
(an independent reference: the estimator, the delayed view and the control stream built here,
not by the node); a dropped peer record stops the barrier with an error naming the peer, and
a peer that left is not waited for."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from comms import keys
from comms.latency import DelayedView
from comms.messages import Done, Message, MessageKind, Record, Status, Tick
from missions.format.loader import load_mission
from planner import estimator as est
from planner.agent import plan, records_as_arrays
from planner.node import NodeError, NodeOptions, PlannerNode
from planner.randomness import CONTROL_DRAWS, control_rng
from planner.step import DroneState, StepScene
from tests.external.helpers import write_mission
from tests.node.fakes import FakeLink, FakeSession

STARTS = [[10.0, 20.0, 8.0], [20.0, 20.0, 8.0]]
SOURCE = np.array([60.0, 90.0, 2.0])  # write_mission's source
STEPS = 3


class ScriptedSwarm:
    """The clock, drone 1's payload and planner 2, answering planner 1's ``Done(k)`` with step
    k + 1: the tick, the vehicle's report at t_{k+1}, the measurement and the peer's record.

    Args:
        drop_peer_record_at: a step whose peer record never comes.
        peer_leaves_at: a step before whose tick the peer's liveliness token goes.
    """

    def __init__(self, mission: Any, link: FakeLink, drop_peer_record_at: int | None = None, peer_leaves_at: int | None = None) -> None:
        self.mission = mission
        self.mid = mission.id
        self.dt = mission.dt_s
        self.link = link
        self.drop_peer_record_at = drop_peer_record_at
        self.peer_leaves_at = peer_leaves_at
        self.session = FakeSession(self.mid, tokens=(keys.alive(self.mid, "planner", 2),), on_publish=self.on_publish)
        self.peer_records: list[Record] = []
        self.measurements: list[Record] = []

    def on_publish(self, key: str, msg: Message) -> None:
        if isinstance(msg, Done) and msg.sender == 1:
            self.step(msg.step + 1)

    def step(self, k: int) -> None:
        s, t = self.session, k * self.dt
        if k >= STEPS:
            s.send(keys.tick(self.mid), Tick(k, t))  # the end-of-mission tick
            return
        if k == self.peer_leaves_at:
            s.leave(keys.alive(self.mid, "planner", 2))
        own = self.link.position_m
        if self.link.setpoints and k > 0:  # the vehicle flew its step's setpoint
            position, velocity = self.link.setpoints[-1]
            own = position + velocity * self.dt if self.link.flavour == "ardupilot" else position
        self.link.report(own, int(round(t * 1000)))
        nan = float("nan")
        meas = Record(1, k, t, tuple(own), True, False, True, float(np.linalg.norm(own - SOURCE)) + 0.5, nan, nan)
        peer_pos = np.array(STARTS[1]) + [0.0, 0.5 * k, 0.0]
        peer = Record(2, k, t, tuple(peer_pos), True, False, True, float(np.linalg.norm(peer_pos - SOURCE)) - 0.3, nan, nan)
        s.send(keys.tick(self.mid), Tick(k, t))
        s.send(keys.measurement(self.mid, 1), meas, MessageKind.MEASUREMENT)
        self.measurements.append(meas)
        if k != self.drop_peer_record_at and (self.peer_leaves_at is None or k < self.peer_leaves_at):
            s.send(keys.record(self.mid, 2), peer, MessageKind.RECORD)
            self.peer_records.append(peer)


def make_node(tmp_path: Path, flavour: str = "ardupilot", step_timeout_s: float = 10.0, **script: Any) -> tuple[PlannerNode, ScriptedSwarm, Any]:
    mission = load_mission(write_mission(tmp_path / "m.yaml", "lockfake", STARTS, STEPS, "hold"))
    link = FakeLink(np.array(STARTS[0]), wall=lambda: 0.0, flavour=flavour, mode="GUIDED" if flavour == "ardupilot" else "OFFBOARD")
    swarm = ScriptedSwarm(mission, link, **script)
    options = NodeOptions(
        uav=1, mavlink="fake:1", lockstep=True, step_timeout_s=step_timeout_s, preflight_timeout_s=10.0, log_path=tmp_path / "planner_1.jsonl"
    )
    node = PlannerNode(mission, options, link_factory=lambda conn, sysid: link, session_factory=lambda settings: swarm.session)
    return node, swarm, mission


def reference_plan_step0(mission: Any, own_record: Record, peer_record: Record) -> tuple[Any, Any]:
    """planner.agent.plan for drone 1's step 0, from its own and its peer's record of step 0;
    returns (plan, estimator state)."""
    config = mission.planner_config()
    view = DelayedView(0, 2, mission.comms.d_hop_m, mission.comms.h_max, emulate=mission.comms.latency == "emulated", seed=mission.seed)
    view.add(own_record)
    view.add(peer_record)
    v = view.advance(0)
    records = [own_record, peer_record]
    meas = est.Measurements(
        positions_m=np.array([r.position_m for r in records]),
        range_m=np.array([r.range_m for r in records]),
        azimuth_rad=np.full(2, np.nan),
        elevation_rad=np.full(2, np.nan),
        los=np.array([r.los for r in records]),
    )
    state = est.update(est.initial_state((), config.estimator), meas, config.channel, config.estimator)
    uniforms = control_rng(mission.seed, 0, 0).random(CONTROL_DRAWS)
    positions, valid, los = records_as_arrays(v.records)
    scene = StepScene(
        0,
        np.array(0),
        np.array(own_record.position_m),
        np.array(own_record.range_m),
        np.array(own_record.los),
        positions,
        valid,
        los,
        np.where(valid, v.saved_steps, -1),
        np.asarray(v.hops),
        state.estimate_m,
        state.information,
        np.asarray(state.observable),
        uniforms,
    )
    return plan(config, scene, DroneState.initial((), 2)), state


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_a_lockstep_step_sends_the_setpoint_plan_gives(tmp_path: Path, flavour: str) -> None:
    node, swarm, mission = make_node(tmp_path, flavour)
    summary = node.run()
    assert summary["steps"] == STEPS and summary["end"]["confirmed"]
    records = [m for m in swarm.session.of_kind(Record) if m.sender == 1]
    assert [r.step for r in records] == list(range(STEPS))
    assert [d.step for d in swarm.session.of_kind(Done)] == [-1, 0, 1, 2]
    # Step 0: the record carries the payload's measurement at the reported position.
    own0 = records[0]
    assert own0.position_m == tuple(STARTS[0]) and own0.range_m == swarm.measurements[0].range_m
    result, state = reference_plan_step0(mission, own0, swarm.peer_records[0])
    expected = result.step
    # The pre-flight held the start (position-only setpoints); then one setpoint per step.
    flown = [(p, v) for p, v in swarm.link.setpoints if v is not None]
    assert len(flown) == STEPS
    position, velocity = flown[0]
    u = np.asarray(expected.displacement)
    # ArduPilot moves a position+velocity target along its velocity: it starts at the drone;
    # PX4 holds the point (the planned next position) with the velocity as a feed-forward.
    want = np.array(STARTS[0]) if flavour == "ardupilot" else np.asarray(expected.next_position)
    np.testing.assert_allclose(position, want, rtol=0, atol=1e-12)
    np.testing.assert_allclose(velocity, u / mission.dt_s, rtol=0, atol=1e-12)
    assert np.linalg.norm(u) > 0.1  # the drone does move
    # The status of step 0 carries the reference's estimate (float32 on the wire).
    status0 = swarm.session.of_kind(Status)[0]
    assert status0.step == 0 and status0.saved_steps == (0, 0)
    np.testing.assert_allclose(status0.estimate_m, state.estimate_m, rtol=1e-6, atol=1e-4)
    # The end of mission (hold): ArduPilot stays in GUIDED, PX4 switches to AUTO.LOITER; a
    # vehicle armed in the guided mode at the start is not switched again.
    assert swarm.link.modes_set == ([] if flavour == "ardupilot" else ["AUTO.LOITER"])


def test_a_dropped_peer_record_stops_the_barrier_naming_the_peer(tmp_path: Path) -> None:
    node, swarm, _ = make_node(tmp_path, step_timeout_s=0.5, drop_peer_record_at=1)
    with pytest.raises(NodeError, match=r"records of step 1 from the planners within 0.5 s \(missing: \[2\]\)"):
        node.run()
    assert [d.step for d in swarm.session.of_kind(Done)] == [-1, 0]
    assert swarm.session.closed and swarm.link.closed


def test_a_peer_that_left_is_not_waited_for(tmp_path: Path) -> None:
    """Planner 2 leaves before step 1: planner 1 flies steps 1 and 2 on its saved record of
    step 0 (its age grows), without waiting for the step timeout."""
    node, swarm, _ = make_node(tmp_path, step_timeout_s=30.0, peer_leaves_at=1)
    summary = node.run()
    assert summary["steps"] == STEPS
    saved = [s.saved_steps for s in swarm.session.of_kind(Status)]
    assert saved == [(0, 0), (1, 0), (2, 0)]
    assert all(math.isfinite(v) for s in swarm.session.of_kind(Status) for v in s.estimate_m)

"""The planner node: one process per drone (``fimnav plan``), at the edge of the math core.

It flies one drone of a mission. Zenoh carries the swarm's records, the payload's measurements
and, in lockstep simulation, the clock; MAVLink carries the setpoints to its own autopilot.
Each step, in order (docs/distributed.md, "The planner node"): read own position (MAVLink) → take own measurement (payload)
→ publish own record → collect the peers' records for the step → delayed view → estimate the
source → control step under constraints → send the setpoint (position with velocity
feed-forward). The maths is :func:`planner.agent.plan`, the same function the in-process
simulator runs, so a lockstep run reproduces the simulator.

Modules:

- :mod:`~planner.node.config`: :class:`NodeOptions` (the command line) and the frozen
  :class:`NodeConfig` the process runs on, built once from the mission.
- :mod:`~planner.node.core`: :class:`~planner.node.core.StepCore`, one step of one planner,
  the same for both clocks.
- :mod:`~planner.node.lockstep`: the lockstep driver (clock ticks over Zenoh, simulation).
- :mod:`~planner.node.realtime` and :mod:`~planner.node.realtime_preflight`: the real-time
  driver (wall clock, external autopilots).
- :mod:`~planner.node.takeover`: pilot take-over and ``fimnav handback``, in both clocks, and
  the one rule at a planner's start (a vehicle armed in a pilot's mode is left alone).
- :mod:`~planner.node.stopping`: the mission's ``on_stop``, told to the vehicle when the
  planner stops early (a signal, a fatal error, the launch stopping it).
- :mod:`~planner.node.swarm`, :mod:`~planner.node.inbox`: the Zenoh side.
- :mod:`~planner.node.io`: the injected clock and the waits that serve Zenoh and MAVLink.
- :mod:`~planner.node.steplog`: the JSON-lines step log, read back by a rejoining planner.
- :mod:`~planner.node.process`: :class:`PlannerNode`, which builds the parts and runs a driver.

Autopilot differences (ArduPilot, PX4) are read from the profile in :mod:`comms.autopilot`.

Pilot take-over, in both clocks (docs/in-the-field.md): a vehicle that leaves GUIDED/OFFBOARD
(a ground station or the RC switched it to LOITER, LAND, RTL, ...) is no longer commanded from
the moment the planner sees the mode; every step the planner publishes the drone's telemetry
position as a record flagged ``taken_over`` without a measurement (the others keep clear of
it) and, in lockstep, still answers the step (``Done(k)``: the clock never waits for a drone a
pilot flies). It never switches the vehicle back on its own: ``fimnav handback`` does, and the
planner plans again from where the drone is.
"""

from __future__ import annotations

from planner.node.config import NodeConfig, NodeError, NodeOptions
from planner.node.core import OWN_TRACK_STEPS, StepCore
from planner.node.inbox import Inbox
from planner.node.io import NodeClock
from planner.node.lockstep import LockstepDriver
from planner.node.process import PlannerNode
from planner.node.realtime import PeerRecordGrid, RealtimeDriver
from planner.node.steplog import read_step_log, replay_step_logs

__all__ = [
    "OWN_TRACK_STEPS",
    "Inbox",
    "LockstepDriver",
    "NodeClock",
    "NodeConfig",
    "NodeError",
    "NodeOptions",
    "PeerRecordGrid",
    "PlannerNode",
    "RealtimeDriver",
    "StepCore",
    "read_step_log",
    "replay_step_logs",
]

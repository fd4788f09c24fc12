"""The planner node process (``fimnav plan``): builds the node's parts from its
:class:`~planner.node.config.NodeConfig` and runs one of the two drivers."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from comms.latency import DelayedView
from comms.mavlink_client import LinkError, VehicleLink
from comms.session import SessionSettings, open_session
from planner.node.config import NodeConfig, NodeError, NodeOptions
from planner.node.core import StepCore, build_view
from planner.node.io import NodeClock, NodeIO
from planner.node.lockstep import LockstepDriver
from planner.node.realtime import PeerRecordGrid, RealtimeDriver
from planner.node.steplog import StepLog, read_step_log
from planner.node.stopping import OnStop, command_on_stop, stop_reason
from planner.node.swarm import Swarm
from planner.node.takeover import TakeoverWatch

#: Builds the vehicle link from (connection string, system id).
LinkFactory = Callable[[str, int], VehicleLink]


class PlannerNode:
    """One drone's planner: MAVLink to its vehicle, Zenoh to the swarm.

    Args:
        mission: the mission (``missions.format.schema.Mission``; duck-typed here), read once into
            the node's :class:`NodeConfig` (:attr:`config`).
        options: how to run.
        link_factory: builds the :class:`VehicleLink` (in-memory fakes in tests).
        session_factory: opens the Zenoh session (in-memory fakes in tests).
        clock: the node's clocks and its blocking wait (a simulated clock in tests).
        taken_over: a take-over is in force from the start, whatever the vehicle's mode (the
            launch restarts a planner whose drone a pilot flies: ``fimnav plan --taken-over``).
    """

    def __init__(
        self,
        mission: Any,
        options: NodeOptions,
        link_factory: LinkFactory | None = None,
        session_factory: Callable[[SessionSettings], Any] = open_session,
        clock: NodeClock | None = None,
        taken_over: bool = False,
    ) -> None:
        self.config = NodeConfig.from_mission(mission, options)
        #: What the vehicle is told when this planner stops early (the mission's ``on_stop``).
        self.on_stop: OnStop = getattr(mission, "on_stop", "hold")
        #: The outcome of that command, once the planner stopped early.
        self.stopped: dict[str, object] | None = None
        config = self.config
        self.clock = clock or NodeClock()
        self._link_factory = link_factory or self._default_link
        #: The delayed view of the peers' records (hop latency, injected faults).
        self.view: DelayedView = build_view(config)
        self.grid = PeerRecordGrid(config.uav, config.dt_wall_s, self.view)
        self.swarm = Swarm(config, session_factory, self.clock.wall, self.view.add if config.lockstep else self.grid.add)
        self.io = NodeIO(config, self.swarm, self.clock)
        self.core = StepCore(config, self.view, self.swarm)
        self.takeover = TakeoverWatch(self.io, in_force=taken_over)
        self._step_log: StepLog | None = None
        #: A rejoining planner's step logs: its predecessor's and its peers' (drone index → rows).
        self.predecessor_rows: dict[int, list[dict[str, Any]]] = {}

    def _default_link(self, conn: str, sysid: int) -> VehicleLink:
        c = self.config
        return VehicleLink(
            conn,
            sysid,
            signing_key=c.signing_key,
            wall=self.clock.wall,
            frame=c.setpoint_frame,
            mission_frame=c.mission_frame,
            altitude_reference=c.altitude_reference,
            flavour=None if c.flavour_setting == "auto" else c.flavour_setting,
            tlog=c.tlog_path,
        )

    def run(self) -> dict[str, Any]:
        """Fly the mission; return a summary (steps done, dropped messages, ...).

        A planner that stops early (any exception: Ctrl-C's KeyboardInterrupt, the exception a
        SIGTERM or SIGHUP raised, a fatal error) first tells its vehicle the mission's
        ``on_stop`` and waits briefly for it to confirm (:func:`command_on_stop`), then the
        exception goes on (the command's exit status is unchanged)."""
        try:
            self._open()
            self.swarm.drain(0.0)
            if self.config.lockstep:
                return LockstepDriver(self.config, self.io, self.core, self.takeover, self.predecessor_rows).run()
            return RealtimeDriver(self.config, self.io, self.core, self.takeover, self.grid, self.predecessor_rows).run()
        except BaseException as exc:
            self.stopped = command_on_stop(self.io, self.takeover, self.on_stop, stop_reason(exc))
            raise
        finally:
            self.close()

    def _open(self) -> None:
        """The Zenoh session, the step log (a rejoining planner first reads its predecessor's
        and, named as a launch names them, its peers' logs) and the vehicle link."""
        c = self.config
        self.swarm.open()
        if c.log_path is not None and c.rejoin:
            path = c.log_path
            self.predecessor_rows.update({c.drone_index: read_step_log(path)})
            if path.name == f"planner_{c.uav}.jsonl":
                for j in range(c.drone_count):
                    peer = path.with_name(f"planner_{j + 1}.jsonl")
                    if j != c.drone_index and peer.exists():
                        self.predecessor_rows[j] = read_step_log(peer)
        self._step_log = StepLog(c.log_path, append=c.rejoin)
        self.core.step_log = self._step_log
        try:
            self.io.link = self._link_factory(c.mavlink, c.sysid)
        except LinkError as exc:
            raise NodeError(f"uav {c.uav}: vehicle unreachable: {exc}") from None

    def close(self) -> None:
        """Release the link, the Zenoh session and the log (idempotent)."""
        if self.io.link is not None:
            self.io.link.close()
            self.io.link = None
        self.swarm.close()
        if self._step_log is not None:
            self._step_log.close()

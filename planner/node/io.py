"""The planner node's I/O loop, shared by both drivers: the injected clocks, the vehicle link
with its autopilot profile, and waiting on a condition while serving Zenoh and MAVLink
(blocking in select() on the MAVLink socket and the Zenoh self-pipe, never busy polling)."""

from __future__ import annotations

import select
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from comms.autopilot import FlavourInfo, flavour_info
from comms.mavlink_client import VehicleLink
from planner.node.config import NodeConfig, NodeError
from planner.node.swarm import Swarm


def wait_readable(fds: list[int], timeout_s: float) -> None:
    """Block until one of ``fds`` is readable or ``timeout_s`` (wall s) has passed."""
    try:
        select.select(fds, [], [], max(timeout_s, 0.0))
    except (OSError, ValueError):
        pass


@dataclass(frozen=True)
class NodeClock:
    """The node's time, injected (tests pass a simulated clock).

    Attributes:
        wall: monotonic wall clock (s): timeouts, link watch, the setpoint stream.
        unix: UNIX wall clock (s): the real-time step grid and record times.
        wait_readable: blocks until a file descriptor is readable or a timeout (wall s) ends.
    """

    wall: Callable[[], float] = time.monotonic
    unix: Callable[[], float] = time.time
    wait_readable: Callable[[list[int], float], None] = wait_readable


class NodeIO:
    """The vehicle link, the swarm and the clock of one node, and the waits that serve them.

    Args:
        config: the node's configuration. swarm: its Zenoh side. clock: its time.
    """

    def __init__(self, config: NodeConfig, swarm: Swarm, clock: NodeClock) -> None:
        self.config = config
        self.swarm = swarm
        self.clock = clock
        self.link: VehicleLink | None = None
        #: Called after every serve (real time: the link-loss watch).
        self.on_served: Callable[[], None] | None = None

    def require_link(self) -> VehicleLink:
        """The open vehicle link; NodeError once it is closed."""
        if self.link is None:
            raise NodeError(f"uav {self.config.uav}: the vehicle link is closed")
        return self.link

    @property
    def profile(self) -> FlavourInfo:
        """The autopilot profile of the vehicle's flavour (forced, or from its HEARTBEAT)."""
        return flavour_info(self.require_link().flavour)

    def mode_name(self, custom_mode: int) -> str:
        """The name the link sets a mode of the profile by (PX4: ``AUTO.LOITER``, ...)."""
        return self.profile.require_mode(custom_mode).qualified_name

    @property
    def guided_mode(self) -> str:
        """The mode that follows the planner's setpoints: GUIDED (ArduPilot), OFFBOARD (PX4)."""
        return self.mode_name(self.profile.guided_mode)

    def wait(self, predicate: Callable[[], bool], timeout_s: float, what: str, missing: Callable[[], Any] | None = None) -> None:
        """Serve Zenoh and MAVLink until ``predicate()``; NodeError naming ``what`` on timeout."""
        link = self.require_link()
        wall = self.clock.wall
        deadline = wall() + timeout_s
        self.swarm.drain(0.0)
        link.pump(0.0)
        while not predicate():
            remaining = deadline - wall()
            if remaining <= 0:
                detail = f" (missing: {missing()})" if missing is not None else ""
                raise NodeError(f"uav {self.config.uav}: no {what} within {timeout_s:g} s{detail}")
            self.sleep_io(min(remaining, 0.25))

    def sleep_io(self, timeout_s: float) -> None:
        """Block on the MAVLink socket and the Zenoh self-pipe for at most ``timeout_s`` (wall
        s; in real time at most one setpoint-stream period), then serve both."""
        link = self.require_link()
        if not self.config.lockstep:
            timeout_s = min(timeout_s, link.stream_period_s)
        fd = link.fileno()
        inbox = self.swarm.inbox
        self.clock.wait_readable([inbox.wake_r] + ([fd] if fd is not None else []), timeout_s)
        inbox.clear_wake()
        self.swarm.drain(0.0)
        link.pump(0.0)
        if self.on_served is not None:
            self.on_served()

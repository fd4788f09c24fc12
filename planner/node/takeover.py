"""Pilot take-over, in both clocks (docs/in-the-field.md): a vehicle that leaves the guided
mode (GUIDED/OFFBOARD) has been taken over; the planner stops commanding it and never switches
it back on its own: only ``fimnav handback`` does.

The one rule holds on every path a planner starts by (a start, a rejoin, a restart by the
launch; lockstep and real time): a vehicle found armed in any mode but the guided one is a
pilot's from the planner's first moment (:meth:`TakeoverWatch.found_at_start`), and so is one
whose take-over the launch says is in force (``fimnav plan --taken-over``). So is one found
so when its link returns after a loss (:meth:`TakeoverWatch.found_after_link_loss`): a
failsafe's mode change during the loss looks like a pilot's, and the planner takes neither."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from comms.mavlink_client import LinkError
from planner.node.config import NodeError
from planner.node.io import NodeIO

log = logging.getLogger("fimnav.plan")


class TakeoverWatch:
    """Whether a pilot flies the drone, and every take-over and mode change seen.

    Args:
        io: the node's I/O (its link and profile).
    """

    def __init__(self, io: NodeIO, in_force: bool = False) -> None:
        self.io = io
        self.uav = io.config.uav
        #: A take-over is in force from the start whatever the vehicle's mode (the launch
        #: restarted this planner while a pilot flew its drone: ``fimnav plan --taken-over``).
        self.in_force = in_force
        #: The pilot's take-over in force ({"step", "mode"}), or None.
        self.current: dict[str, Any] | None = None
        #: Every take-over ({"step", "mode"}, and "handed_back_step" once handed back).
        self.takeovers: list[dict[str, Any]] = []
        #: Steps flown by a pilot.
        self.steps = 0
        #: Every mode the vehicle was seen in outside the guided mode.
        self.mode_changes: list[str] = []
        self._reported_mode: str | None = None

    @property
    def active(self) -> bool:
        """Whether a pilot flies the drone now."""
        return self.current is not None

    def watch(self, k: int) -> None:
        """A vehicle that left GUIDED/OFFBOARD while the link is up has been taken over (a
        pilot, a ground station or a failsafe). The planner stops commanding it at once (the
        setpoint stream ends), says so, and never switches it back on its own: only
        ``fimnav handback`` does (:meth:`hand_back`). Mode changes while taken over are
        reported too."""
        link = self.io.require_link()
        want = self.io.guided_mode
        now = link.mode_name()
        link.left_guided = False  # read now (the link already stopped the stream when it heard it)
        if not link.in_mode(want) and now != self._reported_mode:
            self.mode_changes.append(now)
            if self.current is None:
                link.set_stream(None)
                self.current = {"step": k, "mode": now}
                self.takeovers.append(dict(self.current))
                log.warning(
                    "uav %d: taken over at step %d: the vehicle left %s (now %s); not commanding it; publishing its "
                    "position without measurements; hand it back with: fimnav handback MISSION --uav %d",
                    self.uav,
                    k,
                    want,
                    now,
                    self.uav,
                )
            else:
                log.warning("uav %d: taken over, the vehicle is now in %s", self.uav, now)
        self._reported_mode = now if not link.in_mode(want) else None

    def found_at_start(self, where: str) -> bool:
        """The one rule at a planner's start (``where``: ``"start"`` or ``"rejoin"``): a
        vehicle armed in a mode other than the guided one is flown by a pilot (a ground station,
        the RC, a failsafe), and so is every vehicle when :attr:`in_force`. Then the planner
        does not change its mode, flies nothing, publishes its position flagged taken over and
        waits for ``fimnav handback`` (True, logged once); False: the planner may prepare it
        (disarmed on the ground) or fly it (armed in the guided mode)."""
        link = self.io.require_link()
        want = self.io.guided_mode
        now = link.mode_name()
        pilot = link.telemetry.armed and not link.in_mode(want)
        if not (pilot or self.in_force):
            return False
        why = (
            f"the vehicle is {'armed' if link.telemetry.armed else 'disarmed'} in {now} and the launch restarted this planner while a pilot flew it"
            if not pilot
            else f"the vehicle is armed in {now}, not {want}: a pilot or a ground station flies it"
        )
        self._take({"step": None, "mode": now, "at_start": where}, f"at {where}: {why}")
        return True

    def found_after_link_loss(self, k: int) -> bool:
        """The one rule when the vehicle link returns at step ``k`` after a loss: a vehicle
        found armed in another mode than the guided one was switched while the link was down,
        by a pilot, a ground station or its own failsafe, which the planner cannot tell apart.
        It is taken over from step ``k`` as at a start (:meth:`found_at_start`: no mode change,
        no setpoint, its position published flagged taken over, until ``fimnav handback``;
        True, logged once); False: in the guided mode (or disarmed, which the driver refuses),
        flown on."""
        link = self.io.require_link()
        want = self.io.guided_mode
        now = link.mode_name()
        if not link.telemetry.armed or link.in_mode(want):
            return False
        why = f"the vehicle is armed in {now}, not {want}: a pilot, a ground station or its failsafe changed the mode while the link was down"
        self._take({"step": k, "mode": now, "reason": "after link loss"}, f"at step {k} after the link loss: {why}")
        return True

    def _take(self, entry: dict[str, Any], why: str) -> None:
        """A take-over found (not seen happen): the stream ends, ``entry`` is recorded and the
        operator told once, with ``why`` and the hand-back command."""
        link = self.io.require_link()
        link.set_stream(None)
        link.left_guided = False
        self.current = entry
        self.takeovers.append(dict(entry))
        if not link.in_mode(self.io.guided_mode):
            self.mode_changes.append(entry["mode"])
            self._reported_mode = entry["mode"]
        log.warning(
            "uav %d: taken over %s; not changing its mode, not commanding it; publishing its position without "
            "measurements; hand it back with: fimnav handback MISSION --uav %d",
            self.uav,
            why,
            self.uav,
        )

    def still_taken_over(self, k: int, enter_guided: Callable[[np.ndarray], None]) -> bool:
        """Whether the pilot still flies the drone at step ``k``: taken over and not handed
        back by a ``fimnav handback`` that arrived (:meth:`hand_back`). A take-over found at the
        start is dated by the first step it holds."""
        if self.current is not None and self.current["step"] is None:
            self.current["step"] = k
            self.takeovers[-1]["step"] = k
        return self.current is not None and not (self.io.swarm.handback_requested() and self.hand_back(k, enter_guided))

    def hand_back(self, k: int, enter_guided: Callable[[np.ndarray], None]) -> bool:
        """``fimnav handback``: switch the vehicle back to GUIDED/OFFBOARD at its position
        (``enter_guided(hold position m, ENU)``, the driver's sequence) and plan again from step
        ``k``; False (logged) when the vehicle refuses or is not armed."""
        link = self.io.require_link()
        pos = link.telemetry.position_enu_m
        if not link.telemetry.armed or pos is None:
            log.error("uav %d: hand-back refused: the vehicle is %s", self.uav, "disarmed" if not link.telemetry.armed else "without a position")
            return False
        try:
            enter_guided(pos.astype(float))
        except LinkError as exc:
            link.set_stream(None)
            log.error("uav %d: hand-back refused: %s", self.uav, exc)
            return False
        if self.current is None:
            raise NodeError(f"uav {self.uav}: internal: hand-back at step {k} of a drone not taken over")
        self.takeovers[-1]["handed_back_step"] = k
        self.current = None
        self._reported_mode = None
        log.warning("uav %d: handed back at step %d: in %s, planning again", self.uav, k, self.io.guided_mode)
        return True

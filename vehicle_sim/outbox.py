"""What a simulated vehicle sends besides telemetry: STATUSTEXT and COMMAND_ACK, on its link."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

from vehicle_sim.link import MavlinkLink

log = logging.getLogger("vehicle_sim.vehicle")

#: Repeated warnings of the same key are rate limited to one per this many wall seconds.
STATUSTEXT_MIN_GAP_S = 1.0


class Outbox:
    """The vehicle's sending side: any message, STATUSTEXT (rate limited per key) and
    COMMAND_ACK (counted).

    Args:
        link: the MAVLink endpoint. sysid: the vehicle's system id (for the log).
        wall: wall clock (s), used only for the STATUSTEXT rate limit.
    """

    def __init__(self, link: MavlinkLink, sysid: int, wall: Callable[[], float]) -> None:
        self.link = link
        self.mavlink = link.mavlink
        self.sysid = sysid
        self.wall = wall
        self.acks_sent = 0
        self._text_last_wall_s: dict[str, float] = {}

    def send(self, msg: Any) -> None:
        """Send one MAVLink message."""
        self.link.send(msg)

    def statustext(self, severity: int, text: str, key: str | None = None) -> None:
        """Send a STATUSTEXT (≤ 50 chars); with ``key``, at most one per second of wall time."""
        if key is not None:
            now = self.wall()
            if now - self._text_last_wall_s.get(key, -math.inf) < STATUSTEXT_MIN_GAP_S:
                return
            self._text_last_wall_s[key] = now
        log.info("sysid %d: %s", self.sysid, text)
        self.link.send(self.mavlink.MAVLink_statustext_message(severity, text[:50].encode("utf-8")))

    def ack(self, msg: Any, command: int, result: int, text: str | None = None, severity: int = 4) -> int:
        """COMMAND_ACK of ``command`` to the sender of ``msg``, then the STATUSTEXT reason if
        any; returns ``result``."""
        self.acks_sent += 1
        self.link.send(self.mavlink.MAVLink_command_ack_message(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))
        if text:
            self.statustext(severity, text)
        return result

"""The race between a pilot's mode change and the next setpoint (docs/in-the-field.md): a
heartbeat saying the vehicle left GUIDED/OFFBOARD that has arrived when a setpoint falls due
stops that setpoint and the stream, on a real UDP socket on 127.0.0.1 (the planner's
:class:`comms.mavlink_client.VehicleLink` against a scripted autopilot: pymavlink frames in,
what the link sends read back from the socket).

The same link while it is lost (no heartbeat for 2 s): it streams nothing; a message from the
vehicle then makes it ask for a heartbeat; the heartbeat decides: the guided mode resumes the
stream, a pilot's mode ends it before anything is sent."""

from __future__ import annotations

import os
import select
import socket
from typing import Any

import numpy as np
import pytest

from comms.autopilot import flavour_info

pytestmark = pytest.mark.integration


class ScriptedAutopilot:
    """A UDP endpoint on 127.0.0.1 speaking as system 1, component 1 of ``flavour``: it sends
    the heartbeats the test asks for and reads what the planner's link sent."""

    def __init__(self, flavour: str) -> None:
        os.environ["MAVLINK20"] = "1"
        from pymavlink import mavutil

        self.info = flavour_info(flavour)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.mav = mavutil.mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.parser = mavutil.mavlink.MAVLink(None)
        self.peer: tuple[str, int] | None = None

    def received(self, timeout_s: float = 0.0) -> list[Any]:
        """Every message the link sent that is in the socket now (waiting up to ``timeout_s``
        for the first)."""
        out = []
        while select.select([self.sock], [], [], timeout_s)[0]:
            data, self.peer = self.sock.recvfrom(65536)
            out.extend(self.parser.parse_buffer(data) or [])
            timeout_s = 0.0
        return out

    def heartbeat(self, custom_mode: int, armed: bool = True) -> None:
        assert self.peer is not None, "the link has not spoken yet"
        base = 1 | (128 if armed else 0)  # CUSTOM_MODE_ENABLED, SAFETY_ARMED
        msg = self.mav.heartbeat_encode(2, self.info.autopilot, base, custom_mode, 4)
        self.sock.sendto(msg.pack(self.mav), self.peer)

    def send_attitude(self) -> None:
        """Any message but a heartbeat (a vehicle whose link is back sends telemetry first)."""
        assert self.peer is not None, "the link has not spoken yet"
        self.sock.sendto(self.mav.attitude_encode(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0).pack(self.mav), self.peer)

    def close(self) -> None:
        self.sock.close()


@pytest.mark.parametrize(("flavour", "pilot_mode"), [("ardupilot", "LOITER"), ("px4", "POSCTL")])
def test_a_mode_change_that_arrived_stops_the_setpoint_due(flavour: str, pilot_mode: str) -> None:
    from comms.mavlink_client import VehicleLink

    ap = ScriptedAutopilot(flavour)
    now = [0.0]
    link = VehicleLink(f"udpout:127.0.0.1:{ap.port}", 1, wall=lambda: now[0])
    try:
        link.pump(0.0)  # our heartbeat: the autopilot learns where we are
        assert ap.received(5.0)
        guided = ap.info.guided_mode
        ap.heartbeat(guided)
        link.wait_for(lambda: link.telemetry.custom_mode == guided, 5.0, "the heartbeat in the guided mode")
        target = np.array([1.0, 2.0, 8.0])
        link.set_stream(lambda _t: (target, None), period_s=0.25)  # one setpoint now
        assert link.setpoints_sent == 1
        assert any(m.get_type().startswith("SET_POSITION_TARGET") for m in ap.received(5.0))
        # The pilot's mode change arrives in the middle of the stream's period ...
        mode = ap.info.mode_by_name(pilot_mode)
        assert mode is not None
        ap.heartbeat(mode.custom_mode)
        fd = link.fileno()
        assert fd is not None and select.select([fd], [], [], 5.0)[0], "the heartbeat did not reach the link's socket"
        # ... and the next setpoint falls due before the link has read it.
        now[0] += 1.0
        link.pump(0.0)
        sent = [m.get_type() for m in ap.received(0.0)]
        assert link.telemetry.custom_mode == mode.custom_mode
        assert link.setpoints_sent == 1 and not any(t.startswith("SET_POSITION_TARGET") for t in sent), sent
        assert link.left_guided and not link.streaming
        # Nothing more is streamed afterwards either.
        for _ in range(3):
            now[0] += 1.0
            link.pump(0.0)
        assert link.setpoints_sent == 1
        assert not any(m.get_type().startswith("SET_POSITION_TARGET") for m in ap.received(0.0))
    finally:
        link.close()
        ap.close()


@pytest.mark.parametrize("back_in", ["guided", "pilot"])
@pytest.mark.parametrize(("flavour", "pilot_mode"), [("ardupilot", "LOITER"), ("px4", "POSCTL")])
def test_nothing_is_streamed_while_the_link_is_lost_and_a_heartbeat_decides_after(flavour: str, pilot_mode: str, back_in: str) -> None:
    from comms.mavlink_client import LINK_LOSS_S, VehicleLink

    ap = ScriptedAutopilot(flavour)
    now = [0.0]
    link = VehicleLink(f"udpout:127.0.0.1:{ap.port}", 1, wall=lambda: now[0])

    def setpoints_in(msgs: list[Any]) -> int:
        return sum(1 for m in msgs if m.get_type().startswith("SET_POSITION_TARGET"))

    try:
        link.pump(0.0)
        assert ap.received(5.0)
        guided = ap.info.guided_mode
        ap.heartbeat(guided)
        link.wait_for(lambda: link.telemetry.custom_mode == guided, 5.0, "the heartbeat in the guided mode")
        link.set_stream(lambda _t: (np.array([1.0, 2.0, 8.0]), None), period_s=0.25)
        assert link.setpoints_sent == 1 and setpoints_in(ap.received(5.0)) == 1
        # No heartbeat for longer than the loss threshold: the link is lost, nothing is streamed.
        now[0] += LINK_LOSS_S + 0.5
        for _ in range(4):
            now[0] += 0.3
            link.pump(0.0)
        assert link.lost and link.streaming and link.setpoints_sent == 1
        assert setpoints_in(ap.received(0.0)) == 0
        # The vehicle is heard again, but not its mode yet: the link asks for a heartbeat.
        ap.send_attitude()
        fd = link.fileno()
        assert fd is not None and select.select([fd], [], [], 5.0)[0]
        now[0] += 0.3
        link.pump(0.0)
        sent = ap.received(5.0)
        assert any(m.get_type() == "COMMAND_LONG" and m.command == 512 and int(m.param1) == 0 for m in sent), [m.get_type() for m in sent]
        assert setpoints_in(sent) == 0 and link.lost
        # The heartbeat decides.
        mode = ap.info.mode_by_name(pilot_mode)
        assert mode is not None
        ap.heartbeat(guided if back_in == "guided" else mode.custom_mode)
        assert select.select([fd], [], [], 5.0)[0]
        now[0] += 0.3
        link.pump(0.0)
        assert not link.lost
        if back_in == "guided":
            assert link.streaming and link.setpoints_sent == 2 and setpoints_in(ap.received(5.0)) == 1
        else:
            assert not link.streaming and link.left_guided and link.setpoints_sent == 1
            for _ in range(3):
                now[0] += 0.3
                link.pump(0.0)
            assert link.setpoints_sent == 1 and setpoints_in(ap.received(0.0)) == 0
    finally:
        link.close()
        ap.close()

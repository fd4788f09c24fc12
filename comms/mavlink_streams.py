"""Asking the vehicle for its telemetry streams: SET_MESSAGE_INTERVAL per message, with
ArduPilot's REQUEST_DATA_STREAM groups as the fallback where the autopilot refuses it or does
not answer (older firmware, some radios)."""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any, Protocol

from comms.mavlink_telemetry import (
    AUTOPILOT_COMPONENT,
    MSG_EKF_STATUS_REPORT,
    MSG_EXTENDED_SYS_STATE,
    MSG_GLOBAL_POSITION_INT,
    MSG_GPS_RAW_INT,
    MSG_HOME_POSITION,
    MSG_LOCAL_POSITION_NED,
    MSG_SYS_STATUS,
)
from comms.mavlink_transport import LinkError, LinkTimeout

#: REQUEST_DATA_STREAM groups (ArduPilot) that carry each message, for the fallback.
DATA_STREAM_OF = {
    MSG_SYS_STATUS: 2,
    MSG_GPS_RAW_INT: 2,
    MSG_LOCAL_POSITION_NED: 6,
    MSG_GLOBAL_POSITION_INT: 6,
    MSG_EKF_STATUS_REPORT: 12,
    MSG_HOME_POSITION: 12,
    MSG_EXTENDED_SYS_STATE: 12,
}


class CommandLink(Protocol):
    """What :func:`request_streams` uses of the link (:class:`comms.mavlink_client.VehicleLink`)."""

    mavutil: Any
    mav: Any
    target_system: int

    def command(self, command: int, params: Iterable[float] = (), timeout_s: float = 15.0, what: str = "") -> int:
        """COMMAND_LONG, acknowledged (LinkError: refused; LinkTimeout: unanswered)."""
        ...


def request_streams(link: CommandLink, rates_hz: dict[int, float], optional: Iterable[int] = ()) -> list[str]:
    """Request each message at its rate with SET_MESSAGE_INTERVAL; where the autopilot
    refuses it or does not answer (older firmware, some radios), fall back to
    REQUEST_DATA_STREAM for the message's ArduPilot stream group. Messages in ``optional``
    may be refused without a fallback (e.g. EKF_STATUS_REPORT on PX4). Returns notes of
    what fell back, for the log."""
    m = link.mavutil.mavlink
    optional = set(optional)
    notes: list[str] = []
    fallback: dict[int, float] = {}
    unanswered = False
    for msg_id, hz in rates_hz.items():
        try:
            if unanswered:  # one unanswered request is enough: do not spend 6 s on each
                raise LinkTimeout("SET_MESSAGE_INTERVAL not answered")
            link.command(m.MAV_CMD_SET_MESSAGE_INTERVAL, [msg_id, 1e6 / hz], timeout_s=6.0, what=f"SET_MESSAGE_INTERVAL({msg_id})")
        except LinkTimeout:
            unanswered = True
            if msg_id in DATA_STREAM_OF:
                group = DATA_STREAM_OF[msg_id]
                fallback[group] = max(fallback.get(group, 0.0), hz)
            notes.append(f"message {msg_id}: no answer to SET_MESSAGE_INTERVAL, REQUEST_DATA_STREAM instead")
        except LinkError as exc:
            if msg_id in optional:
                notes.append(f"message {msg_id}: not streamed ({exc})")
                continue
            if msg_id in DATA_STREAM_OF:
                group = DATA_STREAM_OF[msg_id]
                fallback[group] = max(fallback.get(group, 0.0), hz)
            notes.append(f"message {msg_id}: SET_MESSAGE_INTERVAL refused, REQUEST_DATA_STREAM instead")
    for group, hz in fallback.items():
        link.mav.request_data_stream_send(link.target_system, AUTOPILOT_COMPONENT, group, max(1, int(math.ceil(hz))), 1)
    return notes

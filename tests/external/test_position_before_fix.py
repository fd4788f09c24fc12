"""GLOBAL_POSITION_INT before the first GPS fix: ArduPilot sends lat = lon = 0, which is no
position (it would be a point in the Gulf of Guinea); the link must not take it as one."""

from __future__ import annotations

import os

import numpy as np

from comms.geodesy import MissionFrame
from comms.mavlink_client import VehicleLink


def test_global_position_at_zero_zero_is_no_position() -> None:
    os.environ["MAVLINK20"] = "1"
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    frame = MissionFrame(47.397742, 8.545594, 488.0)
    link = VehicleLink("udpout:127.0.0.1:9", 1, frame="global", mission_frame=frame)
    try:
        enc = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)

        def received(msg: object) -> object:  # through the parser, as a frame off the wire
            return mavlink.MAVLink(None).parse_char(msg.pack(enc))  # type: ignore[attr-defined]

        link._handle(received(mavlink.MAVLink_global_position_int_message(1000, 0, 0, 0, 0, 0, 0, 0, 0)))
        assert link.telemetry.position_enu_m is None
        lat, lon = int(round(47.397742e7)), int(round(8.545594e7))
        link._handle(received(mavlink.MAVLink_global_position_int_message(2000, lat, lon, 488_000, 8_000, 0, 0, 0, 0)))
        assert link.telemetry.position_enu_m is not None
        np.testing.assert_allclose(link.telemetry.position_enu_m, [0.0, 0.0, 8.0], atol=0.02)
    finally:
        link.close()

"""The planner against a scripted autopilot (a MAVLink endpoint of the test): what it does when
the autopilot refuses SET_MESSAGE_INTERVAL (REQUEST_DATA_STREAM instead), and what it says
while the autopilot is not ready to fly. vehicle_sim is always ready and accepts every
interval, so these paths need an autopilot that behaves otherwise."""

from __future__ import annotations

import os
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.external.helpers import write_mission
from tests.support.proc import Proc, fimnav

pytestmark = pytest.mark.integration


class ScriptedAutopilot:
    """An ArduPilot-like endpoint on UDP: heartbeats at 5 Hz, a GPS without fix, an EKF
    without position, no home and no EKF origin; every COMMAND_LONG is answered UNSUPPORTED;
    REQUEST_DATA_STREAM requests are recorded."""

    def __init__(self, answer_commands: bool = True) -> None:
        os.environ["MAVLINK20"] = "1"
        self.answer_commands = answer_commands
        from pymavlink.dialects.v20 import ardupilotmega as mavlink

        self.m = mavlink
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.peer: tuple[str, int] | None = None
        self.enc = mavlink.MAVLink(self, srcSystem=1, srcComponent=1)
        self.parser = mavlink.MAVLink(None)
        self.data_streams: list[tuple[int, int]] = []
        self.commands: list[int] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def write(self, buf: bytes) -> None:  # the encoder's file
        if self.peer is not None:
            self.sock.sendto(buf, self.peer)

    def _run(self) -> None:
        m = self.m
        self.sock.settimeout(0.2)
        while not self._stop.is_set():
            try:
                data, addr = self.sock.recvfrom(65535)
            except socket.timeout:
                data, addr = b"", None
            if addr is not None:
                self.peer = addr
                for msg in self.parser.parse_buffer(data) or []:
                    self._on(msg)
            self.enc.heartbeat_send(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 0, m.MAV_STATE_STANDBY)
            self.enc.gps_raw_int_send(0, 1, 0, 0, 0, 65535, 65535, 0, 0, 0)
            self.enc.ekf_status_report_send(0, 0, 0, 0, 0, 0)

    def _on(self, msg: Any) -> None:
        m = self.m
        if msg.get_type() == "COMMAND_LONG":
            self.commands.append(msg.command)
            if self.answer_commands:
                self.enc.command_ack_send(msg.command, m.MAV_RESULT_UNSUPPORTED, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
        elif msg.get_type() == "REQUEST_DATA_STREAM":
            self.data_streams.append((msg.req_stream_id, msg.req_message_rate))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.sock.close()


@pytest.fixture(params=["refusing", pytest.param("silent", marks=pytest.mark.slow)])
def autopilot(request: pytest.FixtureRequest) -> Iterator[ScriptedAutopilot]:
    """An autopilot that answers every command UNSUPPORTED, or (slow) answers none."""
    ap = ScriptedAutopilot(answer_commands=request.param == "refusing")
    yield ap
    ap.close()


def test_refused_intervals_fall_back_to_data_streams_and_the_readiness_wait_says_what_is_missing(tmp_path: Path, autopilot: ScriptedAutopilot) -> None:
    mission = write_mission(tmp_path / "m.yaml", "notready", [[10.0, 20.0, 8.0]], 5, "hold")
    p = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--mavlink", f"udpout:127.0.0.1:{autopilot.port}", "--preflight-timeout", "3"))
    try:
        assert p.wait(60.0) == 1, p.tail()
    finally:
        p.stop()
    assert "autopilot ardupilot (HEARTBEAT.autopilot = 3)" in p.err
    if autopilot.answer_commands:
        assert "SET_MESSAGE_INTERVAL refused, REQUEST_DATA_STREAM instead" in p.err
    else:  # one unanswered request (6 s), then data streams for every message at once
        assert "no answer to SET_MESSAGE_INTERVAL, REQUEST_DATA_STREAM instead" in p.err
        assert autopilot.commands.count(511) == 3, autopilot.commands  # 3 tries of the first only
    # POSITION (6), EXTENDED_STATUS (2) and EXTRA3 (12, home) groups, each at least once
    assert {6, 2, 12} <= {sid for sid, _ in autopilot.data_streams}, autopilot.data_streams
    assert "waiting for the vehicle: GPS 3D fix (fix_type 1" in p.err
    last = p.err.strip().splitlines()[-1]
    assert "vehicle not ready to fly after 3 s; still waiting for:" in last
    for what in ("GPS 3D fix", "EKF position estimate (EKF_STATUS_REPORT flags 0x0000)", "home position (HOME_POSITION)", "EKF origin (GPS_GLOBAL_ORIGIN)"):
        assert what in last, last
    assert "Traceback" not in p.err
    # Nothing was armed or moved: no ARM, no mode change, no take-off was sent.
    assert not {400, 176, 22} & set(autopilot.commands), autopilot.commands

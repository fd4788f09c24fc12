"""One ground-station port for a launched swarm (``fimnav launch --realtime --gcs ENDPOINT``),
real processes on 127.0.0.1.

A ground station (pymavlink, system 255, component 190, the way MAVProxy and QGroundControl
talk) listens on a free UDP port; the launch forwards its three simulated vehicles there. The
ground station sees three systems (1, 2, 3) with positions that move as the swarm flies; a
command it addresses to system 2 is answered by system 2 and reaches only vehicle 2 (its
.tlog has it, the others' do not).
"""

from __future__ import annotations

import pytest

import os
import socket
import time
from pathlib import Path

import numpy as np
import yaml

from .test_launch import Launch, launches, processes_mentioning  # noqa: F401 (fixture)

SPEEDUP = 8.0
MAV_CMD_REQUEST_MESSAGE, AUTOPILOT_VERSION = 512, 148


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def commands_in(tlog: Path, command: int) -> int:
    """COMMAND_LONGs of ``command`` from system 255 in a vehicle's .tlog."""
    from pymavlink import mavutil

    log = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    n = 0
    while (m := log.recv_match(type="COMMAND_LONG")) is not None:
        n += m.get_srcSystem() == 255 and int(m.command) == command
    return n


@pytest.mark.slow  # a real-time launch (17 s); the default run keeps under 5 minutes
def test_one_ground_station_port_sees_every_vehicle_and_commands_reach_their_target(tmp_path: Path, launches: list[Launch]) -> None:  # noqa: F811
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    port = free_udp_port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255, source_component=190)
    mission = tmp_path / "gcs.yaml"
    mission.write_text(yaml.safe_dump({
        "id": "gcs", "dt_s": 1.0, "steps": 30, "seed": 3, "end_action": "land",
        "drones": {"count": 3, "roles": ["ranging", "bearing", "joint"],
                   "start": {"positions_m": [[10.0, 20.0, 8.0], [30.0, 20.0, 8.0], [50.0, 20.0, 8.0]]}},
        "source": {"position_m": [60.0, 90.0, 2.0]},
    }))
    out = tmp_path / "run"
    run = Launch(mission, out, "--realtime", "--speedup", str(SPEEDUP), "--start-delay", "8", "--gcs", f"udpout:127.0.0.1:{port}")
    launches.append(run)
    try:
        seen: dict[int, list[tuple[float, float, float]]] = {1: [], 2: [], 3: []}
        acks: dict[int, int] = {}
        asked = False
        deadline = time.monotonic() + 180.0
        while time.monotonic() < deadline and run.proc.poll() is None:  # the whole flight
            m = gcs.recv_match(blocking=True, timeout=0.5)
            if m is None:
                continue
            sysid = m.get_srcSystem()
            if m.get_type() == "GLOBAL_POSITION_INT" and sysid in seen:
                seen[sysid].append((m.lat * 1e-7, m.lon * 1e-7, m.relative_alt * 1e-3))
            elif m.get_type() == "COMMAND_ACK" and int(m.command) == MAV_CMD_REQUEST_MESSAGE and m.target_system == 255:
                acks[sysid] = acks.get(sysid, 0) + 1
            if not asked and min(len(v) for v in seen.values()) >= 5:
                gcs.mav.heartbeat_send(6, 8, 0, 0, 0)
                gcs.mav.command_long_send(2, 1, MAV_CMD_REQUEST_MESSAGE, 0, AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0)
                asked = True
        code, stdout, stderr = run.wait(240.0)
    finally:
        gcs.close()
    assert code == 0, stderr[-3000:]
    assert "ground station port udpout:127.0.0.1" in stderr and "Traceback" not in stderr
    # Three systems, each moving (the swarm flew: metres between its first and last report).
    for sysid, track in seen.items():
        assert len(track) >= 30, (sysid, len(track))
        a, b = np.array(track[0]), np.array(track[-1])
        moved_m = float(np.hypot((b[0] - a[0]) * 111_320.0, (b[1] - a[1]) * 111_320.0 * np.cos(np.radians(a[0]))) + abs(b[2] - a[2]))
        assert moved_m > 3.0, (sysid, moved_m)
    # The command to system 2 reached vehicle 2 only, and only system 2 answered.
    assert acks == {2: 1}, acks
    counts = {i: commands_in(out / "tlogs" / f"vehicle_{i}.tlog", MAV_CMD_REQUEST_MESSAGE) for i in (1, 2, 3)}
    assert counts == {1: 0, 2: 1, 3: 0}, counts
    assert not processes_mentioning(str(out))

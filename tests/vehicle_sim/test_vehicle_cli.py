"""``fimnav vehicle`` as a real process: ready line, several vehicles, mission start positions,
lockstep over zenoh, bad input without traceback. Every process group is killed at the end."""

from __future__ import annotations

import json
import socket
import time
from pathlib import Path

import numpy as np
import pytest

from tests.support.net import free_port
from tests.support.proc import Proc, fimnav
from tests.vehicle_sim.clients import connect_client, hello, mavlink as R, wait_msg

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
MISSION = ROOT / "missions" / "paper" / "ranging_nlos.yaml"


def _ready(proc: Proc) -> dict:
    line = proc.expect(r"\{\"event\": \"ready\".*\}\n", timeout_s=30).group(0)
    return json.loads(line)


def test_several_vehicles_in_one_process():
    proc = Proc(fimnav("vehicle", "--sysid", "4", "--count", "3", "--mavlink", "udpin:127.0.0.1:0", "--speedup", "5"))
    clients = []
    try:
        ready = _ready(proc)
        vehicles = ready["vehicles"]
        assert [v["sysid"] for v in vehicles] == [4, 5, 6]
        assert len({v["mavlink"] for v in vehicles}) == 3
        for v in vehicles:
            c = connect_client(v["mavlink"])
            clients.append(c)
            hb = hello(c, v["sysid"])
            assert hb.get_srcComponent() == 1 and hb.autopilot == R.MAV_AUTOPILOT_ARDUPILOTMEGA
        # vehicle 5 starts 2 m east of vehicle 4 (--spacing default)
        m = wait_msg(clients[1], "LOCAL_POSITION_NED", lambda m: m.get_srcSystem() == 5)
        assert (m.x, m.y, m.z) == (0.0, 2.0, 0.0)
    finally:
        for c in clients:
            c.close()
        proc.stop()


def test_mission_start_position_and_airborne():
    from missions.format.loader import load_mission

    mission = load_mission(MISSION)
    expect = mission.drones.start_positions_m()[2]  # drone 3 (sysid 3), ENU
    proc = Proc(fimnav("vehicle", "--mission", str(MISSION), "--sysid", "3", "--airborne",
                       "--mavlink", "tcpin:127.0.0.1:0", "--speedup", "5"))
    c = None
    try:
        ready = _ready(proc)
        c = connect_client(ready["vehicles"][0]["mavlink"])
        hb = hello(c, 3)
        assert hb.base_mode & R.MAV_MODE_FLAG_SAFETY_ARMED and hb.custom_mode == 4  # GUIDED
        m = wait_msg(c, "LOCAL_POSITION_NED")
        np.testing.assert_allclose([m.y, m.x, -m.z], expect, atol=1e-4)  # NED -> ENU
        # the mission fence is reported as parameters
        c.mav.param_request_read_send(3, 1, b"FENCE_ALT_MAX", -1)
        pv = wait_msg(c, "PARAM_VALUE", lambda m: m.param_id == "FENCE_ALT_MAX")
        assert pv.param_value == pytest.approx(mission.constraints.z_max_m)
    finally:
        if c is not None:
            c.close()
        proc.stop()


def test_lockstep_process_advances_only_on_zenoh_ticks():
    from comms import keys
    from comms.messages import Tick, encode
    from comms.session import SessionSettings, open_session

    zport = free_port()
    proc = Proc(fimnav("vehicle", "--lockstep", "--mission-id", "lk1", "--zenoh-listen", f"tcp/127.0.0.1:{zport}",
                       "--mavlink", "udpin:127.0.0.1:0", "--airborne", "--start", "0,0,5", "--profile", "ideal"))
    c = None
    session = None
    try:
        ready = _ready(proc)
        assert ready["tick_key"] == "fimnav/lk1/clock/tick"
        c = connect_client(ready["vehicles"][0]["mavlink"])
        hello(c, 1)
        c.mav.command_long_send(1, 1, R.MAV_CMD_REQUEST_MESSAGE, 0, R.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 0, 0, 0, 0, 0, 0)
        assert wait_msg(c, "LOCAL_POSITION_NED").time_boot_ms == 0  # no tick yet: time stands still
        session = open_session(SessionSettings(listen=(), connect=(f"tcp/127.0.0.1:{zport}",)))
        pub = session.declare_publisher(keys.tick("lk1"))
        # velocity north 1 m/s, then ticks of 0.5 s
        c.mav.set_position_target_local_ned_send(0, 1, 1, R.MAV_FRAME_LOCAL_NED, 0b110111000111, 0, 0, 0, 1.0, 0, 0, 0, 0, 0, 0, 0)
        deadline = time.monotonic() + 10
        while True:
            pub.put(encode(Tick(1, 0.5), "lk1", 1))
            m = c.recv_match(type="LOCAL_POSITION_NED", blocking=True, timeout=0.1)
            if m is not None and m.time_boot_ms == 500:
                break
            assert time.monotonic() < deadline, "tick 1 not applied"
        assert m.x == pytest.approx(0.5, abs=1e-6)
        pub.put(encode(Tick(2, 1.0), "lk1", 2))
        m = wait_msg(c, "LOCAL_POSITION_NED", lambda m: m.time_boot_ms == 1000)
        assert m.x == pytest.approx(1.0, abs=1e-6)
    finally:
        if session is not None:
            session.close()
        if c is not None:
            c.close()
        proc.stop()


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["--mavlink", "serial:/dev/x"], "expected KIND:HOST:PORT"),
        (["--mavlink", "udpin:127.0.0.1:99999"], "outside 0..65535"),
        (["--start", "1,2"], "--start"),
        (["--sysid", "300"], "1..255"),
        (["--mission", "/nonexistent.yaml"], "nonexistent"),
        (["--mission", str(MISSION), "--sysid", "11"], "10 drones"),
        (["--lockstep"], "--mission-id"),
        (["--signing-key", "/nonexistent.key"], "signing key"),
        (["--fence-z", "10,2"], "z_min_m <= z_max_m"),
        (["--speedup", "0"], "--speedup"),
    ],
)
def test_bad_input_exits_2_without_traceback(args, fragment):
    if "--mavlink" not in args:  # never the default port: another program (e.g. SITL) may hold it
        args = [*args, "--mavlink", "tcpin:127.0.0.1:0"]
    proc = Proc(fimnav("vehicle", *args))
    try:
        rc = proc.wait(30)
        assert rc == 2, (proc.out, proc.err)
        assert "Traceback" not in proc.err
        assert fragment in proc.err
    finally:
        proc.stop()


def test_port_in_use_is_a_clear_error():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        proc = Proc(fimnav("vehicle", "--mavlink", f"udpin:127.0.0.1:{port}", "--duration", "1"))
        try:
            rc = proc.wait(30)
        finally:
            proc.stop()
    assert rc == 2 and "Traceback" not in proc.err and "in use" in proc.err


def test_sigterm_stops_cleanly_and_flushes_the_tlogs(tmp_path):
    import os
    import signal

    pattern = str(tmp_path / "v{sysid}.tlog")
    proc = Proc(fimnav("vehicle", "--count", "2", "--mavlink", "udpin:127.0.0.1:0", "--tlog", pattern))
    clients = []
    try:
        ready = _ready(proc)
        for v in ready["vehicles"]:
            c = connect_client(v["mavlink"])
            clients.append(c)
            hello(c, v["sysid"])
        os.killpg(proc.p.pid, signal.SIGTERM)
        assert proc.wait(20) == 143  # 128 + SIGTERM, after the vehicles stopped (missions.runtime.signals)
        assert "Traceback" not in proc.err and "fimnav vehicle: stopped by SIGTERM" in proc.err
    finally:
        for c in clients:
            c.close()
        proc.stop()
    for sysid in (1, 2):
        data = (tmp_path / f"v{sysid}.tlog").read_bytes()
        # uint64 BE time stamp then a MAVLink 2 frame: the first frame is ours or the client's
        assert len(data) > 20 and data[8] == 0xFD

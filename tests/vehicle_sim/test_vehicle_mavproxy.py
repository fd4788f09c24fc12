"""A standard ground station accepts the simulated vehicle: MAVProxy (from PyPI), headless,
driven through its stdin, connects, shows the vehicle, switches to GUIDED, arms, takes off and
flies to a point; an independent pymavlink observer checks where the vehicle ends up."""

from __future__ import annotations

import shutil
import tempfile

import pytest
from pyproj import Geod

from vehicle_sim.config import Origin

from tests.support.proc import MAVPROXY, Proc, fimnav
from tests.vehicle_sim.clients import connect_client, hello, wait_msg

pytestmark = pytest.mark.integration


@pytest.mark.slow  # the MAVProxy interoperability flight (7 s); test_vehicle_vs_ardupilot checks the ground-station view in the default run
def test_mavproxy_connects_arms_and_flies_guided():
    vehicle = Proc(fimnav("vehicle", "--mavlink", "tcpin:127.0.0.1:0", "--speedup", "5"))
    gcs = None
    observer = None
    workdir = tempfile.mkdtemp(prefix="mavproxy-")
    try:
        line = vehicle.expect(r"\{\"event\": \"ready\".*\}\n", timeout_s=30).group(0)
        address = line.split('"mavlink": "')[1].split('"')[0]
        port = address.rsplit(":", 1)[1]
        gcs = Proc([MAVPROXY, f"--master=tcp:127.0.0.1:{port}", "--no-state", "--default-modules=mode,arm,cmdlong,param,misc"],
                   stdin=True, cwd=workdir)
        gcs.expect_next(r"Detected vehicle 1:1|STABILIZE>", timeout_s=60)
        gcs.send("mode GUIDED")
        gcs.expect_next(r"DO_SET_MODE: ACCEPTED")
        gcs.expect_next(r"GUIDED>")
        gcs.send("arm throttle")
        gcs.expect_next(r"COMPONENT_ARM_DISARM: ACCEPTED")
        gcs.expect_next(r"ARMED")
        gcs.send("takeoff 5")
        gcs.expect_next(r"NAV_TAKEOFF: ACCEPTED")
        # independent observer on a second TCP connection; ArduPilot's take-off ends silently
        observer = connect_client(address, source_system=250)
        hello(observer, 1)
        wait_msg(observer, "GLOBAL_POSITION_INT", lambda m: abs(m.relative_alt - 5000) < 150, timeout=30)
        o = Origin()
        lon, lat, _ = Geod(ellps="WGS84").fwd(o.lon_deg, o.lat_deg, 45.0, 25.0)  # 25 m north-east
        gcs.send(f"guided {lat:.7f} {lon:.7f} 8")
        gcs.expect_next(r"(DO_REPOSITION: ACCEPTED|Got MISSION_ACK: TYPE_MISSION: ACCEPTED)")
        gp = wait_msg(
            observer,
            "GLOBAL_POSITION_INT",
            lambda m: Geod(ellps="WGS84").inv(lon, lat, m.lon * 1e-7, m.lat * 1e-7)[2] < 0.3 and abs(m.relative_alt - 8000) < 100,
            timeout=40,
        )
        assert gp.get_srcSystem() == 1
        gcs.send("status HEARTBEAT")
        gcs.expect_next(r"HEARTBEAT \{type : 2, autopilot : 3")
    finally:
        if observer is not None:
            observer.close()
        if gcs is not None:
            gcs.stop()
        vehicle.stop()
        shutil.rmtree(workdir, ignore_errors=True)

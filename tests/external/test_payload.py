"""``fimnav payload``: the simulated RSS payload of a drone flown on an external autopilot,
following the autopilot's position over a second MAVLink connection (real processes on
127.0.0.1: a ``fimnav vehicle`` stands in for the autopilot; against ArduPilot SITL:
tests/sitl/test_sitl_flight.py). And ``fimnav launch --realtime`` refusing a drone with a
connection but nowhere for its simulated payload to follow it."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.external.helpers import start_vehicle, write_mission
from tests.support.proc import ENV, Proc, fimnav
from tests.support.zenoh import open_hub

pytestmark = pytest.mark.integration

SPEEDUP = 5.0


@pytest.mark.slow  # 8 s of real processes; the payload's measurement model is checked in tests/vehicle_sim (test_vehicle_payload.py)
def test_payload_follows_the_autopilot_and_measures_as_the_vehicles_payload(tmp_path: Path, procs: list[Proc]) -> None:
    from comms import keys
    from comms.messages import decode
    from missions.cli.payload import build_payload
    from missions.format.loader import load_mission

    steps = 12
    mission = write_mission(tmp_path / "m.yaml", "payload", [[0.0, 0.0, 6.0]], steps, "land",
                            drones={"count": 1, "roles": ["joint"], "start": {"positions_m": [[0.0, 0.0, 6.0]]}})
    vehicle, port = start_vehicle(procs, mission, tmp_path / "v.tlog", "--speedup", f"{SPEEDUP:g}")
    session, ep = open_hub()
    got: list[Any] = []
    lock = threading.Lock()

    def on_measurement(sample: Any) -> None:
        _, msg = decode(bytes(sample.payload.to_bytes()), "payload", 1)
        with lock:
            got.append(msg)

    sub = session.declare_subscriber(keys.measurement("payload", 1), on_measurement)
    try:
        # The payload's own link to the autopilot (the vehicle answers every UDP peer).
        payload = Proc(fimnav("payload", "--mission", str(mission), "--uav", "1", "--mavlink", f"udpout:127.0.0.1:{port}",
                              "--speedup", f"{SPEEDUP:g}", "--zenoh-connect", ep))
        procs.append(payload)
        payload.expect(r"\{\"event\": \"ready\".*\"key\": \"fimnav/payload/measurement/1\"", 30.0)
        plan = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--mavlink", f"udpout:127.0.0.1:{port}",
                           "--speedup", f"{SPEEDUP:g}", "--zenoh-connect", ep, "--log", str(tmp_path / "p.jsonl")))
        procs.append(plan)
        assert plan.wait(60.0) == 0, plan.tail()
        payload.stop()
        assert "following system 1 (autopilot ardupilot)" in payload.err and "Traceback" not in payload.err, payload.tail()
    finally:
        sub.undeclare()
        session.close()
    # The planner had a fresh measurement at every step (joint: range and bearing).
    rows = [json.loads(line) for line in (tmp_path / "p.jsonl").read_text().splitlines()]
    assert len(rows) >= steps - 1
    assert all(r["measurement"]["range_m"] is not None and r["measurement"]["azimuth_rad"] is not None for r in rows), rows[:3]
    assert "without a payload measurement" not in plan.err
    # Every published record is the vehicle payload's measurement at the autopilot's position:
    # the same noise draws (measurement n uses step n's), taken where the autopilot said it was.
    with lock:
        records = sorted(got, key=lambda o: o.step)
    assert len(records) >= steps
    reference = build_payload(load_mission(mission), 1)
    for obs in records:
        m = reference.measure(obs.position_m, obs.step, obs.step * 1.0)
        assert math.isclose(obs.range_m, m.range_m, rel_tol=1e-12) and math.isclose(obs.azimuth_rad, m.azimuth_rad, rel_tol=1e-12), (obs, m)
    # The positions are the autopilot's: the drone climbed from the ground to its start.
    assert min(o.position_m[2] for o in records) < 1.0 and max(o.position_m[2] for o in records) > 5.0


def test_launch_refuses_an_external_drone_whose_payload_has_no_connection(tmp_path: Path) -> None:
    mission = tmp_path / "m.yaml"
    mission.write_text(yaml.safe_dump({
        "id": "nopayload", "dt_s": 1.0, "steps": 3,
        "drones": {"count": 2, "roles": "ranging", "start": {"positions_m": [[0.0, 0.0, 5.0], [10.0, 0.0, 5.0]]}},
        "source": {"position_m": [60.0, 90.0, 2.0]},
        "vehicles": {"overrides": [{}, {"connection": "tcp:127.0.0.1:5770"}]},
    }))
    r = subprocess.run([sys.executable, "-m", "missions", "launch", str(mission), "--realtime", "--out", str(tmp_path / "out")],
                       capture_output=True, text=True, env=ENV, timeout=60)
    assert r.returncode == 2, r.stderr
    assert "vehicles.overrides[1].payload_connection" in r.stderr and "payload: external" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr

"""End-to-end: ``fimnav launch --realtime`` (issue 6), real processes, real Zenoh and real
MAVLink sockets on 127.0.0.1.

- A mixed fleet: drones 1 and 2 are simulated by the launcher; drone 3 is an "external"
  autopilot the launcher does not start (here a PX4-flavoured ``fimnav vehicle`` with MAVLink 2
  signing on, started by the test, which publishes its payload on its own Zenoh endpoint that
  the mission lists), reached through ``vehicles.overrides[2].connection``. The planners step on
  the wall clock (sped up) from one shared start, and the run's results are those of a lockstep
  run: summary, step logs, zero violations, the end of mission confirmed.
"""

from __future__ import annotations

import json
import socket
from pathlib import Path

import pytest
import yaml

from tests.support.launch import Launch
from tests.support.net import free_port
from tests.support.proc import Proc, fimnav

pytestmark = pytest.mark.integration

SPEEDUP = 5.0


@pytest.mark.slow  # 24 s of real time; with real ArduPilot SITL: tests/sitl/test_sitl_flight.py (-m sitl)
def test_mixed_fleet_in_real_time(tmp_path: Path, launches: list[Launch]) -> None:
    key = tmp_path / "drone3.key"
    key.write_bytes(bytes(range(32)))
    key.chmod(0o600)
    mav_port, zenoh_port = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_STREAM)
    steps = 14
    mission = tmp_path / "mixed.yaml"
    mission.write_text(yaml.safe_dump({
        "id": "mixed", "dt_s": 1.0, "steps": steps, "seed": 3,
        "drones": {"count": 3, "roles": ["ranging", "bearing", "joint"],
                   "start": {"positions_m": [[10.0, 20.0, 8.0], [30.0, 20.0, 8.0], [50.0, 20.0, 8.0]]}},
        "source": {"position_m": [60.0, 90.0, 2.0]},
        "end_action": "land",
        "vehicles": {"overrides": [{}, {}, {"connection": f"udpout:127.0.0.1:{mav_port}", "flavour": "px4", "signing_key_file": str(key),
                                                  "payload": "external"}]},
        "zenoh": {"connect": [f"tcp/127.0.0.1:{zenoh_port}"]},
    }))
    external = Proc(fimnav("vehicle", "--mission", str(mission), "--sysid", "3", "--mavlink", f"udpin:127.0.0.1:{mav_port}",
                           "--speedup", str(SPEEDUP), "--zenoh-listen", f"tcp/127.0.0.1:{zenoh_port}", "--tlog", str(tmp_path / "external.tlog")))
    try:
        ready = external.ready(60.0)
        assert ready.get("payload") == "realtime"
        out = tmp_path / "run"
        run = Launch(mission, out, "--realtime", "--speedup", str(SPEEDUP), "--start-delay", "15")
        launches.append(run)
        code, stdout, stderr = run.wait(240.0)
        assert code == 0, stderr[-3000:]
        assert "results:" in stdout and "Traceback" not in stderr
    finally:
        external.stop()

    # The launcher started vehicles 1 and 2 only; drone 3 flew the external autopilot, whose
    # link its planner logged (signed frames both ways), and started no payload for it (the
    # mission says a real one publishes: here the external vehicle's).
    assert (out / "tlogs" / "vehicle_1.tlog").exists() and (out / "tlogs" / "vehicle_2.tlog").exists()
    assert sorted(p.name for p in (out / "logs").glob("vehicle*.log")) in (["vehicle_1.log", "vehicle_2.log"], ["vehicles_1-2.log"])
    assert not list((out / "logs").glob("payload*.log"))
    from tests.external.helpers import read_tlog  # noqa: PLC0415

    t3 = read_tlog(out / "tlogs" / "vehicle_3.tlog")
    assert t3.commands.get(400, 0) >= 1 and sum(t3.setpoints.values()) > 20, t3.commands
    assert any(armed for _, armed in t3.modes) and t3.landed_state == 1, t3.modes
    ends = {}
    for i in (1, 2, 3):
        last = (out / "logs" / f"planner_{i}.log").read_text().strip().splitlines()[-1]
        ends[i] = json.loads(last)
        assert ends[i]["end"]["confirmed"] and ends[i]["end"]["action"] == "land", ends[i]
        # A step may be skipped when the shared machine stalls a planner; most are flown.
        flown = [json.loads(line)["step"] for line in (out / "logs" / f"planner_{i}.jsonl").read_text().splitlines()]
        assert len(flown) >= steps - 4 and flown[-1] >= steps - 2, (i, flown)
    assert ends[3]["flavour"] == "px4" and ends[1]["flavour"] == "ardupilot"
    assert all(e["frame"] == "global" for e in ends.values())

    summary = json.loads((out / "summary.json").read_text())["runs"][0]
    assert summary["clock"] == f"realtime x{SPEEDUP:g}" and summary["failures"] == []
    assert summary["violations"] == {k: 0 for k in summary["violations"]}
    # Every planner heard the external drone's records (its payload reached its planner
    # through the mission's Zenoh endpoint, its records reached the swarm).
    for i in (1, 2):
        saw = [json.loads(line)["saved_steps"][2] for line in (out / "logs" / f"planner_{i}.jsonl").read_text().splitlines()]
        assert max(saw) >= steps - 4, (i, saw)
    measured = [json.loads(line)["measurement"] for line in (out / "logs" / "planner_3.jsonl").read_text().splitlines()]
    assert sum(m["range_m"] is not None for m in measured) >= steps - 6

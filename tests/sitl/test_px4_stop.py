"""Ctrl-C of a real-time launch leaves a real PX4 SITL (v1.15, the headless SIH quadrotor, x5)
in AUTO.LOITER, the mission's on_stop hold (docs/in-the-field.md, "When fimnav stops").

``fimnav launch --realtime`` flies drone 1 on PX4 (its simulated payload on PX4's GCS link);
SIGINT to the launch's process group after eight steps: exit 130, the planner's log says PX4
confirmed AUTO.LOITER, and a ground station listening on PX4's offboard link afterwards (the
planner's port) sees it in AUTO.LOITER, armed, at the same height, for 10 s of wall time (50 s
of PX4's time). PX4's AUTO.LOITER holds without sticks.

Needs FIMNAV_SITL_PX4 and FIMNAV_SITL_PX4_ETC (tests/sitl/px4.py); skipped with a one-line
reason otherwise.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest
import yaml
from pymavlink import mavutil

from tests.sitl.px4 import px4_config, start_px4
from tests.sitl.test_px4_flight import home_below
from tests.sitl.test_sitl_flight import START, write_mission
from tests.sitl.test_sitl_takeover import heartbeats
from tests.support.launch import Launch
from tests.support.proc import fimnav, with_default_interrupt
from tests.support.wait import wait_for

_CFG, _REASON = px4_config()

pytestmark = [pytest.mark.sitl, pytest.mark.integration, pytest.mark.skipif(_CFG is None, reason=_REASON)]

SPEED = 5.0
PX4_AUTO_LOITER = (4 << 16) | (3 << 24)


def test_ctrl_c_of_a_realtime_launch_leaves_px4_in_auto_loiter(tmp_path: Path, launches: list[Launch]) -> None:
    mission = write_mission(tmp_path / "m.yaml", steps=200)
    with start_px4(_CFG, tmp_path / "px4", home=home_below(mission, START), speed=SPEED, sysid=1) as px4:  # type: ignore[arg-type]
        spec = yaml.safe_load(mission.read_text())
        spec["vehicles"] = {"overrides": [{"connection": px4.offboard, "payload_connection": px4.gcs}]}
        mission.write_text(yaml.safe_dump(spec))
        out = tmp_path / "run"
        run = Launch.command(with_default_interrupt(fimnav("launch", str(mission), "--out", str(out), "--realtime", "--speedup",
                                                           f"{SPEED:g}", "--start-delay", "60")), out, tmp_path)
        launches.append(run)
        steps_log = out / "logs" / "planner_1.jsonl"
        wait_for(lambda: steps_log.exists() and len(steps_log.read_text().splitlines()) >= 8, 240.0, "eight steps")
        os.killpg(run.proc.pid, signal.SIGINT)
        code, _, stderr = run.wait(60.0)
        assert code == 130, stderr[-3000:]
        text = (out / "logs" / "planner_1.log").read_text()
        line = next(x for x in text.splitlines() if "stopping (SIGTERM)" in x)
        assert "the vehicle is in AUTO.LOITER (on_stop hold), confirmed" in line, line
        assert "airborne in OFFBOARD" in text
        # PX4's GCS link keeps answering the first address it heard (the payload's, gone); its
        # offboard/API link sends to a fixed port, the planner's, free again.
        gcs = mavutil.mavlink_connection(px4.offboard, source_system=255, source_component=190)
        try:
            assert gcs.wait_heartbeat(timeout=20) is not None
            pos0 = gcs.recv_match(type="GLOBAL_POSITION_INT", blocking=True, timeout=10)
            held = heartbeats(gcs, 10.0)
            pos1 = gcs.recv_match(type="GLOBAL_POSITION_INT", blocking=True, timeout=10)
        finally:
            gcs.close()
    assert held and set(held) == {(PX4_AUTO_LOITER, True)}, held
    # Still in the air where it stopped (the mission's start height, 8 m), not descending (mm).
    assert pos0 is not None and pos1 is not None and pos0.relative_alt > 5000 and abs(pos1.relative_alt - pos0.relative_alt) < 1000, (pos0, pos1)
    print(f"\nPX4 SIH Ctrl-C: {line.split('stopping ')[1]}; then AUTO.LOITER, armed, for {len(held)} heartbeats over 10 s; "
          f"height above home {pos0.relative_alt / 1000:.1f} -> {pos1.relative_alt / 1000:.1f} m")

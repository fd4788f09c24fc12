"""Link loss against real PX4 SITL (SIH), x5: PX4 is frozen (SIGSTOP) for 3 wall seconds
mid-mission and resumed (SIGCONT), as a radio link that goes silent both ways. SIH is PX4's
own lockstep clock, so PX4 sees no time pass and no failsafe; the planner sees its heartbeat
stop, reports the loss after its 2 s threshold, publishes its records as stale, and when the
heartbeat returns resumes the mission in OFFBOARD and lands it.

Needs FIMNAV_SITL_PX4 and FIMNAV_SITL_PX4_ETC (tests/sitl/px4.py).
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pytest

from tests.external.helpers import SwarmPeer
from tests.sitl.px4 import px4_config, start_px4
from tests.sitl.test_px4_flight import home_below
from tests.sitl.test_sitl_flight import START, write_mission
from tests.support.proc import Proc, fimnav
from tests.support.wait import wait_for

_CFG, _REASON = px4_config()

pytestmark = [pytest.mark.sitl, pytest.mark.integration, pytest.mark.skipif(_CFG is None, reason=_REASON)]

SPEEDUP = 5.0


def test_px4_silent_for_3_s_is_reported_records_go_stale_and_the_planner_resumes(tmp_path: Path, procs: list[Proc]) -> None:
    assert _CFG is not None
    steps = 40
    mission = write_mission(tmp_path / "m.yaml", steps=steps)
    log = tmp_path / "p.jsonl"
    peer = SwarmPeer("sitl_one", 1, {1: 75.0})
    try:
        with start_px4(_CFG, tmp_path / "px4", home=home_below(mission, START), speed=SPEEDUP) as px4:
            plan = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--sysid", str(px4.sysid), "--mavlink", px4.offboard,
                               "--speedup", f"{SPEEDUP:g}", "--log", str(log), "--preflight-timeout", "180", "--zenoh-connect", peer.endpoint))
            procs.append(plan)
            wait_for(lambda: log.exists() and len(log.read_text().splitlines()) >= 8, 150.0, "eight planned steps")
            os.killpg(px4.proc.pid, signal.SIGSTOP)
            t_cut = time.monotonic()
            try:
                plan.expect(r"vehicle link lost", 10.0, stream="err")
                noticed_s = time.monotonic() - t_cut
                seen = len(peer.snapshot())
                wait_for(lambda: sum(1 for r in peer.snapshot()[seen:] if r.sender == 1 and r.stale) >= 3, 10.0, "stale records")
                wait_for(lambda: time.monotonic() - t_cut >= 3.0, 5.0, "3 s of silence")
            finally:
                os.killpg(px4.proc.pid, signal.SIGCONT)
            plan.expect(r"resumed in OFFBOARD", 30.0, stream="err")
            assert plan.wait(120.0) == 0, plan.tail()
    finally:
        peer.close()
    summary = json.loads(plan.out.strip().splitlines()[-1])
    assert len(summary["link_losses"]) == 1 and summary["stale_steps"] >= 3, summary
    assert summary["end"]["confirmed"] and summary["end"]["action"] == "land", summary["end"]
    assert "Traceback" not in plan.err
    print(f"\nPX4 link loss x{SPEEDUP:g}: silence noticed after {noticed_s:.2f} s wall; link down {summary['link_losses'][0]['down_s']} s; "
          f"{summary['stale_steps']} stale steps; resumed in OFFBOARD and landed")

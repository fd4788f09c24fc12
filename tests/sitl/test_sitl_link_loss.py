"""Link loss against real ArduPilot SITL (copter), with the planner's documented behaviour
(docs/external-autopilots.md, "Link loss and the vehicle's own failsafe"):

* the link cut (a TCP relay between the planner and SITL's SERIAL0 drops everything, both
  ways, for 3 wall seconds = 15 s of SITL time at x5) mid-mission: the planner reports the
  loss within 3 s (wall), publishes its last record flagged stale meanwhile, SITL holds in
  GUIDED (its position target; the velocity part stops after GUID_TIMEOUT), and when the
  heartbeats return the planner resumes in GUIDED and finishes the mission (land confirmed);
* SITL killed mid-flight and restarted on the same port: the planner reconnects, finds the
  rebooted autopilot disarmed on the ground and stops with that message (exit 1), without
  taking off again.

Needs FIMNAV_SITL_ARDUCOPTER and FIMNAV_SITL_ARDUCOPTER_DEFAULTS; skipped otherwise.
"""

from __future__ import annotations

import json
import select
import socket
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tests.sitl.sitl import SitlInstance, wait_for_bind
from tests.sitl.test_sitl_flight import _CFG, _REASON, START, home_below, write_mission
from tests.support.net import free_port
from tests.support.proc import Proc, fimnav
from tests.support.wait import wait_for

pytestmark = [pytest.mark.sitl, pytest.mark.integration, pytest.mark.skipif(_CFG is None, reason=_REASON)]

SPEEDUP = 5.0


def last_step(log: Path) -> int | None:
    """The last step in the planner's step log (JSON lines); None before the first."""
    try:
        steps = [json.loads(line)["step"] for line in log.read_text().splitlines() if line.strip()]
    except (OSError, ValueError, KeyError):
        steps = []  # not written yet, or a line being written
    return max(steps, default=None)


def wait_for_step(log: Path, step: int, timeout_s: float) -> None:
    """Wait until the planner's step log holds ``step``; fail after ``timeout_s``."""
    wait_for(lambda: (s := last_step(log)) is not None and s >= step, timeout_s, f"the planner to log step {step}",
             detail=lambda: f"last: {last_step(log)}", interval_s=0.05)


def start_sitl_on(workdir: Path, port: int, home: str, wipe: bool = True) -> SitlInstance:
    """SITL (x5) with SERIAL0 on ``port`` (as tests/sitl/sitl.py starts it); waits until it listens."""
    assert _CFG is not None
    workdir.mkdir(parents=True, exist_ok=True)
    argv = [str(_CFG.binary), "--model", "+", "--speedup", f"{SPEEDUP:g}", "--defaults", str(_CFG.defaults), "--home", home,
            "--sysid", "1", *(["-w"] if wipe else []), "--serial0", f"tcp:{port}:wait", "--serial1", "none:", "--serial2", "none:",
            "--rc-in-port", str(free_port(socket.SOCK_DGRAM, host="0.0.0.0"))]
    log_path = workdir / f"sitl-console-{time.monotonic_ns()}.log"
    with open(log_path, "wb") as out:
        proc = subprocess.Popen(argv, cwd=workdir, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    inst = SitlInstance(proc, f"tcp:127.0.0.1:{port}", port, SPEEDUP, workdir, log_path, argv)
    try:
        wait_for_bind(inst, 20.0)
    except BaseException:
        inst.stop()
        raise
    return inst


class TcpRelay:
    """Forward one TCP client to SITL's SERIAL0; while :attr:`cut` is set, everything read
    either way is dropped (a radio link gone silent; the connections stay up)."""

    def __init__(self, target_port: int) -> None:
        self.listen = socket.create_server(("127.0.0.1", 0))
        self.port = self.listen.getsockname()[1]
        self.target_port = target_port
        self.cut = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        self.listen.settimeout(0.2)
        while not self._stop.is_set():
            try:
                client, _ = self.listen.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with client, socket.create_connection(("127.0.0.1", self.target_port)) as upstream:
                pair = {client: upstream, upstream: client}
                while not self._stop.is_set():
                    ready, _, _ = select.select(list(pair), [], [], 0.1)
                    done = False
                    for s in ready:
                        try:
                            data = s.recv(65536)
                            if data and not self.cut.is_set():
                                pair[s].sendall(data)
                        except OSError:  # a side reset the connection (SITL or the planner ended)
                            data = b""
                        if not data:
                            done = True
                            break
                    if done:
                        break

    def close(self) -> None:
        self._stop.set()
        self._thread.join(3.0)
        self.listen.close()


def test_cut_link_is_reported_records_go_stale_and_the_planner_resumes(tmp_path: Path, procs: list[Proc]) -> None:
    steps = 60
    mission = write_mission(tmp_path / "m.yaml", steps)
    sitl = start_sitl_on(tmp_path / "sitl", free_port(host="0.0.0.0"), home_below(mission, START))
    relay = TcpRelay(sitl.port)
    try:
        plan = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--mavlink", f"tcp:127.0.0.1:{relay.port}",
                           "--speedup", f"{SPEEDUP:g}", "--log", str(tmp_path / "p.jsonl"), "--preflight-timeout", "180"))
        procs.append(plan)
        plan.expect(r"ready at the start position; step 0", 90.0, stream="err")
        wait_for_step(tmp_path / "p.jsonl", 10, 30.0)
        relay.cut.set()
        cut_at = time.monotonic()
        plan.expect(r"vehicle link lost", 5.0, stream="err")
        noticed_s = time.monotonic() - cut_at
        time.sleep(max(0.0, 3.0 - (time.monotonic() - cut_at)))  # the cut lasts 3 wall seconds: the scenario, not a wait
        relay.cut.clear()
        plan.expect(r"vehicle link back after", 10.0, stream="err")
        plan.expect(r"resumed in GUIDED", 10.0, stream="err")
        assert plan.wait(60.0) == 0, plan.tail()
    finally:
        relay.close()
        sitl.stop()
    summary = json.loads(plan.out.strip().splitlines()[-1])
    assert len(summary["link_losses"]) == 1 and summary["stale_steps"] >= 8, summary
    assert summary["end"]["confirmed"] and summary["end"]["landed_state"] == "ON_GROUND", summary
    assert summary["mode_changes"] == [], summary  # SITL stayed in GUIDED through the loss
    assert noticed_s < 3.0, noticed_s
    rows = [json.loads(line) for line in (tmp_path / "p.jsonl").read_text().splitlines()]
    flown = [r["step"] for r in rows]
    gap = [k for k in range(flown[0], flown[-1]) if k not in flown]
    assert gap and flown[-1] >= steps - 2, flown
    before = next(r for r in reversed(rows) if r["step"] < gap[0])
    after = next(r for r in rows if r["step"] > gap[-1])
    # SITL held in GUIDED: from the last step before the cut to the first after it the drone
    # moved at most the last step plus GUID_TIMEOUT (3 s) of its 1 m/s velocity feed-forward.
    drift = float(np.linalg.norm(np.subtract(after["position_m"], before["position_m"])))
    print(f"\nlink cut: noticed after {noticed_s:.2f} s wall, {len(gap)} steps stale, drift across the cut {drift:.2f} m")
    assert drift < 1.0 + 3.0 + 0.5, drift


def test_sitl_killed_and_restarted_is_found_disarmed_and_not_taken_off_again(tmp_path: Path, procs: list[Proc]) -> None:
    mission = write_mission(tmp_path / "m.yaml", 100)
    port = free_port(host="0.0.0.0")
    home = home_below(mission, START)
    sitl = start_sitl_on(tmp_path / "sitl", port, home)
    try:
        plan = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--mavlink", sitl.address,
                           "--speedup", f"{SPEEDUP:g}", "--log", str(tmp_path / "p.jsonl"), "--preflight-timeout", "180"))
        procs.append(plan)
        plan.expect(r"ready at the start position; step 0", 90.0, stream="err")
        wait_for_step(tmp_path / "p.jsonl", 5, 30.0)  # mid-flight
        sitl.stop(grace_s=0.1)  # SIGTERM then SIGKILL: the autopilot is gone mid-flight
        plan.expect(r"vehicle link lost", 5.0, stream="err")
        sitl = start_sitl_on(tmp_path / "sitl", port, home, wipe=False)  # rebooted, on the ground
        assert plan.wait(60.0) == 1, plan.tail()
    finally:
        sitl.stop()
    err = plan.err
    assert "the vehicle is disarmed after the link loss" in err and "not taking off again" in err, err[-2000:]
    assert "Traceback" not in err

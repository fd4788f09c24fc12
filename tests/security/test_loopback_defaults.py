"""By default nothing listens beyond loopback: the mission's default Zenoh endpoints, every
paper mission, a default Zenoh session, ``fimnav vehicle`` with its default MAVLink binding,
and every process of a running ``fimnav launch`` — checked on the sockets the processes
actually hold (/proc), not only on the configuration."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from comms.mavlink_transport import MavlinkTransport, mavutil_module
from comms.session import SessionSettings, open_session
from missions.format.loader import load_mission
from missions.format.schema import ZenohSpec

from tests.security.sockets import Sock, sockets_of
from tests.support.proc import Proc, fimnav
from tests.support.wait import wait_for

ROOT = Path(__file__).resolve().parents[2]
PAPER = sorted((ROOT / "missions" / "paper").glob("*.yaml"))


def _host(endpoint: str) -> str:
    proto, _, rest = endpoint.partition("/")
    return rest.rsplit(":", 1)[0].strip("[]")


def test_default_zenoh_section_is_loopback_only() -> None:
    spec = ZenohSpec()
    assert spec.mode == "peer" and spec.connect == () and spec.multicast_scouting is False
    assert spec.listen and all(_host(e) == "127.0.0.1" for e in spec.listen)
    assert spec.tls is None and spec.auth is None
    assert SessionSettings() == SessionSettings.from_mission(spec)


@pytest.mark.parametrize("path", PAPER, ids=[p.stem for p in PAPER])
def test_paper_missions_listen_on_loopback_only(path: Path) -> None:
    z = load_mission(path).zenoh
    assert all(_host(e) == "127.0.0.1" for e in z.listen), z.listen
    assert z.connect == () and z.multicast_scouting is False


def test_a_default_session_holds_only_loopback_sockets() -> None:
    before = set(sockets_of(os.getpid()))
    s = open_session(SessionSettings())
    try:
        new = [x for x in sockets_of(os.getpid()) if x not in before and x.listening]
        assert new, "the session should listen somewhere (on loopback)"
        assert all(x.loopback for x in new), new
    finally:
        s.close()


def test_a_planner_udpout_link_to_a_local_vehicle_is_bound_to_loopback() -> None:
    """A ``udpout:127.0.0.1:PORT`` link (the planner's link to a vehicle on this machine) sends
    from 127.0.0.1: an unbound socket would be bound to 0.0.0.0 by its first datagram and take
    datagrams from any host."""
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    vehicle.bind(("127.0.0.1", 0))
    vehicle.settimeout(5.0)
    transport = MavlinkTransport(mavutil_module(), f"udpout:127.0.0.1:{vehicle.getsockname()[1]}", 250, 191, None, time.monotonic, 1.0, None)
    try:
        transport.mav.heartbeat_send(6, 8, 0, 0, 0)
        _, sender = vehicle.recvfrom(65535)
        assert sender[0] == "127.0.0.1", sender
        mine = [x for x in sockets_of(os.getpid()) if x.proto == "udp" and x.port == sender[1]]
        assert mine and all(x.loopback for x in mine), mine
    finally:
        transport.conn.close()
        vehicle.close()


@pytest.mark.integration
def test_fimnav_vehicle_default_mavlink_binding_is_loopback() -> None:
    """No ``--mavlink``: tcpin on 127.0.0.1 (port 5760 + 10·(sysid − 1), as SITL)."""
    proc = Proc(fimnav("vehicle", "--sysid", "201"), cwd=ROOT)
    try:
        ready = proc.ready()
        assert ready["vehicles"][0]["mavlink"] == "tcpin:127.0.0.1:7760"
        socks = [x for x in sockets_of(proc.p.pid) if x.listening]
        assert socks and all(x.loopback for x in socks), socks
    finally:
        proc.stop(signal.SIGINT, grace_s=20.0)


@pytest.mark.integration
@pytest.mark.slow
def test_every_process_of_a_launch_listens_on_loopback_only(tmp_path: Path) -> None:
    out = tmp_path / "run"
    run = subprocess.Popen([sys.executable, "-m", "missions", "launch", str(ROOT / "missions/paper/ranging_los.yaml"),
                            "--out", str(out), "--steps", "300", "--no-figures"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                           start_new_session=True, cwd=ROOT)
    try:
        log = out / "logs" / "planner_1.jsonl"
        def flying() -> bool:
            assert run.poll() is None, run.stderr.read().decode(errors="replace")[-2000:] if run.stderr else ""
            return log.exists() and log.read_text().count("\n") >= 2

        wait_for(flying, 180.0, "the mission to start flying")
        # Every snapshot kept, by pid: a forked planner shows its own command line (and opens its
        # sockets) a moment after the fork, and one snapshot of a loaded machine saw 4 of them.
        socks: dict[int, list[Sock]] = {}

        def listening() -> bool:
            pids = {run.pid} | {int(p.name) for p in Path("/proc").iterdir() if p.name.isdigit() and _mentions(p, str(out))}
            for pid in pids:
                found = [x for x in sockets_of(pid) if x.listening]
                if found:
                    socks[pid] = found
            return len(socks) >= 11  # the launcher, the vehicles' process, ten planners: 12

        wait_for(listening, 60.0, "eleven processes of the launch listening", interval_s=0.2)
        exposed = {pid: [x for x in ss if not x.loopback] for pid, ss in socks.items()}
        assert not any(exposed.values()), f"sockets reachable from other hosts: {exposed}"
    finally:
        try:
            os.killpg(run.pid, signal.SIGINT)
        except ProcessLookupError:
            pass
        try:
            run.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(run.pid, signal.SIGKILL)
            run.wait(10)
        for p in Path("/proc").iterdir():
            if p.name.isdigit() and _mentions(p, str(out)):
                try:
                    os.kill(int(p.name), signal.SIGKILL)
                except ProcessLookupError:
                    pass


def _mentions(proc_dir: Path, text: str) -> bool:
    try:
        return text in (proc_dir / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return False

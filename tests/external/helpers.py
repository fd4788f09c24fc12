"""Helpers of the real-time tests: missions, a simulated vehicle started as a real process
(:class:`tests.support.proc.Proc`), a UDP relay the test can cut, a Zenoh peer publishing
payload measurements, and .tlog reading."""

from __future__ import annotations

import os
import select
import socket
import subprocess
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from tests.support.proc import ENV, Proc, fimnav
from tests.support.zenoh import open_hub


def write_mission(path: Path, mission_id: str, starts: list[list[float]], steps: int, end_action: str, **extra: object) -> Path:
    """A one-file mission in ``path``: drones (ranging) at ``starts`` (m, ENU), a source
    far enough from them, dt 1 s."""
    mission = {
        "id": mission_id, "dt_s": 1.0, "steps": steps,
        "drones": {"count": len(starts), "roles": "ranging", "start": {"positions_m": starts}},
        "source": {"position_m": [60.0, 90.0, 2.0]},
        "end_action": end_action, **extra,
    }
    path.write_text(yaml.safe_dump(mission))
    return path


def start_vehicle(procs: list[Proc], mission: Path, tlog: Path, *extra: str, sysid: int = 1) -> tuple[Proc, int]:
    """A simulated vehicle of ``mission`` on a free UDP port (udpin); return it and its port."""
    v = Proc(fimnav("vehicle", "--mission", str(mission), "--sysid", str(sysid), "--mavlink", "udpin:127.0.0.1:0",
                    "--profile", "pointmass", "--tlog", str(tlog), *extra))
    procs.append(v)
    ready = v.ready(30.0)
    port = int(ready["vehicles"][0]["mavlink"].rsplit(":", 1)[1])
    return v, port


class UdpRelay:
    """Forward UDP between a planner (which sends to :attr:`port`) and a vehicle's port, in a
    thread; :attr:`cut` drops everything in both directions (a lost radio link);
    :meth:`restore` ends a cut dropping what was sent before it too."""

    def __init__(self, vehicle_port: int) -> None:
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind(("127.0.0.1", 0))
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back.bind(("127.0.0.1", 0))
        self.port = self.front.getsockname()[1]
        self.vehicle = ("127.0.0.1", vehicle_port)
        self.client: tuple[str, int] | None = None
        self.cut = threading.Event()
        self._restore = threading.Event()
        self._restored = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def restore(self, timeout_s: float = 5.0) -> None:
        """End the cut. What either side sent before this call and the relay has not read yet
        (a loaded machine may leave the relay's thread behind) is dropped, not forwarded late:
        a vehicle's heartbeat from before a mode change never follows the change."""
        self._restored.clear()
        self._restore.set()
        assert self._restored.wait(timeout_s), "the relay did not restore the link"

    def _drain(self) -> None:
        for s in (self.front, self.back):
            while select.select([s], [], [], 0.0)[0]:
                try:
                    s.recvfrom(65536)
                except OSError:
                    break

    def _run(self) -> None:
        while not self._stop.is_set():
            if self._restore.is_set():
                self._drain()
                self.cut.clear()
                self._restore.clear()
                self._restored.set()
            ready, _, _ = select.select([self.front, self.back], [], [], 0.1)
            for s in ready:
                try:
                    data, addr = s.recvfrom(65536)
                except OSError:
                    continue
                if self.cut.is_set():
                    continue
                if s is self.front:
                    self.client = addr
                    self.back.sendto(data, self.vehicle)
                elif self.client is not None:
                    self.front.sendto(data, self.client)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.front.close()
        self.back.close()


@dataclass
class SwarmPeer:
    """The test's Zenoh peer: payload measurements for drones (a payload on its own
    schedule, stamped with UNIX time) and a log of the planners' records."""

    mission_id: str
    count: int
    ranges_m: dict[int, float]
    period_s: float = 0.05
    records: list[Any] = field(default_factory=list)
    #: The hub's Zenoh mode: ``router`` (as ``fimnav launch``'s) when ``fimnav handback`` is to
    #: reach a planner through it (a client's publisher matched through a peer was seen to stay
    #: unmatched at times).
    mode: str = "peer"

    def __post_init__(self) -> None:
        from comms import keys

        self.session, self.endpoint = open_hub(self.mode)
        self._pubs = {uav: self.session.declare_publisher(keys.measurement(self.mission_id, uav)) for uav in self.ranges_m}
        self._lock = threading.Lock()
        self._sub = self.session.declare_subscriber(keys.record(self.mission_id), self._on_record)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _on_record(self, sample: Any) -> None:
        from comms.messages import decode

        _, msg = decode(bytes(sample.payload.to_bytes()), self.mission_id, self.count)
        with self._lock:
            self.records.append(msg)

    def snapshot(self) -> list[Any]:
        with self._lock:
            return list(self.records)

    def _run(self) -> None:
        from comms.messages import MessageKind, Record, encode

        seq = 0
        while not self._stop.wait(self.period_s):
            for uav, rng in self.ranges_m.items():
                seq += 1
                obs = Record(uav, seq, time.time(), (0.0, 0.0, 0.0), True, False, True, rng, float("nan"), float("nan"))
                self._pubs[uav].put(encode(obs, self.mission_id, seq, MessageKind.MEASUREMENT))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.session.close()


def handback(mission: Path, uav: int, *args: str) -> subprocess.CompletedProcess[str]:
    """Run ``fimnav handback MISSION --uav UAV ARGS`` to its end (30 s at most)."""
    return subprocess.run(fimnav("handback", str(mission), "--uav", str(uav), *args), capture_output=True, text=True, env=ENV, timeout=30)


@dataclass
class TlogSummary:
    """What a vehicle's .tlog shows: its STATUSTEXTs, its (mode, armed) sequence, the
    planner's setpoint messages by (type, frame, mask) and the last landed state."""

    texts: list[str]
    modes: list[tuple[int, bool]]
    setpoints: dict[tuple[str, int, int], int]
    landed_state: int | None
    commands: dict[int, int]
    setpoint_times_s: list[float]  # wall time (tlog stamp) of every setpoint received


def read_tlog(path: Path) -> TlogSummary:
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    log = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    texts: list[str] = []
    modes: list[tuple[int, bool]] = []
    setpoints: dict[tuple[str, int, int], int] = {}
    landed = None
    commands: dict[int, int] = {}
    times: list[float] = []
    while True:
        m = log.recv_match()
        if m is None:
            break
        t = m.get_type()
        if t == "STATUSTEXT":
            texts.append(m.text)
        elif t == "HEARTBEAT" and m.get_srcComponent() == 1:
            state = (int(m.custom_mode), bool(m.base_mode & 128))
            if not modes or modes[-1] != state:
                modes.append(state)
        elif t.startswith("SET_POSITION_TARGET"):
            key = (t, int(m.coordinate_frame), int(m.type_mask))
            setpoints[key] = setpoints.get(key, 0) + 1
            times.append(float(m._timestamp))
        elif t == "EXTENDED_SYS_STATE":
            landed = int(m.landed_state)
        elif t == "COMMAND_LONG" and m.get_srcComponent() == 191:
            commands[int(m.command)] = commands.get(int(m.command), 0) + 1
    log.close()
    return TlogSummary(texts, modes, setpoints, landed, commands, times)

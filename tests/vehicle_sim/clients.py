"""pymavlink clients of simulated vehicles for the vehicle_sim tests: connect, wait for a message
with a deadline, drain, say hello; :class:`Rig` (vehicles hosted in a thread and their clients)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pymavlink import mavutil

from vehicle_sim.host import VehicleHost
from vehicle_sim.vehicle import SimVehicle

mavlink = mavutil.mavlink


def connect_client(address: str, source_system: int = 255) -> Any:
    """A pymavlink client for a vehicle listening at ``address`` (udpin:/tcpin:)."""
    kind, host, port = address.split(":")
    client_conn = {"udpin": f"udpout:{host}:{port}", "tcpin": f"tcp:{host}:{port}"}[kind]
    conn = mavutil.mavlink_connection(
        client_conn, source_system=source_system, source_component=190, dialect="ardupilotmega", autoreconnect=False
    )
    return conn


def wait_msg(conn: Any, mtype: str | list[str], cond: Callable[[Any], bool] = lambda m: True, timeout: float = 10.0) -> Any:
    """The first message of ``mtype`` satisfying ``cond`` within ``timeout`` wall seconds."""
    deadline = time.monotonic() + timeout
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            raise AssertionError(f"no {mtype} satisfying the condition within {timeout} s")
        m = conn.recv_match(type=mtype, blocking=True, timeout=min(left, 0.2))
        if m is not None and cond(m):
            return m


def drain(conn: Any) -> None:
    """Read and drop everything queued on the client's socket (at 20x speed-up a client that
    does not read for a while overflows its UDP receive buffer and the kernel drops frames,
    among them the ACK a test then waits for)."""
    while conn.recv_match(blocking=False) is not None:
        pass


@dataclass
class Rig:
    """Vehicles hosted in a background thread plus their clients."""

    host: VehicleHost
    vehicles: list[SimVehicle]
    clients: list[Any] = field(default_factory=list)

    @property
    def vehicle(self) -> SimVehicle:
        return self.vehicles[0]

    @property
    def client(self) -> Any:
        return self.clients[0]

    def command(self, cmd: int, *params: float, index: int = 0, timeout: float = 10.0, use_int: bool = False,
                frame: int = 0, target_system: int | None = None) -> int:
        """Send COMMAND_LONG (or COMMAND_INT) and return the COMMAND_ACK result."""
        c = self.clients[index]
        p = list(params) + [0.0] * (7 - len(params))
        ts = self.vehicles[index].sysid if target_system is None else target_system
        drain(c)
        if use_int:
            c.mav.command_int_send(ts, 1, frame, cmd, 0, 0, p[0], p[1], p[2], p[3], int(p[4]), int(p[5]), p[6])
        else:
            c.mav.command_long_send(ts, 1, cmd, 0, *p)
        ack = wait_msg(c, "COMMAND_ACK", lambda m: m.command == cmd, timeout)
        return int(ack.result)

    def set_mode(self, name: str, index: int = 0) -> int:
        v = self.vehicles[index]
        mode = v.info.mode_by_name(name)
        assert mode is not None, name
        if v.config.flavour == "px4":
            main = (mode.custom_mode >> 16) & 0xFF
            sub = (mode.custom_mode >> 24) & 0xFF
            return self.command(mavlink.MAV_CMD_DO_SET_MODE, 1, main, sub, index=index)
        return self.command(mavlink.MAV_CMD_DO_SET_MODE, 1, mode.custom_mode, index=index)

    def arm(self, index: int = 0) -> int:
        return self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, index=index)

    def takeoff(self, alt_m: float, index: int = 0) -> int:
        return self.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, alt_m, index=index)

    def local(self, cond: Callable[[Any], bool] = lambda m: True, index: int = 0, timeout: float = 10.0) -> Any:
        return wait_msg(self.clients[index], "LOCAL_POSITION_NED", cond, timeout)

    def fly_up(self, alt_m: float = 5.0, index: int = 0) -> None:
        """GUIDED, arm, take off to ``alt_m`` and wait until there."""
        assert self.set_mode("GUIDED", index) == mavlink.MAV_RESULT_ACCEPTED
        assert self.arm(index) == mavlink.MAV_RESULT_ACCEPTED
        assert self.takeoff(alt_m, index) == mavlink.MAV_RESULT_ACCEPTED
        self.local(lambda m: abs(m.z + alt_m) < 0.15, index=index, timeout=20.0)


def hello(conn: Any, sysid: int, timeout: float = 10.0) -> Any:
    """Announce the client with a GCS heartbeat (the vehicle learns our UDP address) and
    wait for the vehicle's heartbeat."""
    deadline = time.monotonic() + timeout
    while True:
        conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        m = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.3)
        if m is not None and m.get_srcSystem() == sysid:
            return m
        if time.monotonic() > deadline:
            raise AssertionError(f"no heartbeat from sysid {sysid} within {timeout} s")

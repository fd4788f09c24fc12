"""One ground-station port for a launched swarm (``fimnav launch --gcs ENDPOINT``).

Every simulated vehicle's MAVLink reaches one endpoint, as mavlink-router's or MAVProxy's
outputs do: the router talks to each vehicle's UDP port (the vehicle answers every peer; the
router announces itself with a 1 Hz HEARTBEAT of MAV_TYPE_GCS from system 255, component 240,
MAV_COMP_ID_UDP_BRIDGE) and forwards each datagram from the vehicles to the ground station
unchanged (signatures included). What the ground station sends is parsed and routed by its
target system: to that vehicle only, or to every vehicle when it names none (target 0, or a
message without a target such as a HEARTBEAT). System ids are the drone ids (1..N).

The endpoint is written as users write MAVLink endpoints (pymavlink's syntax): ``udpout:HOST:PORT``
(send to a ground station listening there, e.g. QGroundControl's 14550), ``udpin:HOST:PORT``
(listen; answer whoever sends), ``tcpin:HOST:PORT`` (listen for one TCP client), ``tcp:HOST:PORT``.
"""

from __future__ import annotations

import logging
import os
import select
import socket
import threading
import time
from collections.abc import Mapping
from typing import Any

from comms.errors import UsageError

log = logging.getLogger("fimnav.gcs")

#: The router's own MAVLink identity towards the vehicles.
ROUTER_SYSID, ROUTER_COMPID = 255, 240
HEARTBEAT_PERIOD_S = 1.0


def check_endpoint(endpoint: str) -> str:
    """``endpoint`` if it is a MAVLink endpoint the router can open, else :class:`UsageError`."""
    kind, _, rest = endpoint.partition(":")
    host, _, port = rest.rpartition(":")
    if kind not in ("udpout", "udpin", "tcpin", "tcp") or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise UsageError(f"--gcs: expected udpout:HOST:PORT, udpin:HOST:PORT, tcpin:HOST:PORT or tcp:HOST:PORT, found {endpoint!r}")
    return endpoint


class GcsRouter:
    """Forward the vehicles at ``vehicle_ports`` (system id → UDP port on 127.0.0.1) to the
    ground station at ``endpoint`` and route its frames back by target system, in a thread
    (:meth:`start`, :meth:`close`). Counts what it forwarded (``to_gcs``, ``to_vehicle``)."""

    def __init__(self, endpoint: str, vehicle_ports: Mapping[int, int]) -> None:
        os.environ.setdefault("MAVLINK20", "1")
        from pymavlink import mavutil

        self.mavutil = mavutil
        self.endpoint = check_endpoint(endpoint)
        self.gcs: Any = mavutil.mavlink_connection(endpoint, source_system=ROUTER_SYSID, source_component=ROUTER_COMPID, autoreconnect=True)
        self.vehicles: dict[int, socket.socket] = {}
        for sysid, port in vehicle_ports.items():
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.connect(("127.0.0.1", int(port)))
            s.setblocking(False)
            self.vehicles[int(sysid)] = s
        enc = mavutil.mavlink.MAVLink(None, srcSystem=ROUTER_SYSID, srcComponent=ROUTER_COMPID)
        self._heartbeat = enc.heartbeat_encode(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0).pack(enc)
        self.to_gcs = 0
        self.to_vehicle: dict[int, int] = dict.fromkeys(self.vehicles, 0)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="gcs-router", daemon=True)

    def start(self) -> None:
        """Start forwarding."""
        self._thread.start()
        log.info("ground station port %s: %d vehicles (system ids %s)", self.endpoint, len(self.vehicles), sorted(self.vehicles))

    def close(self) -> None:
        """Stop forwarding and close every socket (idempotent)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        for s in self.vehicles.values():
            s.close()
        self.gcs.close()

    def _gcs_fd(self) -> int | None:
        fd = getattr(self.gcs, "fd", None)
        return fd if isinstance(fd, int) and fd >= 0 else None

    def _run(self) -> None:
        next_hb = 0.0
        by_fd = {s.fileno(): sysid for sysid, s in self.vehicles.items()}
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_hb:
                for s in self.vehicles.values():
                    try:
                        s.send(self._heartbeat)
                    except OSError:
                        pass  # a vehicle gone: the launcher reports it
                next_hb = now + HEARTBEAT_PERIOD_S
            fds = list(by_fd) + ([g] if (g := self._gcs_fd()) is not None else [])
            try:
                ready, _, _ = select.select(fds, [], [], 0.05)
            except (OSError, ValueError):
                ready = []
            for fd in ready:
                if fd in by_fd:
                    self._from_vehicle(self.vehicles[by_fd[fd]])
            self._from_gcs()

    def _from_vehicle(self, s: socket.socket) -> None:
        while True:
            try:
                data = s.recv(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return  # ICMP port unreachable: the vehicle is not (yet) there
            try:
                self.gcs.write(data)
                self.to_gcs += 1
            except OSError:
                return  # no ground station connected yet (tcpin) or it went away

    def _from_gcs(self) -> None:
        for _ in range(200):
            try:
                msg = self.gcs.recv_msg()
            except OSError:
                return
            if msg is None:
                return
            if msg.get_type() == "BAD_DATA":
                continue
            target = int(getattr(msg, "target_system", 0) or 0)
            buf = msg.get_msgbuf()
            for sysid, s in self.vehicles.items():
                if target in (0, sysid):
                    try:
                        s.send(buf)
                        self.to_vehicle[sysid] += 1
                    except OSError:
                        pass

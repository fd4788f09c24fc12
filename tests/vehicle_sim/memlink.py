"""An in-memory transport (a fake at the socket seam) and a client-side encoder for unit tests."""

from __future__ import annotations

from typing import Any

from vehicle_sim.config import VehicleConfig
from vehicle_sim.link import MavlinkLink, Transport, mavlink_module
from vehicle_sim.vehicle import SimVehicle


class MemoryTransport(Transport):
    """Frames pushed with :meth:`inject` are read by the vehicle; what it writes is kept."""

    kind = "memory"

    def __init__(self) -> None:
        self.inbox: list[tuple[object, bytes]] = []
        self.outbox: list[bytes] = []

    def inject(self, data: bytes, peer: object = "gcs") -> None:
        self.inbox.append((peer, bytes(data)))

    def filenos(self) -> list[int]:
        return []

    def read(self) -> list[tuple[object, bytes]]:
        out, self.inbox = self.inbox, []
        return out

    def write(self, buf: bytes) -> None:
        self.outbox.append(bytes(buf))

    def close(self) -> None:
        pass

    @property
    def address(self) -> str:
        return "memory"

    def peers(self) -> int:
        return 1


class Sink:
    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, buf: bytes) -> None:
        self.frames.append(bytes(buf))


def gcs_encoder(sysid: int = 255, compid: int = 190) -> tuple[Any, Sink]:
    """A pymavlink encoder writing frames into a list (``sink.frames``)."""
    m = mavlink_module()
    sink = Sink()
    return m.MAVLink(sink, srcSystem=sysid, srcComponent=compid), sink


def memory_vehicle(config: VehicleConfig | None = None) -> tuple[SimVehicle, MemoryTransport]:
    """A vehicle behind a :class:`MemoryTransport`."""
    cfg = config or VehicleConfig()
    t = MemoryTransport()
    link = MavlinkLink(t, cfg.sysid, 1)
    return SimVehicle(cfg, link), t


def decode_all(frames: list[bytes]) -> list[Any]:
    """Decode frames written by a vehicle (client-side parser)."""
    m = mavlink_module()
    parser = m.MAVLink(None)
    parser.robust_parsing = True
    out = []
    for f in frames:
        out.extend(x for x in (parser.parse_buffer(f) or []) if x.get_type() != "BAD_DATA")
    return out

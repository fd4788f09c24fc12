"""Fixtures of the vehicle_sim tests: in-process vehicles on loopback sockets with real pymavlink
clients (:mod:`tests.vehicle_sim.clients`), everything closed on teardown."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest

from vehicle_sim.clock import TickQueue, RealTimeClock
from vehicle_sim.config import VehicleConfig
from vehicle_sim.host import VehicleHost, build_vehicle

from tests.vehicle_sim.clients import Rig, connect_client, hello


@pytest.fixture
def make_rig() -> Iterator[Callable[..., Rig]]:
    """Factory: ``make_rig(configs, kind="udpin", speedup=20.0, lockstep=False)``."""
    rigs: list[Rig] = []

    def _make(
        configs: list[VehicleConfig] | VehicleConfig | None = None,
        kind: str = "udpin",
        speedup: float = 20.0,
        lockstep: bool = False,
        connect: bool = True,
    ) -> Rig:
        if configs is None:
            configs = [VehicleConfig()]
        if isinstance(configs, VehicleConfig):
            configs = [configs]
        vehicles = [build_vehicle(c, f"{kind}:127.0.0.1:0") for c in configs]
        clock = TickQueue() if lockstep else RealTimeClock(speedup)
        host = VehicleHost(vehicles, clock)
        rig = Rig(host, vehicles)
        rigs.append(rig)
        host.start()
        if connect:
            for v in vehicles:
                c = connect_client(v.link.transport.address)
                rig.clients.append(c)
                hello(c, v.sysid)
        return rig

    yield _make
    for rig in rigs:
        rig.host.close()
        for c in rig.clients:
            c.close()

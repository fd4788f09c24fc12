"""A mission's simulated vehicles (``Mission.vehicle_config``) against what it is made of, and
against the vehicles ``fimnav vehicle --mission`` hosts."""

from __future__ import annotations

import argparse

import numpy as np

from missions.cli.vehicle import build_configs, register
from missions.format.loader import load_mission


def _vehicle_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    return parser.parse_args(["vehicle", *argv])


def test_vehicle_config_is_the_missions_vehicle() -> None:
    mission = load_mission("paper/heterogeneous")
    starts = mission.drones.start_positions_m()
    for drone in range(mission.drones.count):
        cfg = mission.vehicle_config(drone)
        assert cfg.sysid == drone + 1
        np.testing.assert_array_equal(cfg.start_enu_m, starts[drone])
        assert (cfg.origin.lat_deg, cfg.origin.lon_deg, cfg.origin.alt_m) == (mission.origin.lat_deg, mission.origin.lon_deg, mission.origin.alt_m)
        fence = cfg.geofence
        assert (fence.z_min_m, fence.z_max_m) == (mission.constraints.z_min_m, mission.constraints.z_max_m)
        assert (fence.x_min_m, fence.x_max_m, fence.y_min_m, fence.y_max_m) == (mission.fence.x_min_m, mission.fence.x_max_m, mission.fence.y_min_m, mission.fence.y_max_m)
        resolved = mission.vehicles.for_drone(drone)
        assert (cfg.flavour, cfg.profile, cfg.seed) == (resolved.flavour, resolved.profile, int(mission.seed))
    assert mission.vehicle_config(0, seed=7, flavour="px4").seed == 7


def test_fimnav_vehicle_hosts_the_missions_vehicles() -> None:
    mission = load_mission("paper/heterogeneous")
    n = mission.drones.count
    configs = build_configs(_vehicle_args(["--count", str(n)]), mission)
    assert [cfg for cfg, _ in configs] == [mission.vehicle_config(i) for i in range(n)]
    assert all(payload is not None for _, payload in configs)

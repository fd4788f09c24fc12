"""The command lines ``fimnav launch`` gives its children (``python -m missions ARGS``): a
process of simulated vehicles, a simulated payload following an external autopilot, a planner.
Paths are absolute: the children run in the results' ``logs`` directory."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from comms.session import SessionSettings


def vehicle_command(mission_file: Path, ids: Sequence[int], timing: Sequence[str], physics: Sequence[str], hub: str, tlog: Path) -> list[str]:
    """``fimnav vehicle`` hosting the consecutive drones ``ids``, each listening on a free UDP
    port of 127.0.0.1, a client of the launcher's Zenoh router at ``hub``."""
    return [
        "vehicle",
        "--mission",
        str(mission_file),
        "--sysid",
        str(ids[0]),
        "--count",
        str(len(ids)),
        *[a for _ in ids for a in ("--mavlink", "udpin:127.0.0.1:0")],
        *timing,
        *physics,
        "--zenoh-connect",
        hub,
        "--zenoh-mode",
        "client",
        "--tlog",
        str(tlog),
    ]


def payload_command(mission_file: Path, drone_id: int, speedup: float, zenoh: SessionSettings, connect_timeout_s: float) -> list[str]:
    """``fimnav payload`` for drone ``drone_id``: fimnav's simulated payload following an
    external autopilot over its second MAVLink connection."""
    return [
        "payload",
        "--mission",
        str(mission_file),
        "--uav",
        str(drone_id),
        "--speedup",
        f"{speedup:g}",
        *zenoh.to_cli(),
        "--connect-timeout",
        str(connect_timeout_s),
    ]


def planner_command(
    mission_file: Path, drone_id: int, link: Sequence[str], timing: Sequence[str], zenoh: SessionSettings, step_log: Path, step_timeout_s: float
) -> list[str]:
    """``fimnav plan`` for drone ``drone_id`` (``link``: its MAVLink arguments), its step log
    in ``step_log``."""
    return [
        "plan",
        "--mission",
        str(mission_file),
        "--uav",
        str(drone_id),
        *link,
        *timing,
        *zenoh.to_cli(),
        "--log",
        str(step_log),
        "--step-timeout",
        str(step_timeout_s),
    ]

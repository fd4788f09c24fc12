"""What the process commands (``fimnav plan``, ``fimnav vehicle``, ``fimnav payload``,
``fimnav router``) build alike from their arguments and the mission: the log set-up, the Zenoh
session settings and the simulated payload's world."""

from __future__ import annotations

import json
import logging
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING

from comms.errors import UsageError

if TYPE_CHECKING:  # pragma: no cover - types only
    from comms.session import SessionSettings
    from missions.format.schema import Mission
    from vehicle_sim.payload import PayloadWorld


def setup_logging(level: str, name: str) -> None:
    """Log to stderr at ``level``, each line stamped with the time and ``name`` (e.g. ``plan[3]``).

    pymavlink's own loggers stay at WARNING: at INFO they log every frame whose signature does
    not match (``sig mismatch``), which the MAVLink client counts and reports once instead."""
    logging.basicConfig(level=level, stream=sys.stderr, format=f"%(asctime)s {name} %(levelname)s %(message)s")
    logging.getLogger("pymavlink").setLevel(max(logging.WARNING, logging.getLogger().getEffectiveLevel()))


def zenoh_settings(mission: Mission, zenoh_config: str | None, zenoh_connect: Sequence[str] | None) -> SessionSettings:
    """The Zenoh session settings of a process: ``--zenoh-config`` (the JSON ``fimnav launch``
    writes) if given, else the mission's ``zenoh`` section; ``--zenoh-connect`` endpoints added."""
    from comms.session import SessionSettings

    if zenoh_config:
        try:
            settings = SessionSettings.from_json(json.loads(zenoh_config))
        except (ValueError, TypeError, AttributeError) as exc:
            raise UsageError(f"--zenoh-config: expected the JSON written by fimnav launch ({exc})") from None
    else:
        settings = SessionSettings.from_mission(mission.zenoh)
    if zenoh_connect:
        settings = SessionSettings(**{**settings.__dict__, "connect": settings.connect + tuple(zenoh_connect)})
    return settings


def payload_world(mission: Mission) -> PayloadWorld:
    """The simulated payload's world of ``mission``: the source (position in m, velocity in
    m/s, mission frame ENU), the buildings' boxes (m), the channel and the seed."""
    from planner.geometry import vec3
    from vehicle_sim.payload import PayloadWorld

    mins, maxs = mission.obstacle_bounds()
    return PayloadWorld(
        source_position_m=vec3(mission.source.position_m),
        source_velocity_mps=vec3(mission.source.velocity_mps),
        boxes_min_m=tuple(vec3(row) for row in mins),
        boxes_max_m=tuple(vec3(row) for row in maxs),
        channel=mission.channel.to_planner(),
        seed=int(mission.seed),
        power_offset_db=float(mission.source.power_offset_db),
    )

"""Zenoh key expressions of fimnav: everything under ``fimnav/<mission id>/``.

Drone ids in keys and messages are 1-based (as users number drones); arrays inside the code
use 0-based indices (id − 1).

===============================================  ==========================================
key expression                                   what
===============================================  ==========================================
``fimnav/<id>/record/<uav>``                     a planner's shared record (position + estimate)
``fimnav/<id>/measurement/<uav>``                the RSS payload's measurement for that drone
``fimnav/<id>/status/<uav>``                     a planner's per-step status (for the launcher)
``fimnav/<id>/clock/tick``                       lockstep clock: advance to step k, time t_k
``fimnav/<id>/clock/done/<uav>``                 a participant finished step k
``fimnav/<id>/alive/<role>/<uav>``               liveliness token (role: planner, vehicle, payload)
``fimnav/<id>/control/<uav>``                    operator commands to a planner (``fimnav handback``)
===============================================  ==========================================
"""

from __future__ import annotations

import re

PREFIX = "fimnav"
_ID = re.compile(r"^[A-Za-z0-9_-]+$")


def _check(mission_id: str) -> str:
    if not _ID.match(mission_id):
        raise ValueError(f"mission id: expected letters, digits, '_' or '-', found {mission_id!r}")
    return mission_id


def root(mission_id: str) -> str:
    """``fimnav/<mission id>``."""
    return f"{PREFIX}/{_check(mission_id)}"


def record(mission_id: str, uav: int | str = "*") -> str:
    """Records of drone ``uav`` (1-based), or of all drones with ``"*"``."""
    return f"{root(mission_id)}/record/{uav}"


def measurement(mission_id: str, uav: int | str = "*") -> str:
    """Payload measurements of drone ``uav``."""
    return f"{root(mission_id)}/measurement/{uav}"


def status(mission_id: str, uav: int | str = "*") -> str:
    """Per-step planner status of drone ``uav``."""
    return f"{root(mission_id)}/status/{uav}"


def tick(mission_id: str) -> str:
    """The lockstep clock's tick."""
    return f"{root(mission_id)}/clock/tick"


def done(mission_id: str, uav: int | str = "*") -> str:
    """Step-completion reports to the lockstep clock."""
    return f"{root(mission_id)}/clock/done/{uav}"


def alive(mission_id: str, role: str = "*", uav: int | str = "*") -> str:
    """Liveliness token of a participant (``role`` planner, vehicle or payload)."""
    return f"{root(mission_id)}/alive/{role}/{uav}"


def control(mission_id: str, uav: int | str = "*") -> str:
    """Operator commands to drone ``uav``'s planner (JSON ``{"command": "handback"}``)."""
    return f"{root(mission_id)}/control/{uav}"


def uav_of(key: str) -> int | None:
    """The drone id at the end of a per-drone key expression, or None if it is not one."""
    tail = str(key).rsplit("/", 1)[-1]
    return int(tail) if tail.isdigit() and len(tail) <= 6 else None

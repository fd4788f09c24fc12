"""Zenoh publishers of fimnav: reliable, and blocking rather than dropping under congestion.

Zenoh's default congestion control for a publication is DROP: under load (dozens of processes
on two cores) a tick, a record or a measurement could be discarded, and a lockstep swarm would
wait for it forever. Every fimnav publisher blocks instead, with reliable delivery.
"""

from __future__ import annotations

from typing import Any


def declare_publisher(session: Any, key: str) -> Any:
    """A publisher on ``key`` with BLOCK congestion control and RELIABLE delivery."""
    import zenoh

    return session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)

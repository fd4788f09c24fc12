"""Loopback UDP helpers of the fuzz tests: kernel drop counters, waits with deadlines."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any


def udp_drops(port: int) -> int:
    """Datagrams the kernel dropped on the IPv4 UDP socket bound to local ``port`` (on
    127.0.0.1 or the wildcard address; ``drops`` column of /proc/net/udp): a receive buffer
    overflow shows up here."""
    wanted = {f"0100007F:{port:04X}", f"00000000:{port:04X}"}
    with open("/proc/net/udp") as fh:
        next(fh)
        for line in fh:
            cols = line.split()
            if cols[1] in wanted:
                return int(cols[-1])
    raise AssertionError(f"no UDP socket bound to port {port}")


def recv_until(conn: Any, pred: Callable[[Any], bool], timeout_s: float, what: str) -> Any:
    """Read a pymavlink ``mavutil`` connection until a message satisfies ``pred``."""
    deadline = time.monotonic() + timeout_s
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            raise AssertionError(f"no {what} within {timeout_s:g} s")
        m = conn.recv_match(blocking=True, timeout=min(left, 0.2))
        if m is not None and pred(m):
            return m

"""Free ports for the tests."""

from __future__ import annotations

import socket


def free_port(kind: int = socket.SOCK_STREAM, host: str = "127.0.0.1") -> int:
    """A port of ``kind`` (``SOCK_STREAM``: TCP, ``SOCK_DGRAM``: UDP) free on ``host`` now, chosen
    by the OS. ``host="0.0.0.0"``: free on every interface (for a program that binds them all)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])

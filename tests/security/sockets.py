"""The sockets a process has open, from /proc (Linux): protocol, local address, TCP state."""

from __future__ import annotations

import os
import socket
import struct
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Sock:
    proto: str  # tcp, tcp6, udp, udp6
    host: str
    port: int
    listening: bool  # TCP LISTEN, or any bound UDP socket (it receives from anyone who can reach it)

    @property
    def loopback(self) -> bool:
        return self.host.startswith("127.") or self.host == "::1"


def _addr(hex_addr: str, v6: bool) -> tuple[str, int]:
    h, p = hex_addr.split(":")
    raw = bytes.fromhex(h)
    if v6:
        raw = b"".join(struct.pack("<I", struct.unpack(">I", raw[i : i + 4])[0]) for i in range(0, 16, 4))
        return socket.inet_ntop(socket.AF_INET6, raw), int(p, 16)
    return socket.inet_ntoa(raw[::-1]), int(p, 16)


def _table() -> dict[int, Sock]:
    out: dict[int, Sock] = {}
    for proto in ("tcp", "tcp6", "udp", "udp6"):
        try:
            lines = Path(f"/proc/net/{proto}").read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            cols = line.split()
            host, port = _addr(cols[1], proto.endswith("6"))
            state = int(cols[3], 16)
            listening = state == 0x0A if proto.startswith("tcp") else port != 0
            out[int(cols[9])] = Sock(proto, host, port, listening)
    return out


def sockets_of(pid: int) -> list[Sock]:
    """Every INET socket of process ``pid`` (its threads share the fd table)."""
    inodes = []
    fd_dir = Path(f"/proc/{pid}/fd")
    try:
        for fd in fd_dir.iterdir():
            try:
                target = os.readlink(fd)
            except OSError:
                continue
            if target.startswith("socket:["):
                inodes.append(int(target[8:-1]))
    except OSError:
        return []
    table = _table()
    return [table[i] for i in inodes if i in table]

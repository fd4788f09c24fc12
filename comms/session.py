"""Zenoh sessions built from a mission's ``zenoh`` section.

The default is an embedded peer on loopback only: it listens on 127.0.0.1 (an OS-chosen port
unless the mission names one), multicast scouting is off, so nothing outside the machine is
contacted and nothing else has to be started. ``fimnav launch`` adds, for every child
process, the launcher's own endpoint to ``connect``; peers then learn each other's
endpoints by gossip. Client and router modes and explicit endpoints come from the mission, so
planners on several machines join through Zenoh routers (docs/comms.md).

The transport lease is short (:data:`LEASE_MS`), so a peer that dies is noticed (liveliness
token deleted) within a few seconds.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

#: Zenoh transport lease (ms): a silent peer is declared gone after this.
LEASE_MS: int = 2000
#: Keep-alive messages per lease.
KEEP_ALIVE: int = 4


class ZenohSection(Protocol):
    """What this module reads of ``missions.schema.ZenohSpec`` (duck-typed: comms does not
    import missions)."""

    mode: str
    listen: Sequence[str]
    connect: Sequence[str]
    multicast_scouting: bool
    tls: Any
    auth: Any


@dataclass(frozen=True)
class SessionSettings:
    """Plain settings of one Zenoh session (what :func:`zenoh_config` turns into a Config)."""

    mode: str = "peer"
    listen: tuple[str, ...] = ("tcp/127.0.0.1:0",)
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    tls_root_ca: Path | None = None
    tls_certificate: Path | None = None
    tls_private_key: Path | None = None
    auth_user: str | None = None
    auth_password_file: Path | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_mission(cls, spec: ZenohSection, connect: Sequence[str] = (), listen: Sequence[str] | None = None) -> SessionSettings:
        """Settings from a mission's ``zenoh`` section, plus endpoints to connect to."""
        tls, auth = spec.tls, spec.auth
        return cls(
            mode=spec.mode,
            listen=tuple(listen) if listen is not None else tuple(spec.listen),
            connect=tuple(spec.connect) + tuple(connect),
            multicast_scouting=bool(spec.multicast_scouting),
            tls_root_ca=Path(tls.root_ca_certificate) if tls else None,
            tls_certificate=Path(tls.certificate) if tls and tls.certificate else None,
            tls_private_key=Path(tls.private_key) if tls and tls.private_key else None,
            auth_user=auth.user if auth else None,
            auth_password_file=Path(auth.password_file) if auth else None,
        )

    def to_cli(self) -> list[str]:
        """Command-line options that rebuild these settings in a child process."""
        return ["--zenoh-config", json.dumps(self.to_json())]

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {"mode": self.mode, "listen": list(self.listen), "connect": list(self.connect), "multicast_scouting": self.multicast_scouting}
        for name in ("tls_root_ca", "tls_certificate", "tls_private_key", "auth_user", "auth_password_file"):
            value = getattr(self, name)
            if value is not None:
                d[name] = str(value)
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> SessionSettings:
        paths = {k: Path(d[k]) for k in ("tls_root_ca", "tls_certificate", "tls_private_key", "auth_password_file") if d.get(k)}
        return cls(
            mode=str(d.get("mode", "peer")),
            listen=tuple(d.get("listen", ("tcp/127.0.0.1:0",))),
            connect=tuple(d.get("connect", ())),
            multicast_scouting=bool(d.get("multicast_scouting", False)),
            auth_user=d.get("auth_user"),
            **paths,
        )


def zenoh_config(settings: SessionSettings):  # noqa: ANN201 - zenoh.Config, imported lazily
    """The ``zenoh.Config`` of these settings."""
    import zenoh

    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(settings.mode))
    cfg.insert_json5("listen/endpoints", json.dumps(list(settings.listen)))
    cfg.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    cfg.insert_json5("transport/link/tx/lease", str(LEASE_MS))
    cfg.insert_json5("transport/link/tx/keep_alive", str(KEEP_ALIVE))
    if settings.tls_root_ca is not None:
        tls: dict[str, Any] = {"root_ca_certificate": str(settings.tls_root_ca), "enable_mtls": settings.tls_certificate is not None}
        if settings.tls_certificate is not None and settings.tls_private_key is not None:
            tls.update(
                listen_certificate=str(settings.tls_certificate),
                listen_private_key=str(settings.tls_private_key),
                connect_certificate=str(settings.tls_certificate),
                connect_private_key=str(settings.tls_private_key),
            )
        cfg.insert_json5("transport/link/tls", json.dumps(tls))
    if settings.auth_user is not None and settings.auth_password_file is not None:
        password = settings.auth_password_file.read_text().strip()
        cfg.insert_json5(
            "transport/auth/usrpwd",
            json.dumps({"user": settings.auth_user, "password": password}),
        )
    for key, value in settings.extra.items():
        cfg.insert_json5(key, json.dumps(value))
    return cfg


def open_session(settings: SessionSettings):  # noqa: ANN201 - zenoh.Session
    """Open a Zenoh session with these settings."""
    import zenoh

    return zenoh.open(zenoh_config(settings))

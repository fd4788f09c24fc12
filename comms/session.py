"""Zenoh sessions built from a mission's ``zenoh`` section.

The default is an embedded peer on loopback only: it listens on 127.0.0.1 (an OS-chosen port
unless the mission names one), multicast scouting is off, so nothing outside the machine is
contacted and nothing else has to be started. ``fimnav launch`` adds, for every child
process, the launcher's own endpoint to ``connect``; peers then learn each other's
endpoints by gossip. Client and router modes and explicit endpoints come from the mission, so
planners on several machines join through Zenoh routers (docs/distributed.md).

The transport lease is short (:data:`LEASE_MS`), so a peer that dies is noticed (liveliness
token deleted) within a few seconds.

Security (docs/security.md), configured from the mission's ``zenoh.tls`` and ``zenoh.auth``:

* TLS (zenoh ``transport/link/tls``): ``root_ca_certificate`` verifies the other side's
  certificate; with this node's ``certificate`` + ``private_key`` it is used both to listen
  and to connect, and mutual TLS is on (a peer without a certificate signed by the CA cannot
  connect). With TLS every endpoint speaks TLS: ``tcp/HOST:PORT`` is taken as
  ``tls/HOST:PORT`` (so ``fimnav launch``'s loopback hub needs no change), ``tls/`` and
  ``quic/`` stay, any other protocol is refused (it would bypass TLS).
* User/password (zenoh ``transport/auth/usrpwd``): the node authenticates with ``user`` and
  the password read from ``password_file``, and it accepts only peers that present the same
  credentials (zenoh checks incoming peers against a ``dictionary_file`` of ``user:password``
  lines; fimnav writes a private one for the swarm's credential, read by zenoh when the
  session opens and deleted right after).
* Secret files (private key, password) must not be readable by group or others: refused
  with a clear :class:`~comms.errors.UsageError`. Secrets never appear in messages, logs or
  command lines (children get file paths, not contents).
"""

from __future__ import annotations

import json
import os
import stat
import tempfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from comms.errors import UsageError

if TYPE_CHECKING:  # zenoh is imported when a session is made
    import zenoh

#: Zenoh transport lease (ms): a silent peer is declared gone after this.
LEASE_MS: int = 2000
#: Keep-alive messages per lease.
KEEP_ALIVE: int = 4


class ZenohSection(Protocol):
    """What this module reads of ``missions.format.schema.ZenohSpec`` (duck-typed: comms does not
    import missions). Read-only: the mission's sections are frozen."""

    @property
    def mode(self) -> str: ...
    @property
    def listen(self) -> Sequence[str]: ...
    @property
    def connect(self) -> Sequence[str]: ...
    @property
    def multicast_scouting(self) -> bool: ...
    @property
    def tls(self) -> Any: ...
    @property
    def auth(self) -> Any: ...


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
        d: dict[str, Any] = {
            "mode": self.mode,
            "listen": list(self.listen),
            "connect": list(self.connect),
            "multicast_scouting": self.multicast_scouting,
        }
        for name in ("tls_root_ca", "tls_certificate", "tls_private_key", "auth_user", "auth_password_file"):
            value = getattr(self, name)
            if value is not None:
                d[name] = str(value)
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> SessionSettings:
        def path(key: str) -> Path | None:
            return Path(d[key]) if d.get(key) else None

        return cls(
            mode=str(d.get("mode", "peer")),
            listen=tuple(d.get("listen", ("tcp/127.0.0.1:0",))),
            connect=tuple(d.get("connect", ())),
            multicast_scouting=bool(d.get("multicast_scouting", False)),
            tls_root_ca=path("tls_root_ca"),
            tls_certificate=path("tls_certificate"),
            tls_private_key=path("tls_private_key"),
            auth_user=d.get("auth_user"),
            auth_password_file=path("auth_password_file"),
        )


def check_secret_file(path: Path, what: str) -> None:
    """Refuse a secret file (private key, password) that is missing, not a regular file, or
    readable/writable by its group or others.

    Raises:
        UsageError: naming the file and what to do.
    """
    try:
        st = path.stat()
    except OSError as exc:
        raise UsageError(f"{what} {str(path)!r}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise UsageError(f"{what} {str(path)!r}: expected a regular file")
    if st.st_mode & 0o077:
        raise UsageError(
            f"{what} {str(path)!r}: permissions {stat.S_IMODE(st.st_mode):04o} let the group or others read it; "
            f"expected 0600 or stricter (run: chmod 600 {path})"
        )


def read_password(path: Path) -> str:
    """The password in ``path`` (first line, surrounding white space removed)."""
    check_secret_file(path, "zenoh password file")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UsageError(f"zenoh password file {str(path)!r}: {getattr(exc, 'strerror', None) or exc}") from None
    lines = text.strip().splitlines()
    if not lines or not lines[0].strip():
        raise UsageError(f"zenoh password file {str(path)!r}: expected a password on the first line, found an empty file")
    return lines[0].strip()


def tls_endpoints(endpoints: Sequence[str], what: str) -> list[str]:
    """Endpoints under TLS: ``tcp/`` becomes ``tls/``; ``tls/`` and ``quic/`` stay.

    Raises:
        UsageError: an endpoint of another protocol (it would not be encrypted).
    """
    out = []
    for e in endpoints:
        proto, sep, rest = e.partition("/")
        if not sep:
            raise UsageError(f"zenoh {what} endpoint {e!r}: expected PROTOCOL/ADDRESS (tls/HOST:PORT)")
        if proto == "tcp":
            out.append(f"tls/{rest}")
        elif proto in ("tls", "quic"):
            out.append(e)
        else:
            raise UsageError(f"zenoh {what} endpoint {e!r}: with zenoh.tls every endpoint must be tls/ (or tcp/, taken as tls/), found {proto}/")
    return out


def zenoh_config(settings: SessionSettings, dictionary_file: Path | None = None) -> zenoh.Config:
    """The ``zenoh.Config`` of these settings.

    Args:
        settings: the session settings.
        dictionary_file: the ``user:password`` file zenoh checks incoming peers against
            (required with user/password authentication; :func:`open_session` makes one).

    Raises:
        UsageError: a secret file with open permissions, an endpoint that would bypass TLS,
            authentication without a dictionary.
    """
    import zenoh

    listen, connect = list(settings.listen), list(settings.connect)
    tls: dict[str, Any] | None = None
    if settings.tls_root_ca is not None:
        listen, connect = tls_endpoints(listen, "listen"), tls_endpoints(connect, "connect")
        tls = {"root_ca_certificate": str(settings.tls_root_ca), "enable_mtls": settings.tls_certificate is not None}
        if (settings.tls_certificate is None) != (settings.tls_private_key is None):
            raise UsageError("zenoh.tls: give both certificate and private_key, or neither")
        if settings.tls_certificate is not None and settings.tls_private_key is not None:
            check_secret_file(settings.tls_private_key, "zenoh TLS private key")
            tls.update(
                listen_certificate=str(settings.tls_certificate),
                listen_private_key=str(settings.tls_private_key),
                connect_certificate=str(settings.tls_certificate),
                connect_private_key=str(settings.tls_private_key),
            )
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(settings.mode))
    cfg.insert_json5("listen/endpoints", json.dumps(listen))
    cfg.insert_json5("connect/endpoints", json.dumps(connect))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    cfg.insert_json5("transport/link/tx/lease", str(LEASE_MS))
    cfg.insert_json5("transport/link/tx/keep_alive", str(KEEP_ALIVE))
    if tls is not None:
        cfg.insert_json5("transport/link/tls", json.dumps(tls))
    if settings.auth_user is not None and settings.auth_password_file is not None:
        if dictionary_file is None:
            raise UsageError("zenoh.auth: a user/password session needs a dictionary file (use open_session)")
        password = read_password(settings.auth_password_file)
        cfg.insert_json5(
            "transport/auth/usrpwd",
            json.dumps({"user": settings.auth_user, "password": password, "dictionary_file": str(dictionary_file)}),
        )
    for key, value in settings.extra.items():
        cfg.insert_json5(key, json.dumps(value))
    return cfg


@contextmanager
def _swarm_dictionary(settings: SessionSettings) -> Iterator[Path | None]:
    """A private (0600, own temporary directory) ``user:password`` file holding the swarm's
    credential, deleted when the block ends; None without authentication."""
    if settings.auth_user is None or settings.auth_password_file is None:
        yield None
        return
    user = settings.auth_user
    if ":" in user or any(c.isspace() for c in user):
        raise UsageError(f"zenoh.auth.user {user!r}: expected a name without ':' or white space")
    password = read_password(settings.auth_password_file)
    with tempfile.TemporaryDirectory(prefix="fimnav-zenoh-") as tmp:
        path = Path(tmp) / "usrpwd"
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(f"{user}:{password}\n")
        yield path


def open_session(settings: SessionSettings) -> zenoh.Session:
    """Open a Zenoh session with these settings."""
    import zenoh

    with _swarm_dictionary(settings) as dictionary:
        return zenoh.open(zenoh_config(settings, dictionary))

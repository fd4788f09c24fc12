"""``fimnav router``: a Zenoh router for swarms spread over several machines or networks.

Planners (``fimnav plan --zenoh-config '{"mode": "client", "connect": [...]}'`` or
``--zenoh-connect``) and payloads join the swarm through a router; routers linked with
``--connect`` forward every message and liveliness token between their clients, so two
groups of drones on separate routers form one swarm while the link is up, and two
independent halves (each still flying on its own data) while it is down
(docs/distributed.md, "Partitions").

Examples::

    fimnav router                                           # tcp/127.0.0.1:7447
    fimnav router --listen tcp/0.0.0.0:7447 --connect tcp/10.0.0.2:7447
    fimnav router --listen tcp/127.0.0.1:0 --mission mission.yaml   # TLS/auth of the mission

Once listening, the command prints one JSON line on stdout::

    {"event": "ready", "mode": "router", "zid": "...", "listen": ["tcp/127.0.0.1:7447"], "connect": []}

(``listen`` holds the actual endpoints: the OS-chosen port of ``:0``). It runs until SIGINT
or SIGTERM (or ``--duration``) and then exits 0. The router is the same Zenoh router as
``zenohd`` (Zenoh 1.x, built from :func:`comms.session.zenoh_config`: transport lease 2 s,
multicast scouting off unless asked), so a ``zenohd`` may stand in for it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

from comms.errors import UsageError

if TYPE_CHECKING:
    from comms.session import SessionSettings

#: Where a router listens when no ``--listen`` is given (Zenoh's usual router port).
DEFAULT_LISTEN: str = "tcp/127.0.0.1:7447"
#: Seconds to wait for the router's own admin space to list its locators.
LOCATOR_QUERY_TIMEOUT_S: float = 5.0


def register(subparsers: Any) -> None:
    """Add the ``router`` subcommand to the ``fimnav`` parser."""
    p = subparsers.add_parser(
        "router",
        help="run a Zenoh router (join planners on several machines; link routers with --connect)",
        description="Run a Zenoh router: clients and peers of the swarm connect to it; routers linked with "
        "--connect forward messages and liveliness between their clients. Prints a JSON ready line with the "
        "actual endpoints, runs until SIGINT/SIGTERM (exit 0).",
    )
    p.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help=f"endpoint to listen on, PROTOCOL/HOST:PORT (repeatable; default {DEFAULT_LISTEN}; port 0: OS-chosen)",
    )
    p.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="router or peer to link with, PROTOCOL/HOST:PORT (repeatable; retried until it answers)",
    )
    p.add_argument(
        "--mission", type=Path, metavar="MISSION.yaml", help="take TLS and user/password authentication (zenoh.tls, zenoh.auth) from this mission"
    )
    sec = p.add_argument_group("security (override the mission's; docs/security.md)")
    sec.add_argument("--tls-root-ca", type=Path, metavar="FILE", help="CA certificate that signed the other side's")
    sec.add_argument("--tls-certificate", type=Path, metavar="FILE", help="this router's certificate (mutual TLS)")
    sec.add_argument("--tls-private-key", type=Path, metavar="FILE", help="this router's private key, mode 0600")
    sec.add_argument("--auth-user", metavar="USER", help="swarm user name (user/password authentication)")
    sec.add_argument("--auth-password-file", type=Path, metavar="FILE", help="swarm password file, mode 0600")
    p.add_argument("--multicast-scouting", action="store_true", help="answer multicast scouting on the LAN (default off)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after this many wall seconds")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    p.set_defaults(func=run_router)


def check_endpoint(endpoint: str, option: str) -> str:
    """Refuse an endpoint that is not ``PROTOCOL/ADDRESS`` (zenoh's locator syntax).

    Raises:
        UsageError: naming the option, what was expected and what was found.
    """
    proto, sep, rest = endpoint.partition("/")
    if not sep or not proto or not rest or any(c.isspace() for c in endpoint):
        raise UsageError(f"{option} {endpoint!r}: expected PROTOCOL/HOST:PORT, e.g. tcp/127.0.0.1:7447")
    return endpoint


def router_settings(args: argparse.Namespace) -> SessionSettings:
    """The :class:`comms.session.SessionSettings` of the router from the options (and the
    mission's TLS/auth, if ``--mission`` is given; flags override it).

    Raises:
        UsageError: bad endpoints, half a TLS identity, authentication without both parts.
    """
    from comms.session import SessionSettings  # the run-time import (zenoh-free)

    listen = tuple(check_endpoint(e, "--listen") for e in (args.listen or [DEFAULT_LISTEN]))
    connect = tuple(check_endpoint(e, "--connect") for e in args.connect)
    settings = SessionSettings(mode="router", listen=listen, connect=connect)
    if args.mission is not None:
        from missions.format.loader import load_mission

        mission = load_mission(args.mission)
        settings = dataclasses.replace(SessionSettings.from_mission(mission.zenoh, listen=listen), mode="router", connect=connect)
    overrides: dict[str, Any] = {}
    for flag, name in (
        ("tls_root_ca", "tls_root_ca"),
        ("tls_certificate", "tls_certificate"),
        ("tls_private_key", "tls_private_key"),
        ("auth_user", "auth_user"),
        ("auth_password_file", "auth_password_file"),
    ):
        value = getattr(args, flag)
        if value is not None:
            overrides[name] = value
    settings = dataclasses.replace(settings, **overrides, multicast_scouting=bool(args.multicast_scouting or settings.multicast_scouting))
    if (settings.tls_certificate is not None or settings.tls_private_key is not None) and settings.tls_root_ca is None:
        raise UsageError("--tls-certificate/--tls-private-key: give --tls-root-ca too (the CA that signs the swarm's certificates)")
    if (settings.auth_user is None) != (settings.auth_password_file is None):
        raise UsageError("--auth-user/--auth-password-file: give both, or neither")
    # The router's own admin space (read-only, as zenohd's default) lists the actual locators.
    extra = {**settings.extra, "adminspace": {"enabled": True, "permissions": {"read": True, "write": False}}}
    return dataclasses.replace(settings, extra=extra)


def listening_endpoints(session: Any, timeout_s: float = LOCATOR_QUERY_TIMEOUT_S) -> list[str]:
    """The endpoints the router actually listens on (ports chosen by the OS resolved), from
    its admin space ``@/<zid>/router``; empty if it does not answer within ``timeout_s``."""
    zid = session.info.zid()
    for reply in session.get(f"@/{zid}/router", timeout=timeout_s):
        try:
            info = json.loads(reply.ok.payload.to_string())
        except (AttributeError, ValueError, TypeError):
            continue
        return [str(x) for x in info.get("locators", [])]
    return []


def run_router(args: argparse.Namespace) -> int:
    """Run the router until a stop signal (exit 128 + signal) or ``--duration`` (exit 0)."""
    from missions.cli.process_args import setup_logging

    setup_logging(args.log_level, "router")
    log = logging.getLogger("fimnav.router")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise UsageError(f"--duration: expected a positive number of seconds, found {args.duration}")
    settings = router_settings(args)

    from comms.session import open_session
    from missions.runtime.signals import StopRequest, stop_on_signals

    stop = threading.Event()
    request = StopRequest(stop.set)
    with stop_on_signals(request):
        try:
            session = open_session(settings)
        except UsageError:
            raise
        except Exception as exc:  # zenoh raises its own ZError for bad or busy endpoints
            raise UsageError(f"zenoh: cannot open the router ({exc})") from None
        try:
            ready = {
                "event": "ready",
                "mode": "router",
                "zid": str(session.info.zid()),
                "listen": listening_endpoints(session) or list(settings.listen),
                "connect": list(settings.connect),
            }
            print(json.dumps(ready), flush=True)
            log.info("listening on %s; linking with %s", ", ".join(ready["listen"]), ", ".join(settings.connect) or "nothing")
            stop.wait(args.duration)
            log.info("stopping")
        finally:
            session.close()
    request.raise_if_stopped()
    return 0

"""Zenoh for the tests: a session listening on a free loopback port, a session configured by
hand (not through fimnav's code), and ``fimnav router`` processes."""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from typing import Any

from tests.support.net import free_port
from tests.support.proc import Proc, fimnav


def open_hub(mode: str = "peer") -> tuple[Any, str]:
    """A fimnav Zenoh session (:func:`comms.session.open_session`, ``mode``) listening on a free
    loopback TCP port; the session and its endpoint (``tcp/127.0.0.1:PORT``)."""
    from comms.session import SessionSettings, open_session

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    return open_session(SessionSettings(mode=mode, listen=(endpoint,))), endpoint


def raw_session(*, listen: Sequence[str] = (), connect: Sequence[str] | None = None,
                tls: dict[str, Any] | None = None, auth: dict[str, Any] | None = None) -> Any:
    """A Zenoh peer configured by hand, not through fimnav's session code (an attacker, a source
    of garbage): ``listen`` and ``connect`` endpoints, multicast scouting off, the
    ``transport/link/tls`` and ``transport/auth/usrpwd`` sections if given."""
    import zenoh

    c = zenoh.Config()
    c.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect is not None:
        c.insert_json5("connect/endpoints", json.dumps(list(connect)))
    c.insert_json5("scouting/multicast/enabled", "false")
    if tls is not None:
        c.insert_json5("transport/link/tls", json.dumps(tls))
    if auth is not None:
        c.insert_json5("transport/auth/usrpwd", json.dumps(auth))
    return zenoh.open(c)


def start_router(procs: list[Proc], *connect: str, listen: str = "tcp/127.0.0.1:0") -> tuple[Proc, str, float]:
    """``fimnav router`` listening on ``listen`` (by default a loopback port the OS picks), linked
    to ``connect``; appended to ``procs``. The process, its endpoint (from its ready line) and the
    monotonic time the ready line was seen."""
    args = ["router", "--listen", listen, "--log-level", "WARNING"]
    for e in connect:
        args += ["--connect", e]
    p = Proc(fimnav(*args))
    procs.append(p)
    ready = p.ready(30.0)
    return p, str(ready["listen"][0]), time.monotonic()

"""The signals that stop a ``fimnav launch`` run, and the error that ends a run they stopped.

Ctrl-C, SIGTERM and SIGHUP ask the launcher to stop; it then stops every child and exits with
128 + the signal's number (130, 143, 129), as a shell reports a command the signal ended.
"""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator
from typing import Any, Protocol

from comms.errors import FimnavError


class Interrupted(FimnavError):
    """Ctrl-C, SIGTERM or SIGHUP: every child was stopped. The exit status is 128 + the
    signal's number (130, 143, 129), as a shell reports a command the signal ended."""

    exit_code = 128 + signal.SIGINT

    def __init__(self, message: str, signum: int = signal.SIGINT) -> None:
        super().__init__(message)
        self.signum = int(signum)
        self.exit_code = 128 + self.signum


#: The signals that stop a run: Ctrl-C, ``kill``, and the hang-up of the launcher's terminal
#: (its children, in their own sessions, never see that one).
STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class Stoppable(Protocol):
    """What a signal handler asks to stop (:class:`missions.launch.launcher.Launcher`)."""

    def request_stop(self, signum: int | None = None) -> None:
        """Ask the run to stop; ``signum``: the signal that asked."""


@contextlib.contextmanager
def stop_on_signals(launcher: Stoppable) -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP ask the launcher to stop (children are then stopped cleanly).
    An ignored SIGHUP stays ignored (``nohup fimnav launch``: the run outlives the terminal);
    SIGINT is handled even if inherited ignored (a launch started from a background job)."""
    previous = {}
    for s in STOP_SIGNALS:
        current = signal.getsignal(s)
        if s == signal.SIGHUP and current == signal.SIG_IGN:
            continue
        previous[s] = current

    def handler(signum: int, frame: Any) -> None:
        launcher.request_stop(signum)

    for s in previous:
        signal.signal(s, handler)
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)

"""How a signal stops a ``fimnav`` command: one behaviour per signal, for every command.

Ctrl-C (SIGINT), SIGTERM and SIGHUP stop the command: it stops what it started (child
processes, worker pools, Zenoh sessions, MAVLink links), then exits with 128 + the signal's
number (130, 143, 129), as a shell reports a command the signal ended. SIGINT and SIGTERM are
handled even when inherited ignored (a background job of a script inherits SIGINT ignored, and
``kill -INT`` must still stop it); a SIGHUP inherited ignored stays ignored (``nohup fimnav
...``: the command outlives the terminal). Off the main thread nothing is changed (Python runs
handlers there only).

A command stops in one of two ways:

* :func:`raise_on_signals` (every command, from :func:`missions.cli.main.main`): SIGINT raises
  ``KeyboardInterrupt`` and SIGTERM or SIGHUP :class:`Stopped` in the main thread, so the
  command's ``finally`` blocks stop what it started, within :data:`CLEANUP_GRACE_S`; a second
  such signal ends the process at once.
* :func:`stop_on_signals` (a command with a loop of its own: ``launch``, ``vehicle``,
  ``payload``, ``router``): the signal asks the loop to stop (``request_stop(signum)``); the
  command stops what it started and then raises :class:`Interrupted`, which names the signal.

A worker pool starts inside :func:`signals_deferred` (a signal that arrives while the workers
are forked is handled after, not lost), and each worker runs :func:`worker_defaults`.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from types import FrameType
from typing import Any, Protocol

from comms.errors import FimnavError

#: The signals that stop a command: Ctrl-C, ``kill``, and the hang-up of its terminal.
STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

#: Seconds a command ended by SIGTERM or SIGHUP has for its clean-up (``finally`` blocks, e.g.
#: a process pool finishing its queue) before it exits with 128 + signal regardless.
CLEANUP_GRACE_S: float = 5.0


def exit_status(signum: int) -> int:
    """The exit status of a command a signal stopped: 128 + its number (130, 143, 129)."""
    return 128 + int(signum)


@contextlib.contextmanager
def _handlers(new: dict[signal.Signals, Any]) -> Iterator[None]:
    """Inside: each signal of ``new`` has its handler; on leaving, the previous ones are back."""
    previous = {s: signal.signal(s, h) for s, h in new.items()}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def _handled(signum: int) -> bool:
    """Whether a command takes over ``signum`` now: not a SIGHUP inherited ignored (``nohup``)."""
    return not (signum == signal.SIGHUP and signal.getsignal(signum) == signal.SIG_IGN)


class Interrupted(FimnavError):
    """A stop signal ended the command after it stopped what it started. The exit status is
    128 + the signal's number (130, 143, 129), as a shell reports a command the signal ended."""

    exit_code = exit_status(signal.SIGINT)

    def __init__(self, message: str, signum: int = signal.SIGINT) -> None:
        super().__init__(message)
        self.signum = int(signum)
        self.exit_code = exit_status(self.signum)


class Stopped(BaseException):
    """SIGTERM or SIGHUP ended the command: raised in the main thread like KeyboardInterrupt for
    Ctrl-C (``finally`` blocks run; ``except Exception`` does not catch it); exit 128 + signal."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)


def _exit_now(command: str, signum: int) -> None:
    """The clean-up after ``signum`` took too long: say so and exit 128 + signal at once."""
    name = signal.Signals(signum).name
    sys.stderr.write(f"fimnav {command}: stopped by {name} (clean-up cut short after {CLEANUP_GRACE_S:g} s)\n")
    sys.stderr.flush()
    os._exit(exit_status(signum))


@contextlib.contextmanager
def raise_on_signals(command: str) -> Iterator[None]:
    """While ``command`` runs, SIGINT raises ``KeyboardInterrupt`` and SIGTERM or SIGHUP raise
    :class:`Stopped` in the main thread, with :data:`CLEANUP_GRACE_S` for the clean-up after
    SIGTERM or SIGHUP. A second SIGTERM or SIGHUP ends the process at once (the default
    action); so does one in a process forked from this one (a worker: as before). A SIGHUP
    inherited ignored stays ignored; off the main thread nothing is changed."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    owner = os.getpid()
    handlers: dict[signal.Signals, Any] = {}

    def terminate(signum: int, frame: FrameType | None) -> None:
        if os.getpid() != owner:
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        for s in handlers:
            if s != signal.SIGINT:
                signal.signal(s, signal.SIG_DFL if s == signum else signal.SIG_IGN)
        deadline = threading.Timer(CLEANUP_GRACE_S, _exit_now, args=(command, signum))
        deadline.daemon = True
        deadline.start()
        raise Stopped(signum)

    for s in STOP_SIGNALS:
        current = signal.getsignal(s)
        if s == signal.SIGINT:
            if current in (signal.SIG_IGN, signal.SIG_DFL):  # else: Python's KeyboardInterrupt already, or a caller's
                handlers[s] = signal.default_int_handler
        elif current == signal.SIG_DFL or (current == signal.SIG_IGN and _handled(s)):
            handlers[s] = terminate
    with _handlers(handlers):
        yield


class Stoppable(Protocol):
    """What a signal asks to stop (:class:`missions.launch.launcher.Launcher`, :class:`StopRequest`)."""

    def request_stop(self, signum: int | None = None) -> None:
        """Ask the command to stop; ``signum``: the signal that asked."""


class StopRequest:
    """The :class:`Stoppable` of a command with a loop of its own: records the first signal that
    asked it to stop and calls ``on_stop`` (e.g. an event's ``set``, a host's ``stop``)."""

    def __init__(self, on_stop: Callable[[], None]) -> None:
        self._on_stop = on_stop
        self.signum: int | None = None

    def request_stop(self, signum: int | None = None) -> None:
        """Ask the loop to stop (a signal handler: with the signal's number)."""
        if signum is not None and self.signum is None:
            self.signum = int(signum)
        self._on_stop()

    def raise_if_stopped(self) -> None:
        """After the loop stopped: :class:`Interrupted` if a signal stopped it."""
        if self.signum is not None:
            raise Interrupted(f"stopped by {signal.Signals(self.signum).name}", self.signum)


@contextlib.contextmanager
def stop_on_signals(target: Stoppable) -> Iterator[None]:
    """While inside, SIGINT, SIGTERM and SIGHUP call ``target.request_stop(signum)`` (the
    command then stops what it started, and ends with :class:`Interrupted`). A SIGHUP inherited
    ignored stays ignored; SIGINT and SIGTERM are handled even if inherited ignored. Off the
    main thread nothing is changed."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        target.request_stop(signum)

    with _handlers({s: handler for s in STOP_SIGNALS if _handled(s)}):
        yield


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """Inside: :data:`STOP_SIGNALS` are recorded, not handled; on leaving, the previous
    handlers are back and each recorded signal is raised again. In a process forked inside
    (a pool worker before its initializer) such a signal has its default effect at once:
    KeyboardInterrupt for SIGINT, the end of the process for SIGTERM and SIGHUP. A signal
    ignored (or handled outside Python) is left as it is."""
    owner = os.getpid()
    got: list[int] = []

    def record(signum: int, frame: FrameType | None) -> None:
        if os.getpid() == owner:
            got.append(signum)
        elif signum == signal.SIGINT:
            raise KeyboardInterrupt
        else:
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)

    held_back = [s for s in STOP_SIGNALS if signal.getsignal(s) not in (None, signal.SIG_IGN)]
    try:
        with _handlers(dict.fromkeys(held_back, record)):
            yield
    finally:
        for held in dict.fromkeys(got):
            signal.raise_signal(held)


def worker_defaults() -> None:
    """In a pool worker: SIGTERM and SIGHUP end the process at once (the default action), so
    the pool's ``terminate`` ends it wherever it waits; the command's own handlers belong to
    the parent. Ctrl-C raises KeyboardInterrupt, as in any Python process (the worker was
    forked while the parent held it back, :func:`signals_deferred`)."""
    for signum in (signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(signum) != signal.SIG_IGN:
            signal.signal(signum, signal.SIG_DFL)
    if signal.getsignal(signal.SIGINT) != signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)

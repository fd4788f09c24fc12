"""The ``fimnav`` command line: one entry point, one subcommand module each.

Each subcommand lives in its own module exposing ``register(subparsers) -> None``; the
module adds its parser and sets ``func`` (``Callable[[argparse.Namespace], int]``).
Heavy imports (zenoh, matplotlib, pymavlink) happen inside ``func``, so ``fimnav --help``
stays fast.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from types import FrameType
from typing import Any

from comms.errors import FimnavError

#: Subcommand modules, in the order ``fimnav --help`` lists them.
COMMAND_MODULES: tuple[str, ...] = (
    "missions.cli.vehicle",
    "missions.cli.check",
    "missions.cli.montecarlo",
    "missions.cli.optimum",
    "missions.cli.plan",
    "missions.cli.payload",
    "missions.cli.launch",
    "missions.cli.router",
    "missions.cli.handback",
    "missions.cli.view",
    "missions.cli.missions",
)


def installed_version() -> str:
    """The version of the installed ``fimnav`` distribution (``importlib.metadata``)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("fimnav")
    except PackageNotFoundError:
        return "(unknown version: the fimnav distribution is not installed; python3 -m pip install .)"


class _VersionAction(argparse.Action):
    """``--version``: print ``fimnav X.Y.Z`` on stdout and exit 0 (the version is looked up only then)."""

    def __init__(self, option_strings: Sequence[str], dest: str = argparse.SUPPRESS, help: str | None = None) -> None:
        super().__init__(option_strings, dest=dest, default=argparse.SUPPRESS, nargs=0, help=help)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: object, option_string: str | None = None) -> None:
        sys.stdout.write(f"fimnav {installed_version()}\n")
        parser.exit(0)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand registered."""
    parser = argparse.ArgumentParser(
        prog="fimnav",
        description="Fly a drone swarm to localize a radio source (A/D-optimal Fisher navigation).",
    )
    parser.add_argument("--version", action=_VersionAction, help="print the installed fimnav version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


class Terminated(BaseException):
    """SIGTERM or SIGHUP ended the command: raised in the main thread like KeyboardInterrupt for
    Ctrl-C (``finally`` blocks run; ``except Exception`` does not catch it); exit 128 + signal."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)


#: Signals that end any ``fimnav`` command with status 128 + their number, after its clean-up
#: (SIGINT: KeyboardInterrupt, 130). A command may handle them itself (``fimnav launch`` stops
#: its children first; ``fimnav vehicle`` and ``fimnav router`` stop cleanly with status 0).
TERMINATING_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGTERM, signal.SIGHUP)

#: Seconds a command ended by SIGTERM or SIGHUP has for its clean-up (``finally`` blocks, e.g.
#: a process pool finishing its queue) before it exits with 128 + signal regardless.
CLEANUP_GRACE_S: float = 5.0


def _exit_now(command: str, signum: int) -> None:
    """The clean-up after ``signum`` took too long: say so and exit 128 + signal at once."""
    name = signal.Signals(signum).name
    sys.stderr.write(f"fimnav {command}: stopped by {name} (clean-up cut short after {CLEANUP_GRACE_S:g} s)\n")
    sys.stderr.flush()
    os._exit(128 + signum)


@contextlib.contextmanager
def _terminate_on_signals(command: str) -> Iterator[None]:
    """While the command runs, :data:`TERMINATING_SIGNALS` raise :class:`Terminated` in the
    main thread, with :data:`CLEANUP_GRACE_S` for the clean-up. A second such signal ends the
    process at once (the default action); so does one in a process forked from this one (a
    ``multiprocessing`` worker: as before). A signal inherited ignored stays ignored
    (``nohup``); off the main thread nothing is changed."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    owner = os.getpid()
    # (what signal.signal returns: a handler, SIG_DFL/SIG_IGN, or None if not set from Python)
    previous: dict[signal.Signals, Callable[[int, FrameType | None], Any] | int | None] = {}

    def terminate(signum: int, frame: FrameType | None) -> None:
        if os.getpid() != owner:
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        for s in previous:
            signal.signal(s, signal.SIG_DFL if s == signum else signal.SIG_IGN)
        deadline = threading.Timer(CLEANUP_GRACE_S, _exit_now, args=(command, signum))
        deadline.daemon = True
        deadline.start()
        raise Terminated(signum)

    for s in TERMINATING_SIGNALS:
        if signal.getsignal(s) == signal.SIG_DFL:
            previous[s] = signal.signal(s, terminate)
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``fimnav`` with ``argv`` (default ``sys.argv[1:]``); return the exit status: 0, the
    command's error status (1, 2, 3), or 128 + the signal that ended it (SIGINT 130, SIGTERM
    143, SIGHUP 129)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        with _terminate_on_signals(args.command):
            return int(args.func(args) or 0)
    except FimnavError as exc:
        # An interruption (exit status 128 + signal, e.g. fimnav launch's) is not an error.
        label = "" if exc.exit_code >= 128 else "error: "
        print(f"fimnav {args.command}: {label}{exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"fimnav {args.command}: interrupted by SIGINT", file=sys.stderr)
        return 128 + signal.SIGINT
    except Terminated as exc:
        print(f"fimnav {args.command}: stopped by {exc}", file=sys.stderr)
        return 128 + exc.signum


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

"""The ``fimnav`` command line: one entry point, one subcommand module each.

Each subcommand lives in its own module exposing ``register(subparsers) -> None``; the
module adds its parser and sets ``func`` (``Callable[[argparse.Namespace], int]``).
Heavy imports (zenoh, matplotlib, pymavlink) happen inside ``func``, so ``fimnav --help``
stays fast. A new command's names and module go in :data:`COMMANDS` (a command line naming one
imports that module alone; ``fimnav --help`` lists them in its order).
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
from collections.abc import Sequence

from comms.errors import FimnavError
from missions.runtime.numerics import apply_requested
from missions.runtime.signals import Stopped, exit_status, raise_on_signals
from missions.runtime.threads import one_blas_thread

#: Each command name and the module that registers it, in the order ``fimnav --help`` lists them
#: (tests/missions/test_cli_parser.py checks it against what the modules register). A command
#: line naming one is parsed with that module's parser alone (:func:`build_parser`).
COMMANDS: dict[str, str] = {
    "vehicle": "missions.cli.vehicle",
    "check": "missions.cli.check",
    "schema": "missions.cli.check",
    "montecarlo": "missions.cli.montecarlo",
    "sweep": "missions.cli.sweep",
    "optimum": "missions.cli.optimum",
    "plan": "missions.cli.plan",
    "payload": "missions.cli.payload",
    "launch": "missions.cli.launch",
    "router": "missions.cli.router",
    "handback": "missions.cli.handback",
    "view": "missions.cli.view",
    "missions": "missions.cli.missions",
    "compile": "missions.cli.compile",
    "calibrate": "missions.cli.calibrate",
    "localize": "missions.cli.localize",
}

#: The subcommand modules, each once, in that order.
COMMAND_MODULES: tuple[str, ...] = tuple(dict.fromkeys(COMMANDS.values()))


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


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The argument parser with every subcommand registered; or, when ``argv``'s first word is
    a command's name (:data:`COMMANDS`), with that command's module alone. The parse of such a
    command line is the same either way, and the process imports no other command's module:
    about 50 ms of every planner a launch forks and of every vehicle's start (the other
    modules' imports), 5 s of CPU at the start of a 100-drone launch. ``fimnav``, ``fimnav
    --help`` or an unknown name get every command (to list them, or to name the choices)."""
    parser = argparse.ArgumentParser(
        prog="fimnav",
        description="Fly a drone swarm to localize a radio source (A/D-optimal Fisher navigation).",
    )
    parser.add_argument("--version", action=_VersionAction, help="print the installed fimnav version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    first = argv[0] if argv else None
    for name in (COMMANDS[first],) if first in COMMANDS else COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``fimnav`` with ``argv`` (default ``sys.argv[1:]``); return the exit status: 0, the
    command's error status (1, 2, 3), or 128 + the signal that ended it (SIGINT 130, SIGTERM
    143, SIGHUP 129; :mod:`missions.runtime.signals`)."""
    one_blas_thread(os.environ)  # before any subcommand's module imports numpy
    problem = apply_requested(os.environ)  # FIMNAV_NUMERICS=portable: the same bits on every x86-64 machine
    if problem:
        print(f"fimnav: error: {problem}", file=sys.stderr)
        return 2
    words = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(words)
    args = parser.parse_args(words)
    try:
        with raise_on_signals(args.command):
            return int(args.func(args) or 0)
    except FimnavError as exc:
        # An interruption (exit status 128 + signal, e.g. fimnav launch's) is not an error.
        label = "" if exc.exit_code >= 128 else "error: "
        print(f"fimnav {args.command}: {label}{exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"fimnav {args.command}: interrupted by SIGINT", file=sys.stderr)
        return exit_status(signal.SIGINT)
    except Stopped as exc:
        print(f"fimnav {args.command}: stopped by {exc}", file=sys.stderr)
        return exit_status(exc.signum)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

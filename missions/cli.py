"""The ``fimnav`` command line: one entry point, one subcommand module each.

Each subcommand lives in its own module exposing ``register(subparsers) -> None``; the
module adds its parser and sets ``func`` (``Callable[[argparse.Namespace], int]``).
Heavy imports (zenoh, matplotlib, pymavlink) happen inside ``func``, so ``fimnav --help``
stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from planner.errors import FimnavError

#: Subcommand modules, in the order ``fimnav --help`` lists them.
COMMAND_MODULES: tuple[str, ...] = (
    "missions.cmd_vehicle",
    "missions.cmd_check",
    "missions.cmd_montecarlo",
    "missions.cmd_plan",
    "missions.cmd_launch",
    "missions.cmd_router",
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand registered."""
    parser = argparse.ArgumentParser(
        prog="fimnav",
        description="Fly a drone swarm to localize a radio source (A/D-optimal Fisher navigation).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``fimnav`` with ``argv`` (default ``sys.argv[1:]``); return the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except FimnavError as exc:
        print(f"fimnav {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"fimnav {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

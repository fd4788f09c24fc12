"""Exceptions shared by every fimnav package.

They live in the planner core because every other package may import it (see
``docs/architecture.md``); they carry no I/O.
"""

from __future__ import annotations


class FimnavError(Exception):
    """An error meant for the user: the CLI prints its message (no traceback) and exits with
    :attr:`exit_code`."""

    exit_code: int = 1


class UsageError(FimnavError, ValueError):
    """Bad input from the user (a mission file, a command-line value). Exit status 2."""

    exit_code = 2

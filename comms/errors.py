"""Exceptions shared by every fimnav package but the math core.

Errors meant for the user, raised by the packages that read the user's input (mission files,
keys, command-line values, the network) and printed by the ``fimnav`` command line without a
traceback. They live in ``comms``, the lowest package with I/O, so ``vehicle_sim``, the planner
node and ``missions`` can raise them; the planner's math core raises plain ``ValueError``.
"""

from __future__ import annotations


class FimnavError(Exception):
    """An error meant for the user: the CLI prints its message (no traceback) and exits with
    :attr:`exit_code`."""

    exit_code: int = 1


class UsageError(FimnavError, ValueError):
    """Bad input from the user (a mission file, a command-line value). Exit status 2."""

    exit_code = 2

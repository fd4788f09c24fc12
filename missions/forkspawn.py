"""Start ``fimnav`` child processes from a fork server that has already imported them.

A planner process spends about 0.45 s of CPU importing numpy, pydantic, pymavlink and zenoh
before it does anything; the launcher starts N of them at once on a 2-core machine (10 drones:
~2 s of wall time, 100 drones: ~20 s). :class:`ForkServer` uses the standard library's
``multiprocessing`` fork server (``forkserver`` start method): one server process imports
:data:`PRELOAD` once, and each child is forked from it, already imported. Each child is
still a separate operating-system process, in its own session and process group (as with
``subprocess.Popen(start_new_session=True)``), with stdin from /dev/null and stdout and stderr
appended to its log file, and its process title set to the command line it runs
(``setproctitle``: ``ps`` and ``/proc/PID/cmdline`` show ``python -m missions plan ...``).

:class:`ForkedProcess` gives the launcher the part of ``subprocess.Popen`` it uses (``pid``,
``poll``, ``wait``, ``returncode``); exit statuses follow Popen's convention (−N: killed by
signal N).
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.forkserver
import os
import signal
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

#: Modules the fork server imports once: everything ``fimnav plan`` needs before it flies.
PRELOAD: tuple[str, ...] = (
    "numpy",
    "zenoh",
    "pymavlink.mavutil",
    "missions.loader",
    "missions.cmd_plan",
    "comms.mavlink_client",
    "comms.session",
    "planner.node",
)


def _run_cli(argv: list[str], log_path: str, title: str) -> None:
    """Fork-server child: become ``python -m missions ARGV`` with its output in ``log_path``."""
    os.setsid()  # own session and process group: the launcher signals the group
    fd = os.open(log_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.close(null)
    for stream in (sys.stdout, sys.stderr):
        if stream is not None and hasattr(stream, "reconfigure"):
            stream.reconfigure(write_through=True, line_buffering=True)
    # A process started by the launcher with Popen gets the default dispositions.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    import setproctitle

    setproctitle.setproctitle(title)
    from missions.cli import main

    sys.exit(main(argv))


class ForkedProcess:
    """``subprocess.Popen``'s ``pid``, ``poll``, ``wait`` and ``returncode`` for a fork-server
    child (the launcher is not its parent: its exit status comes through the fork server)."""

    def __init__(self, process: Any, args: Sequence[str]) -> None:
        self._p = process
        self.args = list(args)
        self.pid: int = process.pid

    @property
    def returncode(self) -> int | None:
        return self._p.exitcode  # type: ignore[no-any-return]

    def poll(self) -> int | None:
        """The exit status, or None while it runs."""
        return self._p.exitcode  # type: ignore[no-any-return]

    def wait(self, timeout: float | None = None) -> int:
        """Wait for the exit (at most ``timeout`` s); ``subprocess.TimeoutExpired`` after it."""
        self._p.join(timeout)
        code = self._p.exitcode
        if code is None:
            raise subprocess.TimeoutExpired(self.args, timeout if timeout is not None else 0.0)
        return int(code)


class ForkServer:
    """Starts ``python -m missions ARGS`` children from a pre-imported fork server.

    :meth:`warm_up` starts the server (it imports :data:`PRELOAD` while the caller does other
    work); :meth:`spawn` forks one child. The server ends with the process that created it.
    """

    def __init__(self, python: str = sys.executable) -> None:
        self.ctx = multiprocessing.get_context("forkserver")
        self.python = python
        self.ctx.set_forkserver_preload(list(PRELOAD))

    def warm_up(self) -> None:
        """Start the fork server now (it imports the preload in the background)."""
        multiprocessing.forkserver.ensure_running()

    def spawn(self, args: Sequence[str], log_path: Path) -> ForkedProcess:
        """Fork ``python -m missions ARGS`` with stdout/stderr appended to ``log_path``."""
        title = " ".join([self.python, "-m", "missions", *args])
        p = self.ctx.Process(target=_run_cli, args=(list(args), str(log_path), title), daemon=True)
        p.start()
        return ForkedProcess(p, [self.python, "-m", "missions", *args])

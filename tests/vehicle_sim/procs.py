"""Real subprocesses for the integration tests: own session (process group), output collected
by reader threads, waits on output patterns with deadlines, the whole group killed at the end."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

ENV = dict(os.environ, MAVLINK20="1", PYTHONUNBUFFERED="1")

#: MAVProxy's script: the [test] extra installs it beside this interpreter; PATH may name another
#: installation first.
MAVPROXY = shutil.which("mavproxy.py", path=str(Path(sys.executable).parent)) or shutil.which("mavproxy.py") or "mavproxy.py"


class Proc:
    """A process in its own session with stdout/stderr accumulated in memory."""

    def __init__(self, argv: Sequence[str], stdin: bool = False, cwd: str | None = None) -> None:
        self.argv = list(argv)
        self.p = subprocess.Popen(
            self.argv,
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            start_new_session=True,
            env=ENV,
            cwd=cwd,
        )
        self.out = ""
        self.err = ""
        self._pos = 0
        self._lock = threading.Lock()
        self._threads = [
            threading.Thread(target=self._pump, args=(self.p.stdout, "out"), daemon=True),
            threading.Thread(target=self._pump, args=(self.p.stderr, "err"), daemon=True),
        ]
        for t in self._threads:
            t.start()

    def _pump(self, stream, name: str) -> None:
        fd = stream.fileno()
        while True:
            try:
                chunk = os.read(fd, 65536)
            except OSError:
                return
            if not chunk:
                return
            with self._lock:
                setattr(self, name, getattr(self, name) + chunk.decode("utf-8", errors="replace"))

    def expect(self, pattern: str, timeout: float = 20.0) -> re.Match[str]:
        """Wait until ``pattern`` (regex) appears in stdout after the last match."""
        rx = re.compile(pattern)
        deadline = time.monotonic() + timeout
        while True:
            with self._lock:
                m = rx.search(self.out, self._pos)
                if m:
                    self._pos = m.end()
                    return m
            if self.p.poll() is not None and time.monotonic() > deadline - timeout + 0.5:
                with self._lock:
                    m = rx.search(self.out, self._pos)
                if m:
                    return m
                raise AssertionError(f"{self.argv[0]} exited ({self.p.returncode}) before {pattern!r}:\n{self.out[-3000:]}\n{self.err[-3000:]}")
            if time.monotonic() > deadline:
                raise AssertionError(f"{pattern!r} not seen within {timeout} s:\n{self.out[-3000:]}\n{self.err[-2000:]}")
            time.sleep(0.02)

    def send(self, line: str) -> None:
        assert self.p.stdin is not None
        self.p.stdin.write((line + "\n").encode())
        self.p.stdin.flush()

    def wait(self, timeout: float = 20.0) -> int:
        rc = self.p.wait(timeout)
        for t in self._threads:
            t.join(2)
        return rc

    def kill(self) -> None:
        """SIGTERM the process group (its id is the pid: own session), wait, then SIGKILL it."""
        pgid = self.p.pid
        for sig, grace_s in ((signal.SIGTERM, 3.0), (signal.SIGKILL, 3.0)):
            try:
                os.killpg(pgid, sig)
            except ProcessLookupError:
                break  # no process of the group is left
            try:
                self.p.wait(grace_s)
            except subprocess.TimeoutExpired:
                pass
        for stream in (self.p.stdin, self.p.stdout, self.p.stderr):
            if stream is not None:
                try:
                    stream.close()
                except OSError:
                    pass


def fimnav(*args: str) -> list[str]:
    """argv of ``fimnav`` through the interpreter under test."""
    return [sys.executable, "-m", "missions.cli", *args]

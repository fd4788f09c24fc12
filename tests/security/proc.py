"""A ``fimnav vehicle`` subprocess for the security tests: own session, output collected,
the ready line awaited with a deadline, the whole process group killed at the end."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
ENV = dict(os.environ, MAVLINK20="1", PYTHONUNBUFFERED="1")


class Fimnav:
    """``python -m missions ARGS`` in its own process group."""

    def __init__(self, args: Sequence[str]) -> None:
        self.p = subprocess.Popen(
            [sys.executable, "-m", "missions", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            stdin=subprocess.DEVNULL, start_new_session=True, env=ENV, cwd=ROOT,
        )
        self.out = b""
        self.err = b""
        self._lock = threading.Lock()
        self._threads = [threading.Thread(target=self._pump, args=(s, n), daemon=True) for s, n in ((self.p.stdout, "out"), (self.p.stderr, "err"))]
        for t in self._threads:
            t.start()

    def _pump(self, stream, name: str) -> None:  # noqa: ANN001
        while chunk := os.read(stream.fileno(), 65536):
            with self._lock:
                setattr(self, name, getattr(self, name) + chunk)

    def ready(self, timeout_s: float = 30.0) -> dict:
        """The ``{"event": "ready", ...}`` line of ``fimnav vehicle``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                for line in self.out.decode(errors="replace").splitlines():
                    if line.startswith("{") and '"ready"' in line:
                        return json.loads(line)
            if self.p.poll() is not None:
                break
            time.sleep(0.02)  # polling interval of a deadline wait
        raise AssertionError(f"no ready line within {timeout_s} s (exit {self.p.poll()}):\n{self.err.decode(errors='replace')[-2000:]}")

    def wait(self, timeout_s: float = 30.0) -> int:
        try:
            code = self.p.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.kill()
            raise
        for t in self._threads:
            t.join(5)
        return code

    def stop(self) -> int:
        """SIGINT, then wait (killed after a deadline)."""
        if self.p.poll() is None:
            try:
                os.killpg(self.p.pid, signal.SIGINT)
            except ProcessLookupError:
                pass
        try:
            return self.wait(20)
        finally:
            self.kill()

    def kill(self) -> None:
        try:
            os.killpg(self.p.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        self.p.wait(10)

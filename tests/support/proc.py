"""Real subprocesses for the tests: each in its own session (its own process group), stdout and
stderr gathered by reader threads, waits on their output with deadlines, and the whole group
stopped at the end (SIGTERM, then SIGKILL)."""

from __future__ import annotations

import codecs
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import IO, Any

#: The environment of a :class:`Proc`: MAVLink 2 for pymavlink, unbuffered Python output.
ENV = dict(os.environ, MAVLINK20="1", PYTHONUNBUFFERED="1")

#: MAVProxy's script: the [test] extra installs it beside this interpreter; PATH may name another
#: installation first.
MAVPROXY = shutil.which("mavproxy.py", path=str(Path(sys.executable).parent)) or shutil.which("mavproxy.py") or "mavproxy.py"

_STREAMS = ("out", "err")


def fimnav(*args: str) -> list[str]:
    """argv of ``fimnav ARGS`` run by the interpreter under test (``python -m missions ARGS``)."""
    return [sys.executable, "-m", "missions", *args]


def stop_group(p: subprocess.Popen[bytes], sig: int = signal.SIGTERM, grace_s: float = 5.0) -> int | None:
    """Send ``sig`` to the process group of ``p`` (started in its own session), give ``p`` up to
    ``grace_s`` to exit, then SIGKILL whatever is left of the group; ``p``'s exit status."""
    for s in (sig, signal.SIGKILL):
        try:
            os.killpg(p.pid, s)
        except (ProcessLookupError, PermissionError):
            break  # nothing of the group is left
        try:
            p.wait(grace_s)
        except subprocess.TimeoutExpired:
            pass
    return p.poll()


def child_pids(pid: int) -> set[int]:
    """The direct children of ``pid`` (Linux /proc)."""
    out: set[int] = set()
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out.update(int(c) for c in (task / "children").read_text().split())
        except OSError:
            continue
    return out


def alive(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie (Linux /proc)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def with_signal(argv: Sequence[str], name: str, disposition: str) -> list[str]:
    """``argv`` run with signal ``name`` (e.g. "SIGHUP") set to ``disposition`` ("SIG_DFL" or
    "SIG_IGN") and unblocked, which exec keeps."""
    code = (
        f"import os, signal, sys; signal.signal(signal.{name}, signal.{disposition}); "
        f"signal.pthread_sigmask(signal.SIG_UNBLOCK, [signal.{name}]); os.execvp(sys.argv[1], sys.argv[1:])"
    )
    return [sys.executable, "-c", code, *argv]


def with_hangup(argv: Sequence[str], disposition: str) -> list[str]:
    """``argv`` run with SIGHUP set to ``disposition`` ("SIG_DFL" or "SIG_IGN"), which exec keeps."""
    return with_signal(argv, "SIGHUP", disposition)


def with_default_hangup(argv: Sequence[str]) -> list[str]:
    """``argv`` as started from a terminal: with SIGHUP at its default action even when the suite
    itself runs with it ignored (``nohup pytest``, which every child would inherit, and which
    fimnav honours on purpose: ``nohup fimnav launch`` outlives its terminal)."""
    if signal.getsignal(signal.SIGHUP) != signal.SIG_IGN:
        return list(argv)
    return with_hangup(argv, "SIG_DFL")


def with_default_interrupt(argv: Sequence[str]) -> list[str]:
    """``argv`` as started from a terminal: with SIGINT at its default action and unblocked,
    whatever this process has (exec keeps an ignored or blocked signal, and the process that
    runs the suite, e.g. a pytest-xdist worker, can have SIGINT ignored)."""
    return with_signal(argv, "SIGINT", "SIG_DFL")


class Proc:
    """``argv`` in its own session, its output gathered in memory by two reader threads.

    ``stdin=True`` gives it a pipe to :meth:`send` lines to; ``env=None`` passes this process's
    environment unchanged (default: :data:`ENV`).
    """

    def __init__(self, argv: Sequence[str], *, cwd: str | Path | None = None, stdin: bool = False,
                 env: Mapping[str, str] | None = ENV) -> None:
        self.argv = list(argv)
        self.p = subprocess.Popen(
            with_default_hangup(self.argv), stdin=subprocess.PIPE if stdin else subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            start_new_session=True, env=env, cwd=cwd,
        )
        self._lock = threading.Lock()
        self._raw = {name: bytearray() for name in _STREAMS}
        self._text = dict.fromkeys(_STREAMS, "")
        self._next = dict.fromkeys(_STREAMS, 0)  # where expect_next searches from
        self._readers = [threading.Thread(target=self._pump, args=(stream, name), daemon=True)
                         for name, stream in zip(_STREAMS, (self.p.stdout, self.p.stderr))]
        for t in self._readers:
            t.start()

    def _pump(self, stream: IO[bytes], name: str) -> None:
        decoder = codecs.getincrementaldecoder("utf-8")(errors="replace")
        fd = stream.fileno()
        try:
            while True:
                try:
                    chunk = os.read(fd, 65536)
                except OSError:
                    return
                with self._lock:
                    self._raw[name] += chunk
                    self._text[name] += decoder.decode(chunk, final=not chunk)
                if not chunk:
                    return
        finally:
            stream.close()

    # -- what it wrote ----------------------------------------------------------------------------

    @property
    def label(self) -> str:
        """The command and its first arguments, for messages (``vehicle --mission m.yaml``)."""
        words = self.argv[3:] if self.argv[1:2] == ["-m"] else [Path(self.argv[0]).name, *self.argv[1:]]
        return " ".join(words[:3])

    @property
    def out(self) -> str:
        """Its stdout so far (UTF-8, undecodable bytes replaced)."""
        with self._lock:
            return self._text["out"]

    @property
    def err(self) -> str:
        """Its stderr so far (UTF-8, undecodable bytes replaced)."""
        with self._lock:
            return self._text["err"]

    @property
    def out_bytes(self) -> bytes:
        """Its stdout so far, as written."""
        with self._lock:
            return bytes(self._raw["out"])

    @property
    def err_bytes(self) -> bytes:
        """Its stderr so far, as written."""
        with self._lock:
            return bytes(self._raw["err"])

    def tail(self, chars: int = 4000) -> str:
        """The last ``chars`` characters of stdout and of stderr, for failure messages."""
        return f"--- stdout\n{self.out[-chars:]}\n--- stderr\n{self.err[-chars:]}"

    def join_output(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for both streams to end (every writer closed them); True if they did."""
        deadline = time.monotonic() + timeout_s
        for t in self._readers:
            t.join(max(deadline - time.monotonic(), 0.0))
        return not any(t.is_alive() for t in self._readers)

    # -- waits on its output ----------------------------------------------------------------------

    def expect(self, pattern: str, timeout_s: float = 20.0, stream: str = "out") -> re.Match[str]:
        """The first match of the regex ``pattern`` in ``stream`` (``"out"`` or ``"err"``), waiting
        up to ``timeout_s`` for it; fails with the output if the process exits first."""
        return self._await(re.compile(pattern), timeout_s, stream, 0)

    def expect_next(self, pattern: str, timeout_s: float = 20.0, stream: str = "out") -> re.Match[str]:
        """As :meth:`expect`, but the match must start after the previous :meth:`expect_next`
        match in ``stream`` (output read as a dialogue: a prompt, an answer, the next prompt)."""
        m = self._await(re.compile(pattern), timeout_s, stream, self._next[stream])
        self._next[stream] = m.end()
        return m

    def ready(self, timeout_s: float = 30.0) -> dict[str, Any]:
        """The ``{"event": "ready", ...}`` line of a fimnav ``vehicle``, ``router`` or ``payload``."""
        return dict(json.loads(self.expect(r"\{\"event\": \"ready\".*\}\n", timeout_s).group(0)))

    def _await(self, rx: re.Pattern[str], timeout_s: float, stream: str, start: int) -> re.Match[str]:
        if stream not in _STREAMS:
            raise ValueError(f"stream must be 'out' or 'err', not {stream!r}")
        deadline = time.monotonic() + timeout_s
        while True:
            with self._lock:
                m = rx.search(self._text[stream], start)
            if m:
                return m
            if self.p.poll() is not None:
                self.join_output(5.0)  # what it wrote before it exited
                with self._lock:
                    m = rx.search(self._text[stream], start)
                if m:
                    return m
                raise AssertionError(f"{self.label} exited {self.p.returncode} before {rx.pattern!r}:\n{self.tail()}")
            if time.monotonic() > deadline:
                raise AssertionError(f"{rx.pattern!r} not seen within {timeout_s:g} s:\n{self.tail()}")
            time.sleep(0.02)  # polling interval of a deadline wait

    # -- input, signals, end ----------------------------------------------------------------------

    def send(self, line: str) -> None:
        """Write ``line`` and a newline to its stdin (started with ``stdin=True``)."""
        assert self.p.stdin is not None, "started without stdin=True"
        self.p.stdin.write((line + "\n").encode())
        self.p.stdin.flush()

    def close_stdin(self) -> None:
        """End its input (end of file on its stdin)."""
        if self.p.stdin is not None and not self.p.stdin.closed:
            self.p.stdin.close()

    def send_signal(self, sig: int) -> None:
        """Send ``sig`` to its process group (nothing if no process of the group is left)."""
        try:
            os.killpg(self.p.pid, sig)
        except (ProcessLookupError, PermissionError):
            pass

    def wait(self, timeout_s: float = 20.0) -> int:
        """Its exit status, waiting up to ``timeout_s`` (then AssertionError with its output), and
        up to 5 s more for the rest of its output."""
        try:
            code = self.p.wait(timeout_s)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"{self.label} still running after {timeout_s:g} s:\n{self.tail()}") from None
        self.join_output(5.0)
        return code

    def stop(self, sig: int = signal.SIGTERM, grace_s: float = 5.0) -> int | None:
        """``sig`` (SIGTERM) to its process group, up to ``grace_s`` to exit, then SIGKILL to what
        is left of the group; its exit status. Does nothing more once the group is gone."""
        code = stop_group(self.p, sig, grace_s)
        if self.p.stdin is not None:
            try:
                self.p.stdin.close()
            except OSError:
                pass  # (a broken pipe on the flush of unread input)
        self.join_output(2.0)
        return code


def stop_all(procs: Iterable[Proc], grace_s: float = 5.0) -> None:
    """Stop every process group at once: SIGTERM to all, up to ``grace_s`` for all to exit, then
    :meth:`Proc.stop` (SIGKILL) for whatever lingers."""
    procs = list(procs)
    for p in procs:
        if p.p.poll() is None:
            p.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    for p in procs:
        try:
            p.p.wait(max(deadline - time.monotonic(), 0.01))
        except subprocess.TimeoutExpired:
            pass
    for p in procs:
        p.stop()

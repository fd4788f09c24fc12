"""Start and stop real ArduPilot SITL (copter) for tests, on free ports, in a scratch directory.

The binary and its defaults file come from the environment (nothing of ArduPilot is in this
repository):

* ``FIMNAV_SITL_ARDUCOPTER``: the ``arducopter`` SITL binary;
* ``FIMNAV_SITL_ARDUCOPTER_DEFAULTS``: its defaults file (``Tools/autotest/default_params/copter.parm``).

:func:`sitl_config` reads them (None, with the reason, when unset); :func:`start_sitl` starts one
instance (``with start_sitl(cfg, workdir) as sitl: ... sitl.address``) and stops it and its
process group whatever happens. SITL's TCP ports bind every interface; clients connect to
127.0.0.1 only. Each instance gets its own free SERIAL0 TCP port (``--serial0 tcp:PORT:wait``),
its own free RC-input UDP port (``--rc-in-port``), SERIAL1/2 switched off (``none``), its own
working directory (eeprom.bin, logs), and ``--sysid``.
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from tests.support.net import free_port
from tests.support.proc import stop_group

ENV_BINARY = "FIMNAV_SITL_ARDUCOPTER"
ENV_DEFAULTS = "FIMNAV_SITL_ARDUCOPTER_DEFAULTS"
#: ArduPilot's CMAC test field, fimnav's default origin (lat, lon, alt AMSL m, heading deg).
CMAC_HOME = "-35.363261,149.165230,584,353"


@dataclass(frozen=True)
class SitlConfig:
    """Where SITL is: the ``arducopter`` binary and its defaults (parameter) file."""

    binary: Path
    defaults: Path


def sitl_config() -> tuple[SitlConfig | None, str]:
    """The SITL configuration from the environment, or (None, a one-line reason to skip)."""
    b, d = os.environ.get(ENV_BINARY), os.environ.get(ENV_DEFAULTS)
    if not b or not d:
        return None, f"needs real ArduPilot SITL: set {ENV_BINARY} and {ENV_DEFAULTS}"
    binary, defaults = Path(b), Path(d)
    if not (binary.is_file() and os.access(binary, os.X_OK)):
        return None, f"{ENV_BINARY}={b} is not an executable file"
    if not defaults.is_file():
        return None, f"{ENV_DEFAULTS}={d} is not a file"
    return SitlConfig(binary, defaults), ""


def console_tail(path: Path, n: int = 3000) -> str:
    """The last ``n`` characters of a simulator's console log ("" when there is none)."""
    try:
        return path.read_text(errors="replace")[-n:]
    except OSError:
        return ""


@dataclass
class SitlInstance:
    """A running SITL: its process, its SERIAL0 address (``tcp:127.0.0.1:PORT``), its speed-up,
    its working directory and console log."""

    proc: subprocess.Popen[bytes]
    address: str
    port: int
    speedup: float
    workdir: Path
    log_path: Path
    argv: list[str]

    def log_tail(self, n: int = 3000) -> str:
        """The end of SITL's console output (for failure messages)."""
        return console_tail(self.log_path, n)

    def stop(self, grace_s: float = 5.0) -> None:
        """SIGTERM the process group, then SIGKILL it if still there; wait for the process."""
        stop_group(self.proc, grace_s=grace_s)


def wait_for_bind(inst: SitlInstance, deadline_s: float) -> None:
    """Wait until SITL says it listens on its SERIAL0 port (its console line ``bind port PORT
    for SERIAL0``), or raise RuntimeError when it exits or the deadline passes."""
    end = time.monotonic() + deadline_s
    needle = f"bind port {inst.port} for SERIAL0"
    while True:
        text = inst.log_tail(200_000)
        if needle in text and "Waiting for connection" in text:
            return
        if inst.proc.poll() is not None:
            raise RuntimeError(f"SITL exited ({inst.proc.returncode}) before listening on {inst.port}:\n{inst.log_tail()}")
        if time.monotonic() > end:
            raise RuntimeError(f"SITL did not listen on {inst.port} within {deadline_s} s:\n{inst.log_tail()}")
        time.sleep(0.05)  # polling SITL's log, with the deadline above


@contextlib.contextmanager
def start_sitl(cfg: SitlConfig, workdir: Path, *, speedup: float = 10.0, home: str = CMAC_HOME,
               sysid: int = 1, model: str = "+", attempts: int = 3, deadline_s: float = 20.0) -> Iterator[SitlInstance]:
    """Start one SITL copter in ``workdir`` (created; wiped with ``-w``) on free ports and wait
    until it listens; stop it and its process group on exit, whatever happens.

    SITL waits for a connection on SERIAL0 before it boots (the caller connects to
    ``instance.address``), and exits when its parent (this process) dies. A port taken between
    choosing and binding (SITL then exits) is retried with new ports ``attempts`` times.
    """
    workdir.mkdir(parents=True, exist_ok=True)
    inst: SitlInstance | None = None
    try:
        for attempt in range(attempts):
            port, rc_port = free_port(host="0.0.0.0"), free_port(socket.SOCK_DGRAM, host="0.0.0.0")  # SITL binds every interface
            argv = [str(cfg.binary), "--model", model, "--speedup", f"{speedup:g}", "--defaults", str(cfg.defaults),
                    "--home", home, "--sysid", str(sysid), "-w",
                    "--serial0", f"tcp:{port}:wait", "--serial1", "none:", "--serial2", "none:", "--rc-in-port", str(rc_port)]
            log_path = workdir / f"sitl-console-{attempt}.log"
            with open(log_path, "wb") as out:
                proc = subprocess.Popen(argv, cwd=workdir, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
                                        start_new_session=True)
            inst = SitlInstance(proc, f"tcp:127.0.0.1:{port}", port, speedup, workdir, log_path, argv)
            try:
                wait_for_bind(inst, deadline_s)
                break
            except RuntimeError:
                inst.stop()
                if attempt == attempts - 1:
                    raise
                inst = None
        assert inst is not None
        yield inst
    finally:
        if inst is not None:
            inst.stop()

"""Start and stop real PX4 SITL instances with the headless SIH quadrotor for tests.

The binary and its ROMFS ``etc`` directory come from the environment (nothing of PX4 is in
this repository):

* ``FIMNAV_SITL_PX4``: the ``px4`` SITL binary (``build/px4_sitl_default/bin/px4``);
* ``FIMNAV_SITL_PX4_ETC``: its ``etc`` directory (``build/px4_sitl_default/etc``).

:func:`px4_config` reads them (None, with the reason, when unset); :func:`start_px4` starts one
instance (``with start_px4(cfg, workdir, home=...) as px4: ... px4.offboard``) and stops it
and its process group whatever happens.

PX4's ports are fixed per instance number ``N`` (``-i N``, system id N + 1): the offboard/API
link (MAVLink "Onboard" mode) binds UDP 14580+N and sends to 127.0.0.1:14540+N; the GCS link
binds 18570+N and sends to 127.0.0.1:14550 (the same for every instance); the payload link
binds 14280+N (-> 14030+N), the gimbal link 13030+N (-> 13280+N), the SIH display link
19450+N (-> 19410+N, ground truth). An instance number is chosen whose ports (both ends) are
free and whose server lock ``/tmp/px4_lock-N`` is not held. PX4 binds 0.0.0.0 but sends to
127.0.0.1 only; clients use 127.0.0.1.

Home: SIH takes ``PX4_HOME_LAT`` / ``PX4_HOME_LON`` as integer degrees × 1e7 (decimal degrees
are truncated to whole degrees) and its ground altitude from the parameter ``SIH_LOC_H0`` (m
AMSL), which is set by a ``px4-rc.params`` boot hook written into the instance's own directory
and put first in PATH (PX4's rcS sources the first ``px4-rc.params`` on PATH).
``PX4_SIM_SPEED_FACTOR`` is always given (1 too): rcS then sets COM_OF_LOSS_T = 0.5·F,
COM_DL_LOSS_T = 10·F, COM_RC_LOSS_T = 0.5·F, COM_OBC_LOSS_T = 5·F (sim seconds) and saves them
in the working directory's parameters.bson; every instance gets a fresh working directory.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import socket
import subprocess
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

from tests.sitl.sitl import console_tail
from tests.support.proc import stop_group

ENV_BINARY = "FIMNAV_SITL_PX4"
ENV_ETC = "FIMNAV_SITL_PX4_ETC"
#: PX4's SIH quadrotor airframe (ROMFS ``init.d-posix/airframes/10040_sihsim_quadx``).
SIH_AIRFRAME = 10040
#: UDP ports PX4 instance N binds (add N): GCS, offboard/API, payload, gimbal, SIH display.
LOCAL_PORTS = (18570, 14580, 14280, 13030, 19450)
#: UDP ports PX4 instance N sends to (add N): offboard/API, payload, gimbal, SIH display.
REMOTE_PORTS = (14540, 14030, 13280, 19410)


@dataclass(frozen=True)
class Px4Config:
    """Where PX4 SITL is: the ``px4`` binary and its ROMFS ``etc`` directory."""

    binary: Path
    etc: Path


def px4_config() -> tuple[Px4Config | None, str]:
    """The PX4 SITL configuration from the environment, or (None, a one-line reason to skip)."""
    b, e = os.environ.get(ENV_BINARY), os.environ.get(ENV_ETC)
    if not b or not e:
        return None, f"needs real PX4 SITL (SIH): set {ENV_BINARY} and {ENV_ETC}"
    binary, etc = Path(b), Path(e)
    if not (binary.is_file() and os.access(binary, os.X_OK)):
        return None, f"{ENV_BINARY}={b} is not an executable file"
    if not (etc / "init.d-posix" / "rcS").is_file():
        return None, f"{ENV_ETC}={e} has no init.d-posix/rcS (expected build/px4_sitl_default/etc)"
    return Px4Config(binary, etc), ""


def _udp_free(port: int) -> bool:
    """True when UDP ``port`` can be bound on every interface (PX4 binds 0.0.0.0)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True


def _lock_free(instance: int) -> bool:
    """True when no PX4 server holds ``/tmp/px4_lock-N`` (PX4 takes a POSIX write lock on it)."""
    path = f"/tmp/px4_lock-{instance}"
    if not os.path.exists(path):
        return True
    try:
        fd = os.open(path, os.O_RDWR)
    except OSError:
        return False
    try:
        fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        fcntl.lockf(fd, fcntl.LOCK_UN)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)


def free_instance(exclude: frozenset[int] = frozenset(), first: int = 0, last: int = 9) -> int:
    """The lowest PX4 instance number in [first, last] (not in ``exclude``) whose UDP ports are
    all free and whose server lock is not held. Instances above 9 send their offboard link to
    14549 (shared), so they are not used. Raises RuntimeError when none is free."""
    for n in range(first, last + 1):
        if n in exclude:
            continue
        if _lock_free(n) and all(_udp_free(p + n) for p in (*LOCAL_PORTS, *REMOTE_PORTS)):
            return n
    raise RuntimeError(f"no PX4 instance number in {first}..{last} has its UDP ports free")


def e7(deg: float) -> int:
    """Degrees as PX4's SIH_LOC_LAT0/LON0 integers (degrees × 1e7, rounded)."""
    return int(round(deg * 1e7))


@dataclass
class Px4Instance:
    """A running PX4 SITL: its process, instance number, system id, speed factor, working
    directory and console log."""

    proc: subprocess.Popen[bytes]
    instance: int
    sysid: int
    speed: float
    workdir: Path
    log_path: Path
    argv: list[str]

    @property
    def offboard_port(self) -> int:
        """The UDP port PX4's offboard/API link sends to (bind it: ``udpin:127.0.0.1:PORT``)."""
        return 14540 + self.instance

    @property
    def offboard(self) -> str:
        """The planner's connection string for the offboard/API link."""
        return f"udpin:127.0.0.1:{self.offboard_port}"

    @property
    def gcs(self) -> str:
        """A second MAVLink link to the same PX4 (its GCS link's own port, 18570+N): a client
        sends to it first (``udpout:``) and PX4 answers to that address."""
        return f"udpout:127.0.0.1:{18570 + self.instance}"

    @property
    def truth_port(self) -> int:
        """The UDP port the SIH display link sends ground truth (HIL_STATE_QUATERNION) to."""
        return 19410 + self.instance

    def log_tail(self, n: int = 3000) -> str:
        """The end of PX4's console output (for failure messages)."""
        return console_tail(self.log_path, n)

    def stop(self, grace_s: float = 5.0) -> None:
        """SIGTERM the process group ("PX4 Exiting..."), then SIGKILL it if still there; wait."""
        stop_group(self.proc, grace_s=grace_s)


def wait_for_startup(inst: Px4Instance, deadline_s: float) -> None:
    """Wait until PX4's console says ``Startup script returned successfully`` (every MAVLink
    port is open then), or raise RuntimeError when it exits or the deadline (wall s) passes."""
    end = time.monotonic() + deadline_s
    while True:
        text = inst.log_tail(200_000)
        if "Startup script returned successfully" in text:
            return
        if "ERROR [px4] Startup script returned with return value" in text or inst.proc.poll() is not None:
            raise RuntimeError(f"PX4 instance {inst.instance} failed to start ({inst.proc.poll()}):\n{inst.log_tail()}")
        if time.monotonic() > end:
            raise RuntimeError(f"PX4 instance {inst.instance} did not start within {deadline_s} s:\n{inst.log_tail()}")
        time.sleep(0.05)  # polling PX4's console log, with the deadline above


def params_hook(directory: Path, params: Mapping[str, float | int]) -> Path:
    """Write a ``px4-rc.params`` boot hook (``param set NAME VALUE`` lines) into ``directory``
    (created) and return the directory, to be put first in PX4's PATH."""
    directory.mkdir(parents=True, exist_ok=True)
    lines = ["#!/bin/sh", "# fimnav test hook: sourced by PX4's rcS (first px4-rc.params on PATH)"]
    lines += [f"param set {name} {value:g}" if isinstance(value, float) else f"param set {name} {value}"
              for name, value in params.items()]
    hook = directory / "px4-rc.params"
    hook.write_text("\n".join(lines) + "\n")
    hook.chmod(0o755)
    return directory


@contextlib.contextmanager
def start_px4(cfg: Px4Config, workdir: Path, *, home: tuple[float, float, float], speed: float = 1.0,
              sysid: int | None = None, params: Mapping[str, float | int] | None = None, exclude: frozenset[int] = frozenset(),
              attempts: int = 3, deadline_s: float = 30.0) -> Iterator[Px4Instance]:
    """Start one headless PX4 SIH quadrotor in a fresh ``workdir`` (must not hold a previous
    run's parameters.bson) and wait until its startup script has run; stop it and its process
    group on exit, whatever happens.

    home: (latitude deg, longitude deg, ground altitude m AMSL) of the simulated vehicle's
    start; speed: PX4_SIM_SPEED_FACTOR (sim seconds per wall second); sysid: MAV_SYS_ID
    (default: PX4's instance + 1, whatever instance number is free); params: extra
    parameters set at boot (PX4 names and units); exclude: instance numbers not to use (ones
    another instance of the same test is about to take). A start that fails (ports taken
    between the check and PX4's bind) is retried with another instance number.
    """
    if (workdir / "parameters.bson").exists():
        raise ValueError(f"{workdir} holds a previous PX4 run's parameters.bson: give a fresh directory")
    workdir.mkdir(parents=True, exist_ok=True)
    lat, lon, alt = home
    boot: dict[str, float | int] = {"SIH_LOC_H0": float(alt), **(params or {})}
    if sysid is not None:
        boot["MAV_SYS_ID"] = int(sysid)
    hook = params_hook(workdir / "hook", boot)
    inst: Px4Instance | None = None
    tried: set[int] = set(exclude)
    try:
        for attempt in range(attempts):
            n = free_instance(frozenset(tried))
            tried.add(n)
            run = workdir / f"run{attempt}"
            run.mkdir()
            env = dict(os.environ, PX4_SYS_AUTOSTART=str(SIH_AIRFRAME), PX4_SIMULATOR="sihsim", PX4_SIM_MODEL="sihsim_quadx",
                       PX4_SIM_SPEED_FACTOR=f"{speed:g}", PX4_HOME_LAT=str(e7(lat)), PX4_HOME_LON=str(e7(lon)),
                       PATH=f"{hook}{os.pathsep}{os.environ.get('PATH', '')}")
            argv = [str(cfg.binary), "-d", "-i", str(n), "-w", str(run), str(cfg.etc)]
            log_path = workdir / f"px4-console-{attempt}.log"
            with open(log_path, "wb") as out:
                proc = subprocess.Popen(argv, cwd=run, env=env, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
                                        start_new_session=True)
            inst = Px4Instance(proc, n, sysid if sysid is not None else n + 1, speed, run, log_path, argv)
            try:
                wait_for_startup(inst, deadline_s)
                break
            except RuntimeError:
                inst.stop()
                inst = None
                if attempt == attempts - 1:
                    raise
        assert inst is not None
        yield inst
    finally:
        if inst is not None:
            inst.stop()

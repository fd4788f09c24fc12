"""A real Dask cluster on loopback for the tests: ``dask scheduler`` and ``dask worker``
processes (no nanny, one thread each, no dashboard) on free ports of 127.0.0.1.

Each process is a :class:`tests.support.proc.Proc` (its own session, stopped by the ``procs``
fixture) and is also killed by the kernel when the test process dies, whatever ends it
(SIGKILL included: ``prctl(PR_SET_PDEATHSIG, SIGKILL)`` before exec, :func:`orphan_proof`)."""

from __future__ import annotations

import signal
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from tests.support.net import free_port
from tests.support.proc import Proc
from tests.support.wait import wait_for

#: prctl option: the signal this process gets when its parent dies (linux/prctl.h).
PR_SET_PDEATHSIG = 1


def orphan_proof(argv: Sequence[str]) -> list[str]:
    """``argv`` run with SIGKILL as its parent-death signal: it dies with the process that
    started it (the parent's exit, by any signal, kills it), checked after the prctl too (the
    parent may have died before it)."""
    code = (
        "import ctypes, os, sys; parent = int(sys.argv[1]); "
        f"ctypes.CDLL(None, use_errno=True).prctl({PR_SET_PDEATHSIG}, {int(signal.SIGKILL)}, 0, 0, 0); "
        "os.getppid() == parent or os._exit(1); os.execvp(sys.argv[2], sys.argv[2:])"
    )
    import os

    return [sys.executable, "-c", code, str(os.getpid()), *argv]


@dataclass
class LoopbackCluster:
    """The processes of a loopback cluster: the scheduler's address, its process, and each
    worker's process by the worker's address (``tcp://127.0.0.1:PORT``)."""

    address: str
    scheduler: Proc
    workers: dict[str, Proc]


def start_cluster(procs: list[Proc], workers: int = 2, timeout_s: float = 60.0) -> LoopbackCluster:
    """Start a scheduler and ``workers`` workers (added to ``procs``); return when the scheduler
    counts every worker."""
    from distributed import Client

    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    dask = [sys.executable, "-m", "dask"]
    scheduler = Proc(orphan_proof([*dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"]))
    procs.append(scheduler)
    scheduler.expect(r"Scheduler at:\s+tcp://127\.0\.0\.1:\d+", timeout_s, stream="err")
    started: dict[str, Proc] = {}
    for n in range(workers):
        wport = free_port()
        argv = [*dask, "worker", address, "--host", "127.0.0.1", "--worker-port", str(wport), "--no-nanny", "--nthreads", "1", "--no-dashboard"]
        started[f"tcp://127.0.0.1:{wport}"] = p = Proc(orphan_proof([*argv, "--name", f"w{n}"]))
        procs.append(p)
    with Client(address, timeout=timeout_s, set_as_default=False) as client:
        wait_for(lambda: len(client.scheduler_info(n_workers=-1)["workers"]) == workers, timeout_s, f"{workers} dask workers", procs=procs)
    return LoopbackCluster(address, scheduler, started)


def worker_addresses(client: Any) -> set[str]:
    """The addresses of the workers the scheduler counts now."""
    return set(client.scheduler_info(n_workers=-1)["workers"])

"""A study's chunks on a Dask cluster: the executor of ``fimnav montecarlo/sweep --cluster``.

:class:`DaskCluster` sends each chunk of trials (:class:`missions.study.executors.Chunk`) as one
task to a running ``dask scheduler`` and its ``dask worker`` processes (``distributed``, the
optional extra ``fimnav[cluster]``), so one mission's chunks spread over every worker. A
chunk's trials depend on (seed, trial, drone) alone, so the merged results are those of the
same study on this machine, bit for bit, provided the workers run the same code: every task
checks that its worker has the same fimnav sources, numpy, scipy and Python as this machine
(:func:`environment`) and fails with the difference otherwise.

A worker that dies mid-chunk loses nothing: the scheduler gives its chunks to another worker
(a chunk that killed three workers fails the study, Dask's ``allowed-failures``). Workers
report each chunk's progress as it runs (Dask events, at most every
:data:`PROGRESS_INTERVAL_S`); the study's count of trial-steps done takes, per chunk, the most
that any of its attempts reported, so a chunk run again is not counted twice.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import platform
import queue
import re
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from comms.errors import FimnavError, UsageError
from missions.runtime.numerics import numerics_identity
from missions.study.executors import Chunk, simulate_chunk
from missions.study.records import SimulationResult
from planner.warm import available_cores, compile_aside

#: Most seconds between two progress reports of a running chunk.
PROGRESS_INTERVAL_S: float = 0.5
#: Seconds to wait for the scheduler to answer a connection.
CONNECT_TIMEOUT_S: float = 10.0
#: Packages whose sources make up :func:`environment`'s code fingerprint.
FINGERPRINT_PACKAGES: tuple[str, ...] = ("planner", "comms", "missions", "vehicle_sim")
#: Libraries whose versions must agree between this machine and every worker (when installed).
VERSIONED: tuple[str, ...] = ("numpy", "scipy", "numba", "pydantic")

INSTALL_HINT = "pip install 'fimnav[cluster]'"


class EnvironmentMismatch(ValueError):
    """A worker runs other code than the machine that submitted the study."""


def environment() -> dict[str, str]:
    """What a worker must share with the submitting machine for bit-identical results: Python's
    version, the versions of :data:`VERSIONED` (absent ones as "-"), a SHA-256 of fimnav's
    sources (every ``.py`` of :data:`FINGERPRINT_PACKAGES`, by relative path), and the numerics
    (:func:`missions.runtime.numerics.numerics_identity`: pinned, or the host's CPU kind)."""
    from importlib.metadata import PackageNotFoundError, version

    env = {"python": platform.python_version()}
    for name in VERSIONED:
        try:
            env[name] = version(name)
        except PackageNotFoundError:
            env[name] = "-"
    digest = hashlib.sha256()
    for package in FINGERPRINT_PACKAGES:
        spec = importlib.util.find_spec(package)
        if spec is None or not spec.submodule_search_locations:
            continue
        root = Path(next(iter(spec.submodule_search_locations)))
        for path in sorted(root.rglob("*.py")):
            digest.update(f"{package}/{path.relative_to(root).as_posix()}\0".encode())
            digest.update(path.read_bytes())
    env["fimnav sources"] = digest.hexdigest()[:16]
    env["numerics"] = numerics_identity(os.environ)
    return env


def run_chunk_on_worker(chunk: Chunk, tag: str, topic: str, expected: dict[str, str]) -> SimulationResult:
    """The task of one chunk, on a Dask worker: check the worker's :func:`environment` against
    ``expected`` (the submitting machine's), simulate the chunk, and report its trial-steps done
    under the event ``topic`` as ``{"chunk": tag, "done": n, "worker": address}``.

    Raises:
        EnvironmentMismatch: the worker's environment differs (the message names what).
    """
    from distributed import get_worker

    worker = get_worker()
    here = environment()
    diff = [f"{k} {here.get(k)} (submitted from {v})" for k, v in expected.items() if here.get(k) != v]
    if diff:
        hint = ""
        if here.get("numerics") != expected.get("numerics"):
            hint = "; to mix CPU kinds, pin the numerics of the study and of every worker (docs/studies.md)"
        raise EnvironmentMismatch(f"worker {worker.address} runs other code: {', '.join(diff)}{hint}")
    # A cold kernel cache (a fresh node): the planning and estimator kernels compiled in two
    # child processes at once, by one worker of the node while the others wait (planner.warm).
    compile_aside(available_cores())
    done = 0
    last = time.monotonic()

    def report(n: int) -> None:
        nonlocal done, last
        done += n
        now = time.monotonic()
        if now - last >= PROGRESS_INTERVAL_S:
            last = now
            worker.log_event(topic, {"chunk": tag, "done": done, "worker": worker.address})

    return simulate_chunk(chunk, report)


def connect(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> Any:
    """A ``distributed.Client`` of the scheduler at ``address`` (``tcp://HOST:PORT``, or the
    JSON file ``dask scheduler --scheduler-file`` writes).

    Raises:
        UsageError: distributed is not installed, or no scheduler answers at ``address``.
    """
    try:
        from distributed import Client
    except ImportError:
        raise UsageError(f"--cluster needs Dask's distributed package: {INSTALL_HINT}") from None
    where = {"scheduler_file": address} if Path(address).is_file() else {"address": address}
    if "address" in where:
        _check_reachable(address, timeout_s)
    # The client waits for the scheduler's handshake without its timeout (a port where another
    # server listens and never answers would hang the command): it connects in a thread of its
    # own, waited for twice the timeout at most, and left behind (a daemon) if it is still waiting.
    outcome: dict[str, Any] = {}

    def attempt() -> None:
        try:
            outcome["client"] = Client(**where, timeout=timeout_s, set_as_default=False)
        except (OSError, TimeoutError, ValueError, TypeError) as exc:
            outcome["error"] = exc

    thread = threading.Thread(target=attempt, name="fimnav-dask-connect", daemon=True)
    thread.start()
    thread.join(2.0 * timeout_s)
    if "client" in outcome:
        return outcome["client"]
    if "error" in outcome:
        exc = outcome["error"]
        raise _no_scheduler(address, f"({type(exc).__name__}: {exc})")
    raise _no_scheduler(address, f"within {2.0 * timeout_s:g} s (something accepts connections there, but does not speak Dask)")


def _no_scheduler(address: str, why: str) -> UsageError:
    """The one error of a ``--cluster`` address where no scheduler answered, ``why`` appended."""
    return UsageError(f"--cluster {address}: no Dask scheduler answered {why}")


#: A scheduler's TCP address as ``--cluster`` takes it: ``[tcp://]HOST:PORT`` (HOST a name, an
#: IPv4 address or a bracketed IPv6 one).
_TCP_ADDRESS = re.compile(r"^(?:tcp://)?(\[[^\]]+\]|[^:/\[\]]+):(\d+)$")


def _check_reachable(address: str, timeout_s: float) -> None:
    """Refuse at once a TCP address where nothing listens: Dask's client retries a refused
    connection until its timeout (10 s), a plain connection says so in a millisecond. Other
    addresses (another protocol) are left to the client.

    Raises:
        UsageError: the connection is refused, or does not open within ``timeout_s``.
    """
    match = _TCP_ADDRESS.match(address.strip())
    if match is None:
        return
    host, port = match.group(1).strip("[]"), int(match.group(2))
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except ConnectionRefusedError:
        raise _no_scheduler(address, f"(connection refused: nothing listens on port {port} of {host})") from None
    except OSError as exc:
        raise _no_scheduler(address, f"({type(exc).__name__}: {exc})") from None


class DaskCluster:
    """Chunks as tasks of a Dask cluster (see the module doc); ``map`` yields them in order.

    Use as a context manager (or call :meth:`close`): it holds the client's connection.

    Args:
        address: the scheduler (``tcp://HOST:8786``) or its scheduler file.
        client: an existing ``distributed.Client`` instead (not closed by :meth:`close`).
    """

    def __init__(self, address: str | None = None, client: Any = None) -> None:
        if (address is None) == (client is None):
            raise ValueError("DaskCluster: give exactly one of address or client")
        self._own = client is None
        self.client = connect(address) if address is not None else client
        self.address = str(self.client.scheduler.address)

    def __enter__(self) -> DaskCluster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the connection (if this object opened it)."""
        if self._own:
            self.client.close()

    def describe(self) -> str:
        """``N workers, T threads at ADDRESS`` (now: workers can join and leave at any time)."""
        workers = self.client.scheduler_info(n_workers=-1).get("workers", {})
        threads = sum(int(w.get("nthreads", 0)) for w in workers.values())
        return f"{len(workers)} workers, {threads} threads at {self.address}"

    def map(self, chunks: Sequence[Chunk], progress: Callable[[int], object] | None = None) -> Iterator[SimulationResult]:
        """See :meth:`missions.study.executors.ChunkExecutor.map`: every chunk submitted at once,
        the results yielded in the order of ``chunks`` (each fetched and released as soon as it
        is done); progress as the workers report it. Leaving early cancels the rest."""
        if not chunks:
            return
        if any(c.watch is not None for c in chunks):
            raise UsageError("--view watches a run on this machine only: leave it out with --cluster")
        study = uuid.uuid4().hex[:12]
        topic = f"fimnav-progress-{study}"
        tags = [f"fimnav-chunk-{study}-{n}" for n in range(len(chunks))]
        reported = dict.fromkeys(tags, 0)  # the most trial-steps any attempt of a chunk reported
        lock = threading.Lock()

        def on_event(event: tuple[float, Any]) -> None:
            msg = event[1]
            if isinstance(msg, dict) and msg.get("chunk") in reported:
                with lock:
                    reported[msg["chunk"]] = max(reported[msg["chunk"]], int(msg.get("done", 0)))

        counted = 0

        def advance() -> None:
            nonlocal counted
            with lock:
                total = sum(reported.values())
            if progress is not None and total > counted:
                progress(total - counted)
            counted = max(counted, total)

        expected = environment()
        finished: queue.Queue[Any] = queue.Queue()  # futures, as they finish (done callbacks)
        self.client.subscribe_topic(topic, on_event)
        futures = [self.client.submit(run_chunk_on_worker, chunk, tag, topic, expected, key=tag, pure=False) for chunk, tag in zip(chunks, tags)]
        for f in futures:
            f.add_done_callback(finished.put)
        index = {f.key: n for n, f in enumerate(futures)}
        ready: dict[int, SimulationResult] = {}
        pending = set(index)
        try:
            for n in range(len(chunks)):
                while n not in ready:
                    try:
                        f = finished.get(timeout=PROGRESS_INTERVAL_S)
                    except queue.Empty:
                        advance()
                        continue
                    m = index[f.key]
                    ready[m] = self._result(f, chunks[m])
                    pending.discard(f.key)
                    with lock:
                        reported[f.key] = chunks[m].trial_steps
                    f.release()
                    advance()
                yield ready.pop(n)
        finally:
            if pending:
                self.client.cancel([f for f in futures if f.key in pending])
            self.client.unsubscribe_topic(topic)

    @staticmethod
    def _result(future: Any, chunk: Chunk) -> SimulationResult:
        """The result of a finished chunk's task; a failed one as one :class:`FimnavError`."""
        from distributed import KilledWorker

        try:
            return future.result()
        except EnvironmentMismatch as exc:
            raise FimnavError(f"--cluster: {exc}: install the same fimnav and libraries on every worker") from None
        except KilledWorker as exc:
            spec = chunk.spec
            raise FimnavError(
                f"--cluster: trials {spec.first_trial}-{spec.first_trial + spec.trials - 1} of {spec.label} were running on "
                f"every worker that died ({exc}); the study stops"
            ) from None

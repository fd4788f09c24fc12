"""Loading the compiled kernels into a process, and compiling them once on several cores.

The planning kernels (:mod:`planner.kernels`, the step of :func:`planner.agent.plan`) and the
estimator's (:mod:`planner.estimator.kernels`) are compiled by numba into its on-disk cache the
first time they are used after an install or a change of their source, then loaded from it
(about a second). The two groups are independent and each takes about half of the first
compile (30-40 s of CPU each on this project's reference machine), so :func:`compile_aside`
compiles each missing group in a child process of its own, at once, and the caller then loads
both from the cache: on two cores the first compile takes the time of the longer group instead
of the sum. A group already in the cache costs nothing more than its load.

Used by the fork server of ``fimnav launch`` (through :mod:`planner.node.warm`), ``fimnav
plan``, ``fimnav compile``, a local study (``fimnav montecarlo`` and ``sweep``; with ``--jobs
N`` before the pool forks its workers, which then inherit the loaded kernels) and a Dask worker
at its first chunk. A process compiling aside holds an advisory lock that the other processes
of the machine compiling the same kernels wait on, so a machine compiles them once.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

#: What a compiling child runs, by group: a watchdog thread ends it at once when its parent is
#: gone (the end of its stdin), whatever ended the parent; Ctrl-C ends it without a traceback.
_CHILD = (
    "import os, signal, sys, threading\n"
    "signal.signal(signal.SIGINT, signal.SIG_DFL)\n"
    "threading.Thread(target=lambda: (sys.stdin.buffer.read(), os._exit(1)), daemon=True).start()\n"
    "import planner.warm as w\n"
    "{call}\n"
)


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where the platform tells it)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def warm_planning() -> None:
    """One planning step of drone 0 of two (joint and ranging, one building, start positions
    known), its peer heard directly: every kernel a planner's step calls is loaded (or
    compiled into numba's cache), with the argument types of a planner's steps."""
    from planner.agent import plan
    from planner.config import PlannerConfig
    from planner.estimator import EstimatorConfig
    from planner.params import Channel, Limits
    from planner.step import DroneState, StepScene

    start = np.array([[0.0, 100.0, 10.0], [5.0, 100.0, 10.0]])
    config = PlannerConfig(
        channel=Channel(),
        limits=Limits(),
        criterion="A",
        component_masks={"range": np.array([True, True]), "bearing": np.array([True, False])},
        boxes_min_m=np.array([[20.0, 40.0, 0.0]]),
        boxes_max_m=np.array([[30.0, 50.0, 15.0]]),
        d_hop_m=100.0,
        start_positions_m=start,
        estimator=EstimatorConfig(),
    )
    scene = StepScene(
        step_index=0,
        own_index=np.array(0),
        own_position_m=start[0],
        own_range_m=np.array(100.0),
        own_los=np.array(True),
        view_positions_m=start,
        view_valid=np.ones(2, dtype=bool),
        view_los=np.ones(2, dtype=bool),
        saved_steps=np.zeros(2, dtype=np.int64),
        hops=np.array([0, 1]),
        estimate_m=np.array([0.0, 0.0, 2.0]),
        information=np.eye(3),
        observable=np.array(True),
        perturbation_uniforms=np.array([0.5, 0.5]),
        lost_contact=np.zeros(2, dtype=bool),
    )
    plan(config, scene, DroneState.initial((), 2))


def warm_estimator() -> None:
    """One update of one record (:func:`planner.estimator.warm_up`): the estimator's kernels
    loaded (or compiled into numba's cache)."""
    from planner.estimator import warm_up

    warm_up()


def in_cache(kernel: object) -> bool:
    """Whether numba's on-disk cache holds a compiled version of ``kernel`` (a ``cache=True``
    dispatcher) for its current source. Unknown (not a numba dispatcher, the JIT disabled, a
    numba whose cache is laid out otherwise): True, so that nothing is compiled aside."""
    try:
        return bool(kernel._cache._cache_file._load_index())  # type: ignore[attr-defined]
    except Exception:  # numba internals: any surprise means "do not compile aside"
        return True


def _jit_missing() -> list[str]:
    """The JIT kernel groups ("planning", "estimator") numba's cache lacks: their entry kernel
    has no compiled version for its current source."""
    from planner import kernels
    from planner.aot import jit_kernel
    from planner.estimator.kernels import update

    entries = {"planning": kernels.plan_batch, "estimator": update.update_batch}
    return [group for group, kernel in entries.items() if not in_cache(jit_kernel(kernel))]


def missing_groups() -> list[str]:
    """The kernel groups still to compile: those with no extension module built ahead of time
    (:mod:`planner.aot`; "planning", "estimator", "simulator"), or, where they are turned off
    (``FIMNAV_AOT=0``) or cannot be built here, the JIT groups numba's cache lacks ("planning",
    "estimator")."""
    from planner import aot

    if not aot.enabled():
        return _jit_missing()
    failed = aot.failed()
    return [g for g in aot.missing() if g not in failed] + [g for g in _jit_missing() if g in failed]


@contextlib.contextmanager
def _compiling_alone(source_root: str) -> Iterator[None]:
    """Inside: no other process of this machine compiles aside the same kernels (this source
    tree, this numba cache) at the same time; one that does is waited for. An advisory lock on
    a file in the temporary directory; without one (it cannot be made or opened) no wait."""
    key = f"{source_root}\0{os.environ.get('NUMBA_CACHE_DIR', '')}".encode()
    path = Path(tempfile.gettempdir()) / f"fimnav-compile-{hashlib.sha256(key).hexdigest()[:16]}.lock"
    try:
        handle = path.open("a")
    except OSError:
        yield
        return
    with handle:
        fcntl.flock(handle, fcntl.LOCK_EX)  # released when the file is closed
        yield


def group_names(groups: list[str]) -> str:
    """``a``, ``a and b``, ``a, b and c`` (``no`` for none)."""
    return ", ".join(groups[:-1]) + (" and " if len(groups) > 1 else "") + groups[-1] if groups else "no"


def compile_notice(missing: list[str]) -> str:
    """The one line a command prints before it compiles the ``missing`` kernel groups."""
    return f"compiling the {group_names(missing)} kernels first: once after an install, about a minute on two cores (`fimnav compile` does it beforehand)"


def compile_aside(workers: int) -> list[str]:
    """Compile the kernel groups still to compile (:func:`missing_groups`) in child processes,
    and wait for them; returns the groups compiled so. An extension module built ahead of time
    (:func:`planner.aot.build`) is always built in a child, every group at once when
    ``workers`` ≥ 2, else one after the other; a group that cannot be built is recorded as such
    (:func:`planner.aot.failed`) and is the JIT's from then on. JIT groups are compiled aside
    only when two are missing and ``workers`` ≥ 2 (one compiles as fast in the caller). Another
    process of this machine compiling the same kernels aside (the workers of a cluster node, a
    second command) is waited for first, and what it compiled is not compiled again.

    A JIT child that fails is not an error here: the caller's own load then compiles the group
    and raises what went wrong. Leaving early (an exception, a signal turned into one) kills
    the children; a child also ends by itself when this process is gone (its stdin closes)."""
    from planner import aot

    if not _aside(workers, missing_groups()):
        aot.bind_built()
        return []
    source_root = str(Path(__file__).resolve().parents[1])  # the children import this very code
    with _compiling_alone(source_root):
        missing = missing_groups()  # again: another process may have compiled them meanwhile
        aside = _aside(workers, missing)
        if not aside:
            aot.bind_built()
            return []
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (source_root, os.environ.get("PYTHONPATH")) if p))
        calls = [f"import planner.aot_build as a\na.build_or_record({group!r})" if ahead else f"w.warm_{group}()" for group, ahead in aside]
        children: list[subprocess.Popen[bytes]] = []
        try:
            # At most ``workers`` at once, the longest group (planning) first.
            for call in calls:
                while sum(c.poll() is None for c in children) >= max(workers, 1):
                    time.sleep(0.1)  # the poll interval of the wait for a free slot
                argv = [sys.executable, "-c", _CHILD.format(call=call)]
                children.append(subprocess.Popen(argv, env=env, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
            for child in children:
                child.wait()
        finally:
            for child in children:
                if child.poll() is None:
                    child.kill()
                    child.wait()
                if child.stdin is not None:
                    child.stdin.close()
        aot.bind_built()
        still = missing_groups()
        return [group for group, ahead in aside if not ahead or group not in still]


def _aside(workers: int, missing: list[str]) -> list[tuple[str, bool]]:
    """What :func:`compile_aside` compiles in children, as (group, built ahead of time): every
    group to build ahead of time, and the JIT groups when two are missing and ``workers`` ≥ 2
    (one compiles as fast in the caller)."""
    from planner import aot

    failed = aot.failed() if aot.enabled() else {}
    ahead = [g for g in missing if aot.enabled() and g not in failed]
    jit = [g for g in missing if g not in ahead]
    return [(g, True) for g in ahead] + ([(g, False) for g in jit] if workers >= 2 and len(jit) >= 2 else [])


def load_kernels(workers: int = 1) -> None:
    """Load the planning and the estimator kernels into this process, compiling the missing
    ones first on up to ``workers`` cores (:func:`compile_aside`)."""
    compile_aside(workers)
    warm_planning()
    warm_estimator()


__all__ = [
    "available_cores",
    "compile_aside",
    "compile_notice",
    "group_names",
    "in_cache",
    "load_kernels",
    "missing_groups",
    "warm_estimator",
    "warm_planning",
]

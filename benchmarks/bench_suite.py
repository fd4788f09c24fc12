"""How long the default test run takes on a cold kernel cache, as after a fresh clone (CI, a new
user's first ``python3 -m pytest``), for two checkouts (not a timed test).

Each round runs ``python -m pytest -q`` in each checkout's root, the order swapped every round,
after deleting the numba cache files (``*.nbi``, ``*.nbc``) under that checkout's packages: the
run's warm-up (``tests/conftest.py``) and any test that reaches a kernel not yet compiled
compile it, as in a fresh clone. Each checkout runs its own code, and so does every process its tests start
(``PYTHONPATH`` is the checkout; the script refuses a checkout that imports fimnav from
elsewhere), with this interpreter and its libraries. Printed per run: the wall time of the command, pytest's own
figure (from the start of collection: it leaves the warm-up out), the CPU time of the command
and every process it waited for (``RUSAGE_CHILDREN``: the warm-up, the workers, the processes
the tests start) and the count of passed tests, which must be the same for both.

``--warm`` keeps the caches (each checkout's first round then fills its own).
``--warm-up-only`` runs, instead of the suite, only its warm-up on the cold cache: the two
processes of ``tests.conftest.warm_up_scripts`` at once, as the run starts them; printed: when
each ended, and their CPU time.

Usage::

    python benchmarks/bench_suite.py BEFORE AFTER [--rounds 1] [--warm | --warm-up-only]
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

from bench_cluster_client import require_own_code

PACKAGES = ("planner", "missions", "comms", "vehicle_sim")
SUMMARY = re.compile(r"(\d+) passed(?:, (\d+) skipped)? in ([\d.]+)s")


def drop_kernel_cache(tree: Path) -> int:
    """Delete numba's cache files under ``tree``'s packages; returns how many."""
    files = [p for pkg in PACKAGES for pattern in ("*.nbi", "*.nbc") for p in (tree / pkg).rglob(pattern)]
    for p in files:
        p.unlink()
    return len(files)


def run_suite(tree: Path) -> tuple[float, float, float, int]:
    """Wall seconds of ``python -m pytest -q`` in ``tree``, pytest's own seconds, CPU seconds,
    tests passed."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    argv = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"]
    done = subprocess.run(argv, cwd=tree, env=dict(os.environ, PYTHONPATH=str(tree)), capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    found = SUMMARY.search(done.stdout.splitlines()[-1] if done.stdout else "")
    if done.returncode != 0 or found is None:
        raise SystemExit(f"bench_suite: the run in {tree} failed (exit {done.returncode}):\n{done.stdout[-3000:]}{done.stderr[-2000:]}")
    return wall, float(found.group(3)), cpu, int(found.group(1))


def run_warm_up(tree: Path) -> tuple[float, float, float]:
    """Wall seconds of the run's warm-up in ``tree`` (the later of its two processes' ends),
    the planning process's end, and the CPU seconds of both."""
    env = dict(os.environ, PYTHONPATH=str(tree), FIMNAV_AOT="0")  # as tests/__init__.py sets it
    code = "from tests.conftest import warm_up_scripts; print(chr(0).join(warm_up_scripts()), end='')"
    scripts = subprocess.run([sys.executable, "-c", code], cwd=tree, env=env, capture_output=True, text=True, check=True).stdout.split("\0")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    started = [subprocess.Popen([sys.executable, "-c", script], cwd=tree, env=env) for script in scripts]
    ends: dict[int, float] = {}
    while len(ends) < len(started):
        for i, p in enumerate(started):
            if i not in ends and p.poll() is not None:
                if p.returncode != 0:
                    raise SystemExit(f"bench_suite: the warm-up in {tree} failed (exit {p.returncode})")
                ends[i] = time.perf_counter() - t0
        time.sleep(0.05)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return max(ends.values()), ends[0], (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("before", type=Path)
    parser.add_argument("after", type=Path)
    parser.add_argument("--rounds", type=int, default=1)
    parser.add_argument("--warm", action="store_true", help="keep numba's caches")
    parser.add_argument("--warm-up-only", action="store_true", help="time the run's warm-up alone, on a cold cache")
    args = parser.parse_args()
    trees = {"before": args.before.resolve(), "after": args.after.resolve()}
    for k, tree in trees.items():
        require_own_code("bench_suite", k, tree, dict(os.environ, PYTHONPATH=str(tree)))
    if args.warm_up_only:
        for r in range(args.rounds):
            for k in list(trees)[r % 2 :] + list(trees)[: r % 2]:
                drop_kernel_cache(trees[k])
                wall, planning, cpu = run_warm_up(trees[k])
                print(f"round {r + 1}: {k}: warm-up {wall:.1f} s (planning process {planning:.1f} s), CPU {cpu:.1f} s", flush=True)
        return 0
    res: dict[str, list[tuple[float, float, float, int]]] = {k: [] for k in trees}
    for r in range(args.rounds):
        for k in list(trees)[r % 2 :] + list(trees)[: r % 2]:
            dropped = 0 if args.warm else drop_kernel_cache(trees[k])
            res[k].append(run_suite(trees[k]))
            wall, own, cpu, passed = res[k][-1]
            print(
                f"round {r + 1}: {k}: wall {wall:.1f} s, pytest's figure {own:.1f} s, CPU {cpu:.0f} s, {passed} passed ({dropped} cache files dropped first)",
                flush=True,
            )
    counts = {x[3] for v in res.values() for x in v}
    if len(counts) != 1:
        raise SystemExit(f"bench_suite: the runs passed different numbers of tests: {sorted(counts)}")
    print(f"\n{'warm' if args.warm else 'cold'} kernel cache, {args.rounds} rounds; before = {trees['before']}, after = {trees['after']}\n")
    print("| checkout | wall, median | pytest's figure, median | CPU, median |")
    print("|---|---:|---:|---:|")
    for k, v in res.items():
        wall, own, cpu = (statistics.median(x[i] for x in v) for i in range(3))
        print(f"| {k} | {wall:.1f} s | {own:.1f} s | {cpu:.0f} s |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

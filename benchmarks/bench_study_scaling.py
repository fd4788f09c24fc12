"""How a study scales with its workers (not a timed test): one mission's Monte Carlo run on one
local worker, on two (``--jobs 2``), and on a loopback Dask cluster of two workers
(``--cluster``); and, for the machine's own ceiling, half its trials on one worker alone and two
such commands at once. The five taken in turn, in a rotated order, for ``--rounds`` rounds;
medians of the wall times and of the CPU times.

Each command is ``fimnav montecarlo MISSION --trials M --steps K --no-figures`` in a fresh
process (start-up included). The cluster (a ``dask scheduler`` and two ``dask worker`` processes
of one thread each, no nanny, on 127.0.0.1) is started once, before the rounds, and is not
timed; its CPU time is read from /proc for the scheduler and workers. The local runs' CPU time
is the command's and its pool workers' (``RUSAGE_CHILDREN``). The three full-size summaries must
agree (bit for bit, but the wall times), and so must the half-size ones: the script fails
otherwise.

The ceiling: two independent processes, each doing half the work with its own start, write and
no coordination, are as parallel as two processes can be; 2 × (the half alone) / (two at once)
is what this machine's two cores give on this work (2.00 × on two free, independent cores).
``--jobs 2`` does the same work with one start (its workers forked from it) and the results
merged and written once, at the end: it can come near this ceiling, not past it by more than
the half-study's write.

Usage::

    python benchmarks/bench_study_scaling.py [--mission paper/joint] [--trials 100] [--steps 550] [--rounds 3] [--warm]

``--warm``: before the rounds, one untimed study of two steps on the cluster (two chunks: both
workers import fimnav and load its compiled kernels once, as a long-lived cluster has), its
wall and CPU printed apart; without it the first cluster round pays that start-up.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import resource
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TIMING = ("runtime_s", "drone_steps_per_s")
#: The machine's own ceiling: half the trials on one worker alone, then two such commands at once
#: (no fimnav between them: two independent processes, each with its own start and write).
SOLO = "half the trials, 1 worker, alone"
PAIR = "half the trials, 1 worker, two commands at once"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def proc_cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far (/proc/PID/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


#: prctl's option that sets the signal a process gets when its parent dies (Linux).
PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """In a child between fork and exec: SIGKILL when the benchmark's process ends, whatever
    ends it (a signal that skips its clean-up included), so no cluster process outlives it."""
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)


def start_cluster(env: dict[str, str]) -> tuple[str, list[subprocess.Popen[bytes]]]:
    """A scheduler and two workers on loopback (each killed when this process ends); returns
    the address and the processes once the scheduler counts both workers."""
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    dask = [sys.executable, "-m", "dask"]
    scheduler = [*dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"]
    procs = [subprocess.Popen(scheduler, env=env, stderr=subprocess.DEVNULL, preexec_fn=die_with_parent)]
    for _ in range(2):
        argv = [*dask, "worker", address, "--host", "127.0.0.1", "--no-nanny", "--nthreads", "1", "--no-dashboard"]
        procs.append(subprocess.Popen(argv, env=env, stderr=subprocess.DEVNULL, preexec_fn=die_with_parent))
    from distributed import Client

    with Client(address, timeout=60, set_as_default=False) as client:
        client.wait_for_workers(2, timeout=120)
    return address, procs


def run(argv: list[str], env: dict[str, str], cluster: list[subprocess.Popen[bytes]] | None) -> tuple[float, float]:
    """Wall and CPU seconds of ``argv`` (its own and its waited-for children's, plus the
    cluster's processes' over the same time)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    cluster_before = sum(proc_cpu_s(p.pid) for p in cluster) if cluster else 0.0
    t0 = time.perf_counter()
    subprocess.run(argv, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if cluster:
        cpu += sum(proc_cpu_s(p.pid) for p in cluster) - cluster_before
    return wall, cpu


def run_pair(argvs: list[list[str]], env: dict[str, str]) -> tuple[float, float]:
    """Wall seconds until every command of ``argvs``, started at once, has ended, and their CPU
    seconds (their own and their waited-for children's)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    started = [subprocess.Popen(a, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for a in argvs]
    codes = [p.wait() for p in started]
    wall = time.perf_counter() - t0
    if any(codes):
        raise SystemExit(f"bench_study_scaling: a command of the pair failed ({codes})")
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def untimed(summary_path: Path) -> list[dict[str, object]]:
    runs = json.loads(summary_path.read_text())["runs"]
    return [{k: v for k, v in r.items() if k not in TIMING} for r in runs]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mission", default="paper/joint")
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--steps", type=int, default=550)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--warm", action="store_true", help="an untimed two-step study on the cluster before the rounds")
    args = parser.parse_args()
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    address, cluster = start_cluster(env)
    configs = {
        "1 local worker (--jobs 1)": ["--jobs", "1"],
        "2 local workers (--jobs 2)": ["--jobs", "2"],
        "Dask, 2 workers (--cluster)": ["--cluster", address],
        SOLO: ["--jobs", "1"],
        PAIR: ["--jobs", "1"],
    }
    names = list(configs)
    walls: dict[str, list[float]] = {n: [] for n in names}
    cpus: dict[str, list[float]] = {n: [] for n in names}
    loads = [os.getloadavg()[0]]
    try:
        with tempfile.TemporaryDirectory() as tmp:
            if args.warm:
                argv = [sys.executable, "-m", "missions", "montecarlo", args.mission, "--trials", str(args.trials), "--steps", "2"]
                wall, cpu = run([*argv, "--no-figures", "--out", str(Path(tmp) / "warm"), "--cluster", address], env, cluster)
                print(f"warm-up (untimed in the table): the cluster's first study, 2 steps: wall {wall:.1f} s, CPU {cpu:.1f} s", flush=True)
            half = max(1, args.trials // 2)
            for r in range(args.rounds):
                for n in names[r % len(names) :] + names[: r % len(names)]:
                    out = Path(tmp) / f"{names.index(n)}-{r}"
                    trials = half if n in (SOLO, PAIR) else args.trials
                    argv = [sys.executable, "-m", "missions", "montecarlo", args.mission, "--trials", str(trials), "--steps", str(args.steps)]
                    argv += ["--no-figures", *configs[n]]
                    if n == PAIR:
                        wall, cpu = run_pair([[*argv, "--out", f"{out}-{i}"] for i in range(2)], env)
                    else:
                        wall, cpu = run([*argv, "--out", str(out)], env, cluster if "--cluster" in configs[n] else None)
                    walls[n].append(wall)
                    cpus[n].append(cpu)
                    loads.append(os.getloadavg()[0])
                    print(f"round {r + 1}: {n}: wall {wall:.1f} s, CPU {cpu:.1f} s, load {loads[-1]:.1f}", flush=True)
            # Each output directory is "<config index>-<round>[-<pair member>]".
            halves = {str(names.index(SOLO)), str(names.index(PAIR))}
            reference = {False: untimed(Path(tmp) / "0-0" / "summary.json"), True: untimed(Path(tmp) / f"{names.index(SOLO)}-0" / "summary.json")}
            for d in Path(tmp).iterdir():
                if d.name != "warm" and untimed(d / "summary.json") != reference[d.name.split("-")[0] in halves]:
                    raise SystemExit(f"bench_study_scaling: {d.name}'s summary differs from the one-worker run's")
    finally:
        for p in reversed(cluster):  # the workers, then the scheduler
            p.terminate()
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(10)
    one = statistics.median(walls[names[0]])
    two = statistics.median(walls[names[1]])
    print(f"\n{args.mission}, {args.trials} trials x {args.steps} steps, {args.rounds} rounds; load average {min(loads):.1f}-{max(loads):.1f}\n")
    print("| command | wall, median [min-max] | CPU (all processes), median | wall speed-up over 1 worker | CPU over 1 worker's |")
    print("|---|---|---|---|---|")
    cpu_one = statistics.median(cpus[names[0]])
    for n in names[:3]:
        w, c = statistics.median(walls[n]), statistics.median(cpus[n])
        print(f"| {n} | {w:.1f} s [{min(walls[n]):.1f}-{max(walls[n]):.1f}] | {c:.1f} s | {one / w:.2f} x | {c / cpu_one:.2f} x |")
    # Two workers on two free cores: each does half the CPU work at once.
    print(f"\nspeed-up two free cores would give (2 x CPU of 1 worker / CPU of 2): {2 * cpu_one / statistics.median(cpus[names[1]]):.2f} x")
    solo, pair = statistics.median(walls[SOLO]), statistics.median(walls[PAIR])
    print(
        f"this machine's ceiling for two processes on this work (2 x wall of one half-study alone / wall of two at once, "
        f"each with its own start): {2 * solo / pair:.2f} x (half alone {solo:.1f} s, two at once {pair:.1f} s; "
        f"CPU {statistics.median(cpus[SOLO]):.1f} s against {statistics.median(cpus[PAIR]) / 2:.1f} s each)"
    )
    print(f"\nDask cluster over --jobs 2 (wall, medians): {statistics.median(walls[names[2]]) / two - 1:+.1%}")
    print(f"Dask cluster over --jobs 2 (CPU, medians): {statistics.median(cpus[names[2]]) / statistics.median(cpus[names[1]]) - 1:+.1%}")
    print("the three full-size summaries are equal (but wall times), and the half-size ones")
    return 0


if __name__ == "__main__":
    sys.exit(main())

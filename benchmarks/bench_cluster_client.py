"""The client of a ``--cluster`` study in two checkouts of fimnav, side by side (not a timed
test): each checkout gets its own loopback Dask cluster (a scheduler and two workers running
that checkout's code: a worker refuses chunks from other sources), and its ``--jobs 2`` run as
the reference. The four commands (``fimnav montecarlo MISSION --trials 100 --no-figures`` with
``--jobs 2`` or ``--cluster``, per checkout) are taken in turn, in a rotated order, for
``--rounds`` rounds; medians of the wall time, of the command's CPU time (for ``--cluster``
the client alone) and of the cluster processes' CPU over the same time.

Every summary must equal the first checkout's ``--jobs 2`` one (but the wall times): the
script fails otherwise. Each cluster gets one untimed two-step study first (its workers
import fimnav and load its kernels once, as ``bench_study_scaling.py --warm``).

Usage::

    git worktree add /tmp/fimnav-before COMMIT
    python benchmarks/bench_cluster_client.py /tmp/fimnav-before . [--rounds 6] [--mission paper/joint]
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_study_scaling import proc_cpu_s, start_cluster, untimed


def require_own_code(script: str, label: str, tree: Path, env: dict[str, str]) -> None:
    """Exit with a message unless a process started with ``env`` (outside any checkout) imports
    fimnav from ``tree``."""
    code = "import missions; print(missions.__file__)"
    where = subprocess.run([sys.executable, "-c", code], cwd="/", env=env, capture_output=True, text=True, check=True).stdout.strip()
    if not Path(where).is_relative_to(tree):
        raise SystemExit(f"{script}: {label} imports fimnav from {where}, not from {tree}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("before", type=Path, help="a checkout of the earlier commit")
    parser.add_argument("after", type=Path, help="a checkout of the later commit")
    parser.add_argument("--mission", default="paper/joint")
    parser.add_argument("--rounds", type=int, default=6)
    args = parser.parse_args()
    trees = {"before": args.before.resolve(), "after": args.after.resolve()}
    envs = {k: dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(t)) for k, t in trees.items()}
    clusters = {}
    with tempfile.TemporaryDirectory() as tmp:
        # Every process starts in the temporary directory: started from a checkout's root,
        # ``python -m`` would import that checkout's packages, whatever PYTHONPATH says.
        os.chdir(tmp)
        for k, tree in trees.items():
            require_own_code("bench_cluster_client", k, tree, envs[k])
        try:
            for k in trees:
                clusters[k] = start_cluster(envs[k])
            study = [sys.executable, "-m", "missions", "montecarlo", args.mission, "--trials", "100", "--no-figures", "--out"]
            for k, (address, _) in clusters.items():
                warm = [*study, f"{tmp}/warm-{k}", "--steps", "2", "--cluster", address]
                subprocess.run(warm, env=envs[k], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            names = [(k, m) for k in trees for m in ("--jobs 2", "--cluster")]
            res: dict[tuple[str, str], list[tuple[float, float, float]]] = {n: [] for n in names}
            for r in range(args.rounds):
                for k, m in names[r % len(names) :] + names[: r % len(names)]:
                    address, procs = clusters[k]
                    out = f"{tmp}/{k}-{m[2:]}-{r}"
                    extra = ["--jobs", "2"] if m == "--jobs 2" else ["--cluster", address]
                    before = resource.getrusage(resource.RUSAGE_CHILDREN)
                    cluster_before = sum(proc_cpu_s(p.pid) for p in procs)
                    t0 = time.perf_counter()
                    subprocess.run([*study, out, *extra], env=envs[k], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                    wall = time.perf_counter() - t0
                    after = resource.getrusage(resource.RUSAGE_CHILDREN)
                    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
                    res[(k, m)].append((wall, cpu, sum(proc_cpu_s(p.pid) for p in procs) - cluster_before))
                    print(f"round {r + 1}: {k} {m}: wall {wall:.2f} s, command CPU {cpu:.2f} s, cluster CPU {res[(k, m)][-1][2]:.2f} s", flush=True)
            reference = untimed(Path(f"{tmp}/before-jobs 2-0/summary.json"))
            for d in Path(tmp).iterdir():
                if not d.name.startswith("warm") and untimed(d / "summary.json") != reference:
                    raise SystemExit(f"bench_cluster_client: {d.name}'s summary differs from the first checkout's --jobs 2")
        finally:
            for _, procs in clusters.values():
                for p in reversed(procs):
                    p.terminate()
                    p.wait(10)
    print(f"\n{args.mission}, 100 trials, {args.rounds} rounds; before = {trees['before']}, after = {trees['after']}\n")
    print("| checkout | command | wall, median | command CPU, median | cluster CPU, median |")
    print("|---|---|---:|---:|---:|")
    med = {n: [statistics.median(x[i] for x in v) for i in range(3)] for n, v in res.items()}
    for (k, m), (w, c, cc) in med.items():
        print(f"| {k} | `{m}` | {w:.2f} s | {c:.2f} s | {cc:.2f} s |")
    for k in trees:
        print(f"{k}: --cluster over --jobs 2 (wall, medians): {med[(k, '--cluster')][0] / med[(k, '--jobs 2')][0] - 1:+.1%}")
    print("every summary equals the first checkout's --jobs 2 one (but wall times)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

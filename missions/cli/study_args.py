"""What the study commands (``fimnav montecarlo``, ``fimnav sweep``) share: where the chunks of
trials run (``--jobs``, ``--cluster``, ``--chunk-trials``) and the checks of the numbers."""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Callable
from typing import Any

from comms.errors import UsageError
from missions.study.executors import MAX_CHUNKS, MIN_CHUNK_TRIALS, ChunkExecutor, local_executor


def add_executor_args(p: argparse.ArgumentParser) -> None:
    """``--jobs``, ``--cluster`` and ``--chunk-trials``."""
    where = p.add_mutually_exclusive_group()
    where.add_argument("--jobs", type=int, default=None, help="worker processes on this machine sharing the runs' trials (default 1)")
    where.add_argument(
        "--cluster",
        metavar="ADDRESS",
        help="send the chunks of trials to a running Dask scheduler (tcp://HOST:8786, or its --scheduler-file) and its workers, "
        "which need the same fimnav and libraries (docs/studies.md); the results are those of the run on this machine",
    )
    p.add_argument(
        "--chunk-trials",
        type=int,
        metavar="N",
        help=f"trials per chunk, the unit of work shared by the workers (default: at least {MIN_CHUNK_TRIALS}, "
        f"at most {MAX_CHUNKS} chunks per run); with injected faults it sets the rounding, so compare runs made with the same value",
    )


def add_policy_arg(p: argparse.ArgumentParser) -> None:
    """``--policy NAME[,NAME...]``."""
    from planner.policies import POLICIES

    p.add_argument(
        "--policy",
        metavar="NAME[,NAME...]",
        help=f"navigation policies, one run each with the same seeds: {', '.join(POLICIES)}, or all "
        "(default: the mission's, fim: the paper's planner; docs/studies.md)",
    )


def policies(args: argparse.Namespace) -> list[str] | None:
    """The policies of ``--policy`` (None: each mission's); UsageError naming an unknown one."""
    from planner.policies import POLICIES

    if args.policy is None:
        return None
    names = list(POLICIES) if args.policy.strip() == "all" else [n.strip() for n in args.policy.split(",")]
    for name in names:
        if name not in POLICIES:
            raise UsageError(f"--policy: expected policies among {', '.join(POLICIES)} (or all), found {name!r}")
    if len(set(names)) != len(names):
        raise UsageError(f"--policy: expected different policies, found {args.policy!r}")
    return names


def positive(name: str, value: int | None) -> None:
    """A ``--name`` that must be a positive integer when given (UsageError otherwise)."""
    if value is not None and value < 1:
        raise UsageError(f"--{name}: expected a positive integer, found {value}")


def chunking(args: argparse.Namespace) -> dict[str, int]:
    """``chunk_trials`` and ``max_chunks`` for :func:`missions.study.montecarlo.run_study`:
    ``--chunk-trials N`` cuts a run into as many chunks of about N trials as it holds."""
    positive("chunk-trials", args.chunk_trials)
    if args.chunk_trials is None:
        return {"chunk_trials": MIN_CHUNK_TRIALS, "max_chunks": MAX_CHUNKS}
    return {"chunk_trials": args.chunk_trials, "max_chunks": 1 << 30}


def open_executor(args: argparse.Namespace, stack: contextlib.ExitStack, say: Callable[[str], Any]) -> ChunkExecutor:
    """The executor of ``--jobs`` (a local process pool) or ``--cluster`` (a Dask cluster,
    closed with ``stack``); ``say`` is told which cluster it is, or that the kernels are about
    to be compiled (a cold cache, once after an install)."""
    positive("jobs", args.jobs)
    if args.cluster is None:
        from planner.warm import compile_notice, missing_groups

        missing = missing_groups()
        if missing:
            say(compile_notice(missing))
        return local_executor(args.jobs or 1)
    if getattr(args, "view", False):
        raise UsageError("--view watches a run on this machine only: leave it out with --cluster")
    from missions.study.cluster import DaskCluster

    cluster = stack.enter_context(DaskCluster(args.cluster))
    say(f"cluster: {cluster.describe()}")
    return cluster

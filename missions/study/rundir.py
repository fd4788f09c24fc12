"""The results directory of a ``fimnav launch`` run: which files make a run, refusing (or with
``overwrite`` clearing) a directory that holds a previous run, and claiming a fresh one.

A results directory holds one run: the launcher refuses a directory that holds a previous run's
files (:data:`RUN_ENTRIES`) unless asked to overwrite them, which removes them first.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from comms.errors import UsageError

#: What a run writes at the top of its results directory: a directory holding any of them holds
#: a run (refused, or with ``overwrite`` these, and only these, are removed first).
RUN_ENTRIES: tuple[str, ...] = ("mission.yaml", "summary.json", "logs", "tlogs", "runs", "figures", "view.rrd")


def previous_run(out: Path) -> list[str]:
    """The entries of :data:`RUN_ENTRIES` present in ``out`` (directories with a trailing
    ``/``), in that order; empty when ``out`` holds no run (or does not exist)."""
    found = []
    for name in RUN_ENTRIES:
        p = out / name
        if p.is_symlink() or p.exists():
            found.append(f"{name}/" if p.is_dir() and not p.is_symlink() else name)
    return found


def check_results_dir(out: Path, overwrite: bool = False) -> list[str]:
    """Check that ``out`` can take a run; return the previous run's entries there (removed by
    :func:`claim_results_dir` when ``overwrite``).

    Raises:
        UsageError: ``out`` is not a directory, or it holds a previous run and ``overwrite`` is
            false.
    """
    if out.exists() and not out.is_dir():
        raise UsageError(f"results directory {out}: expected a directory, found a file")
    found = previous_run(out)
    if found and not overwrite:
        raise UsageError(f"results directory {out} already holds a run ({', '.join(found)}); choose another --out or pass --overwrite")
    return found


def claim_results_dir(out: Path, overwrite: bool = False) -> None:
    """Make ``out`` this run's results directory, with empty ``logs/`` and ``tlogs/`` (with
    ``overwrite``, a previous run's files are removed first; nothing else in ``out`` is).

    Raises:
        UsageError: see :func:`check_results_dir`; or another launch claimed ``out`` meanwhile.
    """
    for name in check_results_dir(out, overwrite):
        p = out / name.rstrip("/")
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()
    try:
        (out / "logs").mkdir(parents=True)  # atomic: two launches cannot both create it
    except FileExistsError:
        raise UsageError(f"results directory {out}: another launch started writing it; choose another --out") from None
    (out / "tlogs").mkdir(exist_ok=True)


def unique_results_dir(parent: Path, name: str) -> Path:
    """Create and return ``parent/name``, or ``parent/name-2``, ``-3``, ... if taken (two
    launches in the same second get different directories: ``mkdir`` is atomic)."""
    parent.mkdir(parents=True, exist_ok=True)
    n = 1
    while True:
        path = parent / (name if n == 1 else f"{name}-{n}")
        try:
            path.mkdir()
        except FileExistsError:
            n += 1
            continue
        return path

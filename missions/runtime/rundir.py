"""The one place that makes a results directory, for every command that writes one
(``fimnav montecarlo``, ``fimnav launch``): a directory that cannot be made or written
(a missing or read-only parent, no permission, a file in the way, a full disk) is one
:class:`comms.errors.UsageError` naming it (exit 2), never a traceback.

A ``fimnav launch`` directory holds one run: the launcher refuses a directory that holds a
previous run's files (:data:`RUN_ENTRIES`) unless asked to overwrite them, which removes them
first, and claims a fresh one.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from comms.errors import UsageError


def _why(path: Path, exc: OSError) -> str:
    """Why ``path`` could not be made or written, in a few words: the file in the way, the
    directory it was to be made in, and the system's reason."""
    for parent in [path, *path.parents]:
        if parent.exists() or parent.is_symlink():
            if not parent.is_dir():
                return f"{parent} is a file, not a directory"
            where = f" in {parent}" if parent != path else ""
            return f"{exc.strerror or exc}{where}"
    return str(exc.strerror or exc)


@contextlib.contextmanager
def writing(out: Path) -> Iterator[None]:
    """Inside: an ``OSError`` while making or writing something in results directory ``out``
    (no space left, a read-only file system, ...) ends as one :class:`UsageError` naming the
    directory, the file and the reason."""
    try:
        yield
    except UsageError:
        raise
    except OSError as exc:
        what = f" ({exc.filename})" if exc.filename and Path(os.fsdecode(exc.filename)) != out else ""
        raise UsageError(
            f"results directory {out}: cannot write{what}: {_why(Path(os.fsdecode(exc.filename or out)), exc)}; choose another --out"
        ) from None


def make_results_dir(out: Path) -> Path:
    """Make results directory ``out`` (and its parents) if it does not exist, check that a file
    can be written in it, and return it.

    Raises:
        UsageError: ``out`` cannot be made or written (the message names it and why).
    """
    out = Path(out)
    if (out.exists() or out.is_symlink()) and not out.is_dir():
        raise UsageError(f"results directory {out}: expected a directory, found a file")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"results directory {out}: cannot make it: {_why(out, exc)}; choose another --out") from None
    try:
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as exc:
        raise UsageError(f"results directory {out}: cannot write in it: {exc.strerror or exc}; choose another --out") from None
    return out


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
    previous = check_results_dir(out, overwrite)
    make_results_dir(out)
    with writing(out):
        for name in previous:
            p = out / name.rstrip("/")
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink()
        try:
            (out / "logs").mkdir()  # atomic: two launches cannot both create it
        except FileExistsError:
            raise UsageError(f"results directory {out}: another launch started writing it; choose another --out") from None
        (out / "tlogs").mkdir(exist_ok=True)


def unique_results_dir(parent: Path, name: str) -> Path:
    """Create and return ``parent/name``, or ``parent/name-2``, ``-3``, ... if taken (two
    launches in the same second get different directories: ``mkdir`` is atomic).

    Raises:
        UsageError: ``parent`` cannot be made or written (see :func:`make_results_dir`).
    """
    make_results_dir(parent)
    n = 1
    with writing(parent):
        while True:
            path = parent / (name if n == 1 else f"{name}-{n}")
            try:
                path.mkdir()
            except FileExistsError:
                n += 1
                continue
            return path

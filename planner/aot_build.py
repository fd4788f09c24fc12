"""Building the extension modules of :mod:`planner.aot` (numba.pycc), in a process of its own.

Imports the kernel modules by name (:data:`planner.aot.GROUPS`): only the process that builds
(a child of :func:`planner.warm.compile_aside`) imports this module.
"""

from __future__ import annotations

import importlib
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

from planner.aot import (
    GROUPS,
    UNUSED_MODULE_S,
    directory,
    failed,
    failure_file,
    forget_failure,
    jit_cpu,
    jit_kernel,
    module_name,
    parse_signature,
    path,
)
from planner.aot_signatures import SIGNATURES


class BuildError(RuntimeError):
    """An extension module could not be built (no C compiler, no setuptools, a kernel numba's
    ahead-of-time compiler refuses); the message says which group and why."""


def build(group: str) -> Path:
    """Build ``group``'s extension module (numba.pycc, for the CPU numba's JIT compiles for,
    with its features) and put it in :func:`directory`, atomically; returns its file. Run it in
    a process of its own (:func:`planner.warm.compile_aside`): it changes numba's
    ahead-of-time code generator in this process so that it compiles with the host's features.

    Raises:
        BuildError: the build failed (the message says why).
    """
    module_path, names = GROUPS[group]
    target = path(group)
    try:
        from numba.core import codegen
        from numba.pycc import CC

        # The JIT's feature set rather than the one implied by the CPU model: the same code
        # choices as the JIT, and no instruction a virtual machine masks.
        codegen.AOTCPUCodegen._customize_tm_features = lambda self: self._get_host_cpu_features()  # type: ignore[method-assign]
        kernels = importlib.import_module(module_path)
        name = module_name(group)
        target.parent.mkdir(parents=True, exist_ok=True)
        _remove_stale_builds(target.parent)
        with tempfile.TemporaryDirectory(dir=target.parent, prefix=".build-") as tmp:
            cc = CC(name)
            cc.output_dir = tmp
            # The JIT's CPU: ``NUMBA_CPU_NAME`` where set (missions.runtime.numerics pins it), else the host's.
            cc.target_cpu = jit_cpu()[0]
            cc.verbose = False
            for kernel in names:
                cc.export(kernel, parse_signature(SIGNATURES[kernel]))(jit_kernel(getattr(kernels, kernel)).py_func)
            cc.compile()
            built = [p for p in Path(tmp).iterdir() if p.name.startswith(name) and p.suffix in (".so", ".pyd")]
            if not built:
                raise BuildError(f"{group}: numba.pycc wrote no extension module")
            os.replace(built[0], target)
        remove_unused_modules(target.parent, group)
    except BuildError:
        raise
    except Exception as exc:  # a compiler, setuptools or numba refusing: the reason
        raise BuildError(f"the {group} kernels could not be built ahead of time: {type(exc).__name__}: {exc}") from exc
    return target


#: A build directory left older than this is from a build that was killed (a build takes a minute
#: or two): removed by the next build in the same directory.
STALE_BUILD_S: float = 3600.0


def _unused_for(path: Path, seconds: float, now: float) -> bool:
    """Whether ``path`` was last modified more than ``seconds`` before ``now`` (False when it
    cannot be told: gone, or unreadable)."""
    try:
        return now - path.stat().st_mtime > seconds
    except OSError:
        return False


def _remove_stale_builds(directory: Path) -> None:
    """Remove the temporary directories of killed builds (``.build-*`` older than
    :data:`STALE_BUILD_S`) from ``directory``; a build running now (another machine sharing the
    directory) is younger and kept."""
    now = time.time()
    for old in directory.glob(".build-*"):
        if _unused_for(old, STALE_BUILD_S, now):
            shutil.rmtree(old, ignore_errors=True)


def remove_unused_modules(directory: Path, group: str) -> list[Path]:
    """Remove ``group``'s extension modules (and failure records) of other keys from
    ``directory`` that were not loaded for :data:`planner.aot.UNUSED_MODULE_S` (their
    modification time, renewed by :func:`planner.aot.mark_used`): those of earlier sources,
    numba or Python versions, or of a CPU no longer seen. The current key's are kept whatever
    their age. Returns what was removed."""
    current = module_name(group) + "."
    now = time.time()
    removed = []
    for old in directory.glob(f"fimnav_aot_{group}_*"):
        if old.name.startswith(current) or not _unused_for(old, UNUSED_MODULE_S, now):
            continue
        try:
            old.unlink()
        except OSError:
            continue
        removed.append(old)
    return removed


def build_or_record(group: str) -> None:
    """:func:`build` ``group``; if it fails, record why (:func:`failed`), print it to stderr
    and exit with status 1 (what a child of :func:`planner.warm.compile_aside` runs)."""
    forget_failure(group)
    try:
        build(group)
    except BuildError as exc:
        try:
            failure_file(group).parent.mkdir(parents=True, exist_ok=True)
            failure_file(group).write_text(str(exc) + "\n", encoding="utf-8")
        except OSError:
            pass
        print(exc, file=sys.stderr)
        raise SystemExit(1) from None


def build_for_install() -> int:
    """Build every group into :func:`planner.aot.directory` and leave nothing else there (no
    module of another key, no failure record: an installed package tries again on first use);
    what the package's build runs (``setup.py``, with ``FIMNAV_AOT_DIR`` set to the built
    package's ``planner/__pycache__/aot``). Returns 0 when every group was built, else 1 (the
    reasons printed to stderr)."""
    from planner.warm import available_cores, compile_aside

    compile_aside(available_cores())
    reasons = failed()
    keep = {path(group).name for group in GROUPS if group not in reasons}
    for entry in directory().iterdir() if directory().is_dir() else ():
        if entry.name in keep:
            continue
        if entry.is_dir():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)
    for reason in reasons.values():
        print(reason, file=sys.stderr)
    return 1 if reasons else 0


__all__ = ["BuildError", "build", "build_for_install", "build_or_record", "remove_unused_modules"]

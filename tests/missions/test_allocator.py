"""A study's process keeps the memory it frees (missions.runtime.allocator): arrays freed and
allocated again at every step reuse their pages instead of faulting fresh ones in. Measured in
fresh interpreters, the page faults counted by the kernel (``ru_minflt``)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

_LOOP = textwrap.dedent(
    """
    import resource, sys
    import numpy as np
    if sys.argv[1] == "keep":
        from missions.runtime.allocator import keep_freed_memory
        assert keep_freed_memory()
    size = 1 << 22  # 32 MiB of float64: above glibc's largest adaptive mmap threshold
    a = np.ones(size)
    del a
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(40):
        a = np.ones(size)  # writes every page
        del a
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    """
)


def _faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", _LOOP, mode], cwd=ROOT, capture_output=True, text=True, timeout=120, check=True)
    return int(out.stdout.strip())


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt: Linux only")
def test_a_study_process_reuses_the_pages_of_the_arrays_it_frees() -> None:
    default, kept = _faults("default"), _faults("keep")
    # glibc's default maps each 32 MiB array afresh: every page faults again, 40 times over.
    assert default > 40 * 8
    assert kept * 5 < default


def test_a_local_executor_sets_it_for_its_process(monkeypatch: pytest.MonkeyPatch) -> None:
    import missions.study.executors as ex

    calls: list[int] = []
    monkeypatch.setattr(ex, "keep_freed_memory", lambda: calls.append(1) or True)
    ex.local_executor(1)
    ex.local_executor(2)
    assert len(calls) == 2

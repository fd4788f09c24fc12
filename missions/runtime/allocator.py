"""The C allocator of a study's processes: freed memory kept for the next step's arrays.

A study steps every trial and drone of a chunk together, and each step allocates and frees
the same arrays again (the carried state the planning step returns, the measurements, the
views, numpy's temporaries; from tens of kilobytes to a few megabytes each). glibc's
``malloc`` serves such sizes from fresh ``mmap`` mappings or returns the top of its heap to the
system when they are freed (its adaptive thresholds), so the next step's arrays fault their
pages in again, each a page the kernel clears first. Measured on a 2-core machine, the full
case study (``fimnav montecarlo missions/paper/*.yaml --criterion both --jobs 2 --no-figures``):
1.23 million page faults and 3.4-3.5 s of system time with glibc's defaults; 0.15 million and
1.0 s with both thresholds raised, the wall time 1-1.5 s shorter and the peak memory the same
(0.40-0.43 GB).

:func:`keep_freed_memory` raises them (``mallopt``) in the process that runs a study's chunks
on this machine (:func:`missions.study.executors.local_executor`); its pool's workers, forked
from it, inherit them. The memory a process has freed then stays with it until it ends: a
study's process ends with its study. A Dask worker is not started by fimnav and keeps its own
settings (Dask trims freed memory to keep its count of a worker's memory true). Elsewhere
than glibc (macOS, musl) nothing changes.
"""

from __future__ import annotations

import ctypes
import sys

#: ``mallopt``'s parameters (glibc's malloc.h).
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
#: Both thresholds, bytes: larger than any array a study frees and allocates again.
THRESHOLD_BYTES: int = 2**31 - 1


def keep_freed_memory() -> bool:
    """Raise glibc's trim and mmap thresholds to :data:`THRESHOLD_BYTES` in this process (and
    the processes it forks afterwards): freed memory is kept for reuse rather than returned to
    the system. Returns whether both were set (False where the C library is not glibc)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    mmap_set = mallopt(M_MMAP_THRESHOLD, THRESHOLD_BYTES) == 1
    trim_set = mallopt(M_TRIM_THRESHOLD, THRESHOLD_BYTES) == 1
    return mmap_set and trim_set

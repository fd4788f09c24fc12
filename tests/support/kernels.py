"""Which compiled kernels the suite runs: numba's JIT (the default run, ``FIMNAV_AOT=0`` set by
``tests/__init__.py``) or the ones built ahead of time (``FIMNAV_AOT=1 python -m pytest``)."""

from __future__ import annotations

import pytest

from planner import aot

#: For a test of numba's JIT itself (its first compile, its cache, a dispatcher's signatures):
#: skipped, with its reason, when the suite runs on the kernels built ahead of time.
jit_only = pytest.mark.skipif(aot.enabled(), reason="checks numba's JIT kernels; this run uses the ones built ahead of time (FIMNAV_AOT=1)")

"""The marker of the tests that compare a run with a recording made on the suite's pinned
numerics (``tests/__init__.py``, :mod:`missions.runtime.numerics`)."""

from __future__ import annotations

import pytest

from tests import UNPINNED

#: For a test whose expected values were recorded with the pinned numerics (bit for bit, or a
#: ranging run's trajectory, which parts with the last bits): skipped, with the reason, on a
#: machine that cannot run them (not x86-64, or no AVX2 and FMA).
pinned = pytest.mark.skipif(UNPINNED is not None, reason=UNPINNED or "")

"""Shared fixtures of the math-core tests (tests/planner/).

Every random draw comes from a seeded :class:`numpy.random.Generator`; there is no global RNG.
Hypothesis settings are set per test (``@settings``), never through a global profile, so this
directory does not change how other suites run.
"""

from __future__ import annotations

import zlib

import numpy as np
import pytest


@pytest.fixture
def rng(request: pytest.FixtureRequest) -> np.random.Generator:
    """A generator seeded from the test's node id (stable across runs and machines)."""
    return np.random.default_rng(np.random.SeedSequence(zlib.crc32(request.node.nodeid.encode())))

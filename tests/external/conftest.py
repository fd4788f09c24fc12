"""Fixtures of the real-time tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.support.proc import Proc


@pytest.fixture
def procs() -> Iterator[list[Proc]]:
    """Every process a test starts; each process group is stopped at the end."""
    started: list[Proc] = []
    yield started
    for p in reversed(started):
        p.stop()

"""A value computed once per test run and shared by every pytest-xdist worker.

A module- or session-scoped fixture runs once per worker that runs one of its tests: with three
workers an expensive fixture can run three times. :func:`once_per_run` computes the value in
the first worker that asks (the others wait on a file lock) and writes it as JSON into the run's
shared temporary directory, where the other workers read it.
"""

from __future__ import annotations

import fcntl
import json
import os
from collections.abc import Callable
from typing import Any

import pytest


def once_per_run(tmp_path_factory: pytest.TempPathFactory, name: str, compute: Callable[[], Any]) -> Any:
    """``compute()`` (a JSON value), run once per test run under the name ``name``: by the
    first worker that asks; the others (and later callers) get the value it wrote. Without
    workers the value is computed (no other process needs it). Every caller gets the value as
    JSON gives it back (tuples as lists), whoever computed it."""
    if "PYTEST_XDIST_WORKER" not in os.environ:
        return json.loads(json.dumps(compute()))
    root = tmp_path_factory.getbasetemp().parent  # a worker's is <the run's>/popen-gwN
    path = root / f"shared-{name}.json"
    with open(root / f"shared-{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not path.exists():
            tmp = path.with_suffix(".tmp")
            tmp.write_text(json.dumps(compute()))
            tmp.replace(path)
        return json.loads(path.read_text())

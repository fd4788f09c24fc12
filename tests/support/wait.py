"""Waits with deadlines (never fixed sleeps)."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from tests.support.proc import Proc


def wait_for(predicate: Callable[[], object], timeout_s: float, what: str, *, procs: Sequence[Proc] = (),
             detail: Callable[[], object] | None = None, interval_s: float = 0.1) -> float:
    """Poll ``predicate`` every ``interval_s`` until it is true; return the monotonic time it was.

    Raises AssertionError naming ``what`` after ``timeout_s``, or as soon as one of ``procs``
    exits with a non-zero status; the message holds ``detail()`` and the output of ``procs``.
    """
    deadline = time.monotonic() + timeout_s
    while not predicate():
        for p in procs:
            code = p.p.poll()
            if code not in (None, 0):
                raise AssertionError(f"{p.label} exited {code} while waiting for {what}:\n{p.tail()}")
        if time.monotonic() > deadline:
            extra = f"\n{detail()}" if detail is not None else ""
            tails = "".join(f"\n=== {p.label}\n{p.tail(1500)}" for p in procs)
            raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}{extra}{tails}")
        time.sleep(interval_s)  # polling interval of a deadline wait, not a fixed delay
    return time.monotonic()

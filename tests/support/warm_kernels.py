"""The compiled kernels the tests call directly, compiled into numba's cache by the suite's
warm-up (:func:`tests.conftest.pytest_configure`) with the argument types the tests pass.

A planner's step and a study go through the entry kernels (``plan_batch``, ``update_batch``,
the simulator's loops), which the warm-up compiles by running them. Many tests also call
kernels a step does not enter by themselves: the batch wrappers behind ``planner.control``,
``planner.fim``, ``planner.geometry``, ``planner.agent`` and the range memory's functions
(``planner.estimator.memory``). On a cold cache (a fresh clone: CI, a new user's first
``pytest``) each xdist worker whose test first reached one of them compiled it, with every
inner function under it again (numba links inner functions only into the process that compiled
them): 70-80 s of CPU spread over the run. Compiled here, in the warm-up's process that has just
compiled those inner functions, they are in the cache before any worker starts, and a worker
loads them.

The lists are types, not calls: :func:`compile_planning` and :func:`compile_estimator` compile
each kernel for its signatures (``Dispatcher.compile``, which loads the overload from the cache
when it is there and saves it when it compiles it). A signature no test passes any more costs
one useless compile; a kernel renamed or removed fails the warm-up, and with it the run, by name.
"""

from __future__ import annotations

from typing import Any

from numba import types

F = types.float64
I = types.int64  # noqa: E741 (the type's usual one-letter name)
B = types.boolean


def arr(dtype: Any, ndim: int, readonly: bool = False) -> types.Array:
    """A C-contiguous array type (``readonly``: a read-only view, as a frozen state gives)."""
    return types.Array(dtype, ndim, "C", readonly=readonly)


f1, f2, f3, b1, b2, i1, i2 = arr(F, 1), arr(F, 2), arr(F, 3), arr(B, 1), arr(B, 2), arr(I, 1), arr(I, 2)
rf1, rf2, rf3 = arr(F, 1, True), arr(F, 2, True), arr(F, 3, True)

#: ``planner.kernels``: name → argument types, one tuple per signature.
PLANNING: dict[str, list[tuple[Any, ...]]] = {
    "candidates_batch": [(f2, b1, f1)],
    "cost_gradient_batch": [(f3, f2, f2, b1, b1, f1, f2, B, f1, B, f2)],
    "dead_reckoning_batch": [(f1, f2, f2, f2, f1)],
    "envelope_batch": [(f1, f1, f1, B, f1, f1, f2, f2, f1, f1, f1, f1, F, f2, f2, f1)],
    "followable_batch": [(f2, f2, f1, f1, f2, f1, f1)],
    "invert_batch": [(f3, f3, f2)],
    "link_clearance_batch": [(f2, f2, f2, f2, I, F)],
    "loiter_batch": [(f2, f2, f1)],
    "own_los_batch": [(f2, f2, b1, B, f2, f2)],
    "own_range_batch": [(f1, f1, F, f1, f1)],
    "own_ranges_batch": [(f2, b2, f1)],
    "planes_batch": [(f2, f2, b1)],
    "policy_batch": [(f1, b1, f1, f1, f1, b1, F, f1)],
    "small_batch": [(f3, f2)],
}

#: ``planner.estimator.kernels.memory``: name → argument types.
MEMORY: dict[str, list[tuple[Any, ...]]] = {
    "_group": [(f2, I, f2, f1, f1, F, i1, i1, i2), (f2, I, rf2, rf1, rf1, F, i1, i1, i2)],
    "best_start": [(f2, I, f1, f1, F, f1, I, f2, f1), (f2, I, rf1, rf1, F, f1, I, f2, f1)],
    "best_start_batch": [(f3, rf2, rf2, F, f1, I)],
    "evaluate": [(f2, I, f1, F, B, f2, f1, f2), (f2, I, rf1, F, B, f2, f1, f2)],
    "evaluate_batch": [(f3, rf2, F, B)],
    "insert": [(f2, I, f2, f1, f1, f1, F, i2, f2, f2, B), (f2, I, rf2, rf1, rf1, rf1, F, i2, f2, f2, B)],
    "insert_batch": [(f3, rf3, rf2, rf2, rf2, F)],
    "polish_batch": [(f3, rf2, F, f1, I, F)],
    "refresh_batch": [(f3,)],
}


def _compile(module: Any, table: dict[str, list[tuple[Any, ...]]]) -> None:
    from planner.aot import jit_kernel

    for name, signatures in table.items():
        dispatcher = jit_kernel(getattr(module, name))
        for argtypes in signatures:
            dispatcher.compile(argtypes)


def compile_planning() -> None:
    """Compile (or load) :data:`PLANNING`'s kernels for their signatures."""
    from planner import kernels

    _compile(kernels, PLANNING)


def compile_estimator() -> None:
    """Compile (or load) :data:`MEMORY`'s kernels for their signatures."""
    from planner.estimator.kernels import memory

    _compile(memory, MEMORY)

"""The bridge from the compiled refinement to the measurement components outside its fused
range/bearing kernel (:attr:`planner.sensing.SensingTable.extra_components`), whose terms are
their own Python code (:meth:`planner.sensing.SensingComponent.estimator_terms`): a callback
that the compiled code calls through a C function pointer (numba's first-class function type;
every callback has the same type, so none compiles the kernels again)."""

from __future__ import annotations

import ctypes
from collections.abc import Callable

import numba.experimental.function_type  # noqa: F401 - registers the typing of WrapperAddressProtocol objects
from numba import types

#: The callback's signature: (buffer address, rows K, values X) -> 0.0, or NaN on an error.
SIGNATURE = types.float64(types.uintp, types.int64, types.int64)
_CFUNC = ctypes.CFUNCTYPE(ctypes.c_double, ctypes.c_size_t, ctypes.c_int64, ctypes.c_int64)


class Callback(types.WrapperAddressProtocol):  # type: ignore[misc]
    """A Python function ``fn(address, K, X) -> float`` callable from compiled code."""

    def __init__(self, fn: Callable[[int, int, int], float]) -> None:
        self._cfunc = _CFUNC(fn)  # kept alive as long as the callback

    def __wrapper_address__(self) -> int:
        return int(ctypes.cast(self._cfunc, ctypes.c_void_p).value or 0)

    def signature(self) -> types.Signature:
        return SIGNATURE


def _no_extension(address: int, rows: int, values: int) -> float:
    """The callback of an update without extension values (never called)."""
    return float("nan")


#: The callback passed when no record carries an extension value.
NO_EXTENSION = Callback(_no_extension)

"""The bridge from the compiled refinement to the measurement components outside its fused
range/bearing kernel (:attr:`planner.sensing.SensingTable.extra_components`), whose terms are
their own Python code (:meth:`planner.sensing.SensingComponent.estimator_terms`): a callback
that the compiled code calls through a C function pointer. The kernels take the pointer as an
integer (:attr:`Callback.address`) and call it with :func:`call`: every callback has the same
argument type, so none compiles the kernels again, and a kernel built ahead of time
(:mod:`planner.aot`) takes it as it takes any integer, with no conversion in Python at each call.
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable
from typing import Any

from numba import types
from numba.extending import intrinsic

#: The callback's C type: (buffer address, rows K, values X) -> 0.0, or NaN on an error.
_CFUNC = ctypes.CFUNCTYPE(ctypes.c_double, ctypes.c_size_t, ctypes.c_int64, ctypes.c_int64)


class Callback:
    """A Python function ``fn(address, K, X) -> float`` callable from compiled code at
    :attr:`address` (for as long as this object lives: keep it until the compiled call
    returns)."""

    def __init__(self, fn: Callable[[int, int, int], float]) -> None:
        self._cfunc = _CFUNC(fn)  # kept alive as long as the callback
        #: The C function pointer, as the integer the kernels take.
        self.address: int = int(ctypes.cast(self._cfunc, ctypes.c_void_p).value or 0)


def _no_extension(address: int, rows: int, values: int) -> float:
    """The callback of an update without extension values (never called)."""
    return float("nan")


#: The callback passed when no record carries an extension value.
NO_EXTENSION = Callback(_no_extension)


@intrinsic
def call(typingctx: Any, fn: Any, address: Any, rows: Any, values: Any) -> Any:
    """``fn(address, rows, values)`` in compiled code: the C function at the integer ``fn`` (a
    :attr:`Callback.address`), given the address of its buffer (floats) and the rows K and
    values X it holds; returns its float (0.0, or NaN when the Python side met an error)."""
    sig = types.float64(types.uint64, types.uint64, types.int64, types.int64)
    # The C function's pointer type, as numba lowers a pointer to a function of that signature.
    pointer = types.ExternalFunctionPointer(types.float64(types.uint64, types.int64, types.int64), get_pointer=lambda f: 0)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        target = builder.inttoptr(args[0], context.get_function_pointer_type(pointer))
        return context.call_function_pointer(builder, target, list(args[1:]))

    return sig, codegen

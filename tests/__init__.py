"""fimnav's tests, a regular package: every test module and helper is imported as
``tests.<directory>.<module>``, by pytest and by the scripts run with ``python -m tests.…``.

pymavlink chooses MAVLink 1 or 2 when it is first imported, from ``MAVLINK20`` in the
environment: it is set here, before any test module or test script can import pymavlink; so
are the BLAS libraries' thread counts (:mod:`missions.runtime.threads`), before numpy, and the
numerics are pinned (:mod:`missions.runtime.numerics`: numba's target CPU, OpenBLAS's kernels,
numpy's SIMD loops), so that the recorded references (``tests/data/simulator_reference.npz``, the
open-loop comparison's table) hold on every x86-64 machine with AVX2 and FMA. Where the machine
cannot run the pinned configuration, or with ``FIMNAV_NUMERICS=host``, :data:`UNPINNED` says
why, and the tests that compare with a recording skip with that reason
(:data:`tests.support.numerics.pinned`).

The suite runs numba's JIT kernels (``FIMNAV_AOT=0``, unless the environment sets it), compiled
once into numba's cache by tests/conftest.py: building the extension modules ahead of time
(:mod:`planner.aot`) on top would add about a minute of CPU to every clean run. The
ahead-of-time kernels are tested against the JIT's in tests/planner/test_aot.py, which turns
them on for its own processes; ``FIMNAV_AOT=1 python -m pytest`` runs the suite on them (the
tests of the JIT's cache and signatures skip, :data:`tests.support.kernels.jit_only`). A test of
a first compile sets the kernel path in its command's environment and runs in either.
"""

import os
import sys

from missions.runtime.numerics import is_pinned, pin_unless_host
from missions.runtime.threads import one_blas_thread

os.environ["MAVLINK20"] = "1"
os.environ.setdefault("FIMNAV_AOT", "0")
# As in every fimnav command (missions.cli.main): the tests that call the library in process
# run it as a command does, and their BLAS threads do not spin on the other workers' cores.
one_blas_thread(os.environ)

_ALREADY_PINNED = is_pinned(os.environ)  # an xdist worker inherits the controller's pin
#: ``None`` where the suite's numerics are pinned, else the reason they are not:
#: ``FIMNAV_NUMERICS=host python -m pytest`` runs the suite with this machine's own.
UNPINNED = pin_unless_host(os.environ)
if UNPINNED is None and not _ALREADY_PINNED and {"numpy", "scipy", "numba"} & set(sys.modules):
    raise RuntimeError(
        f"{sorted({'numpy', 'scipy', 'numba'} & set(sys.modules))} imported before tests/__init__.py pinned the numerics "
        "(missions.runtime.numerics): this process would not compute what the recorded references hold; "
        "run the suite with python -m pytest, or set the variables of missions.runtime.numerics.PINNED first"
    )

"""The argument types of the entry kernels built ahead of time (:mod:`planner.aot`), read off
numba's JIT kernels after short simulations: what writes :mod:`planner.aot_signatures`.

    FIMNAV_AOT=0 python -m missions.study.kernel_signatures > planner/aot_signatures.py

(after a change of a kernel's arguments; tests/planner/test_aot.py checks the file against it).
"""

from __future__ import annotations

import importlib
import json

from planner import aot


def record() -> str:
    """The text of :mod:`planner.aot_signatures`: the argument types every entry kernel is
    called with, read off the JIT kernels after a short simulation of each shipped paper
    mission under each policy and a planner's warm-up. Run with ``FIMNAV_AOT=0`` (the JIT
    kernels only) in a fresh process: ``FIMNAV_AOT=0 python -m missions.study.kernel_signatures >
    planner/aot_signatures.py``.

    Raises:
        RuntimeError: the extension modules are on, or an entry kernel was not called or was
            called with two sets of argument types (one is built).
    """
    if aot.enabled():
        raise RuntimeError("record() reads the JIT kernels: run it with FIMNAV_AOT=0")
    from missions.study.montecarlo import expand_runs
    from missions.study.simulator import simulate
    from planner.warm import warm_estimator, warm_planning

    warm_planning()
    warm_estimator()
    for mission in ("joint", "ranging_los", "bearing", "heterogeneous", "dynamic_source"):
        for policy in ("fim", "static", "orbit", "random", "centralized"):
            simulate(expand_runs([f"paper/{mission}"], {}, "D", None, 2, 3, [policy])[0])
    lines = [
        '"""The argument types of the entry kernels built ahead of time (:mod:`planner.aot`), as',
        "expressions of ``numba.core.types``. Written by :func:`missions.study.kernel_signatures.record`; do not edit by hand.",
        '"""',
        "",
        "SIGNATURES: dict[str, str] = {",
    ]
    for module, names in aot.GROUPS.values():
        kernels = importlib.import_module(module)
        for name in names:
            dispatcher = aot.jit_kernel(getattr(kernels, name))
            sigs = list(dispatcher.overloads.values())
            if len(sigs) != 1:
                raise RuntimeError(f"{module}.{name} was compiled for {len(sigs)} sets of argument types; one is built ahead of time")
            lines.append(f"    {json.dumps(name)}: {json.dumps(aot.signature_expression(sigs[0].signature))},")
    lines.append("}")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(record(), end="")

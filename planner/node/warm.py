"""Importing this module loads the compiled planning and estimator kernels into the process
(numba: from its cache, or compiled once after an install, the two groups at once on two cores,
:func:`planner.warm.load_kernels`): the fork server of ``fimnav launch`` imports it before it
forks the planners (``missions.launch.forkspawn.PRELOAD``), so ten planners do not each load,
or compile, the same kernels at their first step.
"""

from __future__ import annotations

from planner.warm import available_cores, load_kernels

load_kernels(available_cores())

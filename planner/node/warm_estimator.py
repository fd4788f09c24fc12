"""Importing this module loads the compiled estimator kernels into the process (numba: from its
cache, or compiled once after an install): the fork server of ``fimnav launch`` imports it
before it forks the planners (``missions.launch.forkspawn.PRELOAD``), and the launcher fixes a
real-time start only once the fork server is ready, so the planners neither each load (or
compile) the same kernels after their start time was fixed nor miss the first steps for it.

It runs :func:`planner.estimator.warm_up`: one update of one record, the same kernels with the
same argument types as a planner's estimator (:class:`planner.node.core.StepCore` calls it
again at its start, then at once).
"""

from __future__ import annotations

from planner.estimator import warm_up

warm_up()

"""The numpy estimator of commit 48f7e03, before the compiled core: the TEST-ONLY reference of
:mod:`planner.estimator` (``tests/simulator/test_open_loop_vs_numpy.py`` runs both on the same
records and compares them call by call). Never imported by production code.

Vendored verbatim from ``git show 48f7e03:planner/estimator/<module>.py`` (the modules
``update`` needs: ``__init__``, ``initialisation``, ``linalg``, ``memory``, ``robust``,
``safeguards``, ``state``, ``update``); the only edits: ``planner.estimator`` ->
``tests.reference_numpy.estimator`` in the imports (sorted again; docstrings still name the
original modules) and this docstring (the original's is :mod:`planner.estimator`'s). It uses
the production :mod:`planner.params` and :mod:`planner.sensing`, whose parts the estimator
calls (the channel, the residuals and the measurement components) are unchanged since 48f7e03
(only the planner node's one-drone Fisher helpers left sensing).
The method is documented in :mod:`planner.estimator` and ``docs/estimator.md``.
"""

from __future__ import annotations

from tests.reference_numpy.estimator.state import EstimatorConfig, EstimatorState, Measurements, empty_measurements, initial_state
from tests.reference_numpy.estimator.update import update

__all__ = ["EstimatorConfig", "EstimatorState", "Measurements", "empty_measurements", "initial_state", "update"]

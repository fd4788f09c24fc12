"""The estimator's compiled kernels (numba, ``@njit(cache=True)``): the per-element arithmetic
of :mod:`planner.estimator`, looping over the batch elements themselves. Imported on the first
update (not by ``import planner.estimator``): importing numba and loading the cached machine
code costs a process that never estimates nothing.

:mod:`.linalg` small linear algebra; :mod:`.memory` the range memory; :mod:`.robust` the
robust refinement; :mod:`.pseudolinear` the pseudo-linear initialisation; :mod:`.update` one
update of a batch (:func:`~planner.estimator.kernels.update.update_batch`). They import only
numpy and numba.
"""

"""The estimator's compiled kernels (numba, ``@njit(cache=True)``): the per-element arithmetic
of :mod:`planner.estimator`, looping over the batch elements themselves. Imported on the first
update (not by ``import planner.estimator``): importing numba and loading the cached machine
code costs a process that never estimates nothing.

:mod:`.linalg` small linear algebra; :mod:`.memory` the range memory; :mod:`.robust` the
robust refinement; :mod:`.pseudolinear` the pseudo-linear initialisation; :mod:`.update` one
update of a batch (:func:`~planner.estimator.kernels.update.update_batch`). They import only
numpy and numba.

Every inner function says whether numba counts the references of its arrays (the decorators
of :mod:`.linalg`): ``@borrowing`` (``_nrt=False``) where it allocates nothing and returns no array (its array arguments are borrowed from its
caller: no atomic increment and decrement of each at every call, which took about a fifth
of the estimator's time), ``@counting`` (``_nrt=True``) where it allocates (said explicitly: a function called
from one compiled without counting would otherwise inherit that). An array returned from an
inner function would be counted by one side only, so none returns one (:func:`.update._get`
fills its output); ``tests/simulator/test_reference_counts.py`` checks that a simulation
leaves no array of the compiled code alive.
"""

"""The numerical libraries' own thread pools: one thread in every ``fimnav`` command.

fimnav's linear algebra is small (3 × 3 Fisher information matrices, SLSQP on a few dozen
variables, least squares over a drone's records): a BLAS thread pool (numpy's and scipy's
OpenBLAS, MKL, OpenMP) gains nothing on it, and its threads spin between calls on the cores
that a study's workers, a swarm's planners and vehicles or a test run's workers need. Measured
on a 2-core machine: ``fimnav optimum paper/joint`` used 15.1 and 15.4 s of CPU for 8.5 and
8.7 s of wall time with the pools at their default (a thread per core), 6.8 and 9.9 s of CPU for
7.0 and 10.2 s with one thread each. The libraries read these variables once, when they are
loaded: :func:`one_blas_thread` sets them where ``fimnav`` starts (:func:`missions.cli.main.main`),
before a command imports numpy, for the command and every process it starts. A value already
in the environment is kept: ``OPENBLAS_NUM_THREADS=4 fimnav ...`` gives OpenBLAS four.
(A Dask worker is not started by ``fimnav``: docs/studies.md starts it with ``OMP_NUM_THREADS=1``.)
"""

from __future__ import annotations

from collections.abc import MutableMapping

#: The variables the BLAS and OpenMP runtimes read for their thread count (OpenBLAS reads its
#: own first, then ``OMP_NUM_THREADS``).
BLAS_THREAD_VARIABLES: tuple[str, ...] = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread(environ: MutableMapping[str, str]) -> None:
    """Set each of :data:`BLAS_THREAD_VARIABLES` to ``"1"`` in ``environ`` (``os.environ``)
    unless it is set already. Has an effect on a library loaded after the call only."""
    for name in BLAS_THREAD_VARIABLES:
        environ.setdefault(name, "1")

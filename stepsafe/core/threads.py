"""BLAS threads for dense kernels.

On the 2-core machines this project is measured on, a multithreaded BLAS spends more time
synchronising than computing on the matrices of a system analysis, and on a busy machine
its threads wait for cores held by other processes: the coupled analysis of a 200-dof
Hessian took 2.5x as long with two threads as with one (lightly loaded), and the symmetric
eigenvalues of a 2500 x 2500 stiffness 19.4 s with two threads against 1.1 s with one while
another process kept one core busy (``benchmarks/run.py`` prints the two-thread ratio).
The kernels therefore run with :data:`THREADS` BLAS threads, one unless the environment
variable ``STEPSAFE_BLAS_THREADS`` says otherwise (``0``: the library's default, for
machines with cores to spare).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager


def _threads() -> int:
    try:
        return max(0, int(os.environ.get("STEPSAFE_BLAS_THREADS", "1")))
    except ValueError:
        return 1


#: BLAS threads for stepsafe's dense kernels (0: the library's default)
THREADS = _threads()


@contextmanager
def blas_threads_for(size: int) -> Iterator[None]:
    """:data:`THREADS` BLAS threads while the block runs (``size``, the matrix rows, is
    kept for callers: measured, one thread was as fast or faster at every size tried)."""
    if THREADS == 0:
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=THREADS, user_api="blas"):
        yield

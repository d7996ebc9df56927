"""BLAS threads for dense kernels.

The dense matrices of a system analysis (one-step matrices of size 2n, eigenproblems of
the stiffness) are small enough that a multithreaded BLAS spends more time synchronising
than computing, and on a busy machine its threads wait for cores held by other processes:
measured on a 2-core machine, the coupled analysis of a 200-dof Hessian took 3.4 s with one
thread and 6.4 s with two, lightly loaded (``benchmarks/run.py`` prints both). Kernels on
matrices up to :data:`PIN_MAX_SIZE` therefore run with one BLAS thread; larger ones keep the
library's default.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

#: matrices up to this size (rows) run with one BLAS thread
PIN_MAX_SIZE = 2000


@contextmanager
def blas_threads_for(size: int) -> Iterator[None]:
    """One BLAS thread while the block runs, if ``size <= PIN_MAX_SIZE``."""
    if size > PIN_MAX_SIZE:
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield

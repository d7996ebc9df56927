"""Blocks of an ensemble's rows integrated on worker threads, with the results of a run
that integrates them one after the other.

A run of many trajectories (:func:`stepsafe.core.ensemble.integrate`) is split into blocks
of rows; each block's trajectories do not depend on the others. A run may stop once
``stop`` of its rows have failed: run in order, block ``i`` then stops at its
``stop - seen``-th failure (``seen`` the failures of the blocks before it) and the blocks
after the one that reaches ``stop`` do not run. :func:`in_order` gives exactly that run's
results while integrating up to ``workers`` blocks at once:

* without ``stop``, every block runs, on a pool of threads;
* with ``stop``, blocks run in waves of ``workers``, each given the budget left before the
  wave. Taken in order, a block's result stands unless a block before it in its wave had
  failures: the budget it should have had is then smaller, and when it reached that
  smaller budget (it would have stopped sooner) it is run again with it, alone. A block
  that reaches the whole budget settles the run, and the blocks after it in its wave are
  cancelled (at their next progress call) and discarded.

Progress is reported from the calling thread only (the blocks' fractions, weighted by
their rows, every :data:`POLL` seconds).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import Protocol, TypeVar

import numpy as np

#: Seconds between progress reports while blocks run on threads.
POLL = 0.25


class Counted(Protocol):
    """A block's result: which of its rows failed."""

    @property
    def escaped(self) -> np.ndarray: ...


Result = TypeVar("Result", bound=Counted)


class _Cancelled(Exception):
    """Raised in a block's progress call once its result is not needed."""


def _failures(result: Counted) -> int:
    return int(np.count_nonzero(result.escaped))


def in_order(run_block: Callable[[int, int | None, Callable[[float], None] | None], Result],
             sizes: Sequence[int], stop: int | None, workers: int,
             progress: Callable[[float], None] | None = None) -> list[Result]:
    """The results of the blocks a run in order integrates (module docstring).

    Parameters
    ----------
    run_block : callable
        ``run_block(i, budget, report)``: block i integrated, stopping after the step at
        which ``budget`` of its rows have failed (None: never); ``report(fraction)`` to be
        called now and then with the fraction of its steps done (None: not).
    sizes : sequence of int
        The rows of each block (weights of the progress).
    stop : int, optional
        Stop the run once this many rows have failed (at least 1).
    workers : int
        Blocks integrated at once (1: one after the other, on the calling thread).
    progress : callable, optional
        Called with the fraction of the run's rows times steps done.

    Returns
    -------
    list
        The results of blocks ``0..k-1``: all blocks, or up to the one at which the failures
        reached ``stop``.
    """
    n = len(sizes)
    total = float(max(1, sum(sizes)))
    done = [0.0] * n

    def fraction() -> float:
        return sum(f * s for f, s in zip(done, sizes)) / total

    out: list[Result] = []
    seen = 0
    if workers <= 1 or n <= 1:
        for i in range(n):
            budget = None if stop is None else stop - seen

            def report(f: float, i: int = i) -> None:
                done[i] = f
                assert progress is not None
                progress(fraction())
            ran = run_block(i, budget, None if progress is None else report)
            out.append(ran)
            seen += _failures(ran)
            if stop is not None and seen >= stop:
                break
        return out
    from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait

    cancel = [threading.Event() for _ in range(n)]

    def task(i: int, budget: int | None) -> Result | None:
        def report(f: float) -> None:
            if cancel[i].is_set():
                raise _Cancelled
            done[i] = f
        try:
            return run_block(i, budget, report)
        except _Cancelled:
            return None

    with ThreadPoolExecutor(max_workers=workers) as pool:
        try:
            start = 0
            while start < n:
                wave = range(start, n if stop is None else min(n, start + workers))
                budget = None if stop is None else stop - seen
                futures = {pool.submit(task, i, budget): i for i in wave}
                pending = set(futures)
                while pending:
                    finished, pending = wait(pending, timeout=POLL,
                                             return_when=FIRST_COMPLETED)
                    for f in finished:
                        result = f.result()
                        i = futures[f]
                        if budget is not None and result is not None and \
                                _failures(result) >= budget:
                            for later in wave:
                                if later > i:
                                    cancel[later].set()
                    if progress is not None:
                        progress(fraction())
                results = {futures[f]: f.result() for f in futures}
                for i in wave:
                    kept = results[i]
                    need = None if stop is None else stop - seen
                    assert kept is not None  # (cancelled only after a block that settles)
                    ran = kept
                    if need is not None and need != budget and _failures(ran) >= need:
                        ran = run_block(i, need, None)
                    out.append(ran)
                    seen += _failures(ran)
                    if stop is not None and seen >= stop:
                        return out
                start = wave.stop
        finally:
            for c in cancel:
                c.set()
    return out

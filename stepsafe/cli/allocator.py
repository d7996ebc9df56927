"""The command's process keeps freed array memory in the heap (glibc only).

Each step of a trajectory ensemble (:mod:`stepsafe.core.ensemble`) makes array temporaries
of the batch's size, a few hundred kB for thousands of trajectories. glibc's allocator
serves blocks that large by ``mmap`` and returns them to the kernel at every ``free``, so
every temporary page-faults afresh: on the Morse scene's analysis at temperature a third of
the CPU time was the kernel's (``benchmarks/thermal.py``). The command line owns its
process, so it raises the allocator's mmap and trim thresholds (``mallopt``) once, before
any command runs; freed temporaries are then reused in place and results are unchanged.
The library leaves the allocator of a program that imports it alone.
"""

from __future__ import annotations

import ctypes
import sys

#: glibc ``mallopt`` parameters (malloc.h) and the values set (bytes).
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
TRIM_BYTES, MMAP_BYTES = 64 << 20, 32 << 20


def keep_freed_memory() -> bool:
    """On glibc, keep freed blocks up to :data:`MMAP_BYTES` in the heap.

    Returns
    -------
    bool
        Whether the thresholds were set (False off Linux or without glibc).
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        return bool(libc.mallopt(M_MMAP_THRESHOLD, MMAP_BYTES)
                    and libc.mallopt(M_TRIM_THRESHOLD, TRIM_BYTES))
    except (OSError, AttributeError):  # not glibc: its allocator is left as it is
        return False

"""Whether this process's allocator keeps freed array memory for reuse.

Work on many trajectories at once makes array temporaries of the batch's size at every
step. With glibc's default thresholds a block above 128 KiB is mapped afresh at each
allocation and page-faulted, so :mod:`stepsafe.systems.thermal.trajectories` keeps its
batches below that. A program that has made its allocator keep freed memory (the command
line does: :mod:`stepsafe.cli.allocator`) says so here, and larger batches, which cost
fewer Python operations per trajectory, are used. Nothing here touches the allocator.
"""

from __future__ import annotations

#: True once the process's allocator keeps freed blocks of a few MB for reuse (set by the
#: program that made it so).
keeps_freed = False

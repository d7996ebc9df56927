"""The command line's process raises glibc's mmap and trim thresholds (``mallopt`` accepts
both parameters), and importing the library leaves the allocator alone."""

from __future__ import annotations

import ctypes
import sys

import pytest

from stepsafe.cli import allocator


def _glibc() -> bool:
    try:
        return sys.platform.startswith("linux") and hasattr(ctypes.CDLL("libc.so.6"),
                                                            "mallopt")
    except OSError:
        return False


@pytest.mark.skipif(not _glibc(), reason="glibc's mallopt only")
def test_glibc_accepts_both_allocator_thresholds():
    assert allocator.keep_freed_memory() is True


def test_a_block_holds_its_values_and_at_least_one_row():
    from stepsafe.systems.thermal import trajectories

    assert trajectories.block_rows(100) == trajectories.BLOCK_VALUES // 100
    assert trajectories.block_rows(10 ** 9) == 1


def test_the_numeric_core_does_not_set_the_allocator():
    import stepsafe.core.ensemble as ensemble

    source = open(ensemble.__file__, encoding="utf-8").read()
    assert "mallopt" not in source and "ctypes" not in source

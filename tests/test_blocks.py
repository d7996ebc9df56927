"""Blocks of an ensemble integrated on worker threads give the results of the same blocks
run one after the other: with no stop every block's, with a stop on failures exactly
the blocks, budgets and stopping steps of the run in order (:mod:`stepsafe.core.blocks`)."""

from __future__ import annotations

import random
import time
from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support import method
from thermal_support import morse

from stepsafe.core import memory, threads
from stepsafe.core.blocks import in_order
from stepsafe.systems.thermal import trajectories
from stepsafe.systems.thermal.trajectories import run, thermal_start

STEPS = 50


@dataclass(frozen=True)
class Block:
    """What a block did: its rows' failures and the steps it ran."""

    escaped: np.ndarray
    steps: int


def integrate_block(fails: list[int], budget: int | None) -> Block:
    """A block whose row r fails at step ``fails[r]`` (0: never), stopped after the step
    at which ``budget`` rows have failed."""
    at = np.array(fails)
    end = STEPS
    failing = np.sort(at[at > 0])
    if budget is not None and failing.size >= budget:
        end = int(failing[budget - 1])
    return Block((at > 0) & (at <= end), end)


def expected_run(blocks: list[list[int]], stop: int | None) -> list[Block]:
    """The blocks run one after the other, each with the budget the ones before left."""
    out, seen = [], 0
    for fails in blocks:
        ran = integrate_block(fails, None if stop is None else stop - seen)
        out.append(ran)
        seen += int(ran.escaped.sum())
        if stop is not None and seen >= stop:
            break
    return out


failure_steps = st.lists(st.lists(st.one_of(st.just(0), st.integers(1, STEPS)),
                                  min_size=1, max_size=6), min_size=1, max_size=7)


@settings(max_examples=60, deadline=None)
@given(blocks=failure_steps, stop=st.one_of(st.none(), st.integers(1, 8)),
       workers=st.integers(1, 4), seed=st.integers(0, 2 ** 16))
def test_blocks_on_threads_give_the_run_in_order(blocks, stop, workers, seed):
    jitter = random.Random(seed)
    delays = [jitter.random() * 2e-3 for _ in blocks]
    reported = []

    def run_block(i, budget, report):
        if report is not None:
            report(0.5)
        time.sleep(delays[i])  # (blocks finish in an order of their own)
        if report is not None:
            report(1.0)
        return integrate_block(blocks[i], budget)

    got = in_order(run_block, [len(b) for b in blocks], stop, workers, reported.append)
    assert [(b.escaped.tolist(), b.steps) for b in got] == \
        [(b.escaped.tolist(), b.steps) for b in expected_run(blocks, stop)]
    assert all(0.0 <= f <= 1.0 for f in reported)


def test_an_error_in_a_block_on_a_thread_reaches_the_caller():
    def run_block(i, budget, report):
        if i == 2:
            raise ValueError("block 2")
        return integrate_block([0, 3], budget)

    with pytest.raises(ValueError, match="block 2"):
        in_order(run_block, [2] * 4, None, 2)


@pytest.mark.parametrize("stop", [None, 1, 3, 40])
def test_a_run_on_two_threads_equals_the_run_on_one_bit_for_bit(monkeypatch, stop):
    """Morse bonds near the 4:1 resonance (blocks of 9 rows, the failed rows first): the
    same failures, failed rows, stopping step, drift, its error and fluctuation."""
    pot = morse()
    start = thermal_start(pot, 0.006, 120, seed=8)
    monkeypatch.setattr(memory, "keeps_freed", True)
    monkeypatch.setattr(trajectories, "BLOCK_VALUES_KEPT", 9)
    h = [1.40784] if stop is not None else [1.40784, 1.2]
    rho = [1.0 / (1.0 - x * x / 4.0) for x in h]
    out = []
    for workers in (1, 2):
        monkeypatch.setattr(threads, "TRAJECTORY_THREADS", workers)
        out.append(run(method("verlet"), pot, start, h, 300, rho, stop_failures=stop,
                       first=[5, 77, 3]))
    assert out[0] == out[1]
    assert out[0][0].failures >= (stop or 2)  # (the test can fail: rows are lost)

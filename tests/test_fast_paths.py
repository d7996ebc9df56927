"""The shortcuts behind HMC's speed compute what the general paths compute.

* A splitting's M(z) from its four entries held apart equals the jet's M bit for bit, over
  every library splitting (compositions, processed and force-gradient ones included), both
  linear models and z from 1e-300 to 1e300.
* The bracket narrowing used by the step searches returns a point where the function is
  still >= 0 within the tolerance of a sign change, for hostile monotone functions.
* Lumping the smallest energy errors by a partition gives the acceptance that a full sort
  gives.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support import method

from stepsafe.core import hmc as H
from stepsafe.core.roots import narrowed
from stepsafe.core.transfer import transfer_jet, transfer_matrix
from stepsafe.methods.library import builtin_names
from stepsafe.methods.tableaux import Composition, Processed, Splitting


def _splittings() -> list[str]:
    out = []
    for name in builtin_names(single_force=True):
        try:
            m = method(name)
        except Exception:  # families need a stage count
            continue
        if isinstance(m, (Splitting, Processed)) or (
                isinstance(m, Composition) and isinstance(m.flattened().base, Splitting)):
            out.append(name)
    return out


@pytest.mark.parametrize("name", _splittings())
def test_splitting_matrix_is_the_jets_bit_for_bit(name):
    m = method(name)
    rng = np.random.default_rng(len(name))
    z = np.concatenate([np.geomspace(1e-300, 1e300, 600), rng.uniform(0, 6, 400), [0.0]])
    for model in ("oscillator", "inverted"):
        with np.errstate(all="ignore"):
            fast = transfer_matrix(m, z, model)
            slow = transfer_jet(m, z, model, scale=False, order=0).M
        assert np.array_equal(fast, slow, equal_nan=True), (name, model)


@settings(max_examples=60, deadline=None)
@given(root=st.floats(1e-6, 0.999999), power=st.floats(0.05, 8.0),
       scale=st.floats(-200, 200), rtol=st.sampled_from([1e-3, 1e-6, 1e-9]))
def test_narrowing_stops_within_the_tolerance_of_the_sign_change(root, power, scale, rtol):
    """f decreasing with its sign change at ``root`` in (0, 1), as flat or steep as a power
    makes it, at any scale of its values."""
    size = 10.0 ** scale

    def f(x):
        return size * (root ** power - x ** power)

    lo = narrowed(f, 0.0, f(0.0), 1.0, f(1.0), rtol)
    assert f(lo) >= 0
    assert root - lo <= rtol * 1.0 + 1e-15


def test_lumped_acceptance_is_the_sorted_ones():
    rng = np.random.default_rng(4)
    errors = rng.exponential(1e-3, 6000) * rng.uniform(0, 1, 6000) ** 8
    counts = rng.integers(1, 4, 6000).astype(float)
    got = H.acceptances(errors[None, :], counts)[0]
    order = np.argsort(errors, kind="stable")  # the reference lumps the sorted smallest
    e, c = errors[order], counts[order]
    a, b = H._weights(e)
    cut = e.size - H.MAX_EXACT_MODES
    mean_g = float(np.sum(c[:cut] * (a[:cut] + b[:cut])))
    var_g = float(np.sum(c[:cut] * 2.0 * (a[:cut] ** 2 + b[:cut] ** 2)))
    want = H._gil_pelaez(a[None, cut:], b[None, cut:], c[cut:], np.array([mean_g]),
                         np.array([var_g]))[0]
    assert got.approximate
    assert got.rate == pytest.approx(want, abs=1e-13)


@pytest.mark.parametrize("name, steps, jitter, h", [
    ("bcss2", None, 0.1, 0.9), ("bcss3", None, 0.05, 1.9), ("verlet", 20, 0.1, 0.6),
    ("bcss2", 15, 0.05, 1.1)])
def test_narrow_jitter_on_few_panels_is_exact_to_1e7(name, steps, jitter, h):
    """Panels in proportion to the jitter: against the midpoint rule on 8000 steps of the
    exact fixed-step acceptance of several modes."""
    m = method(name)
    betas = np.array([0.3, 0.7, 1.0, 1.3, 1.6, 2.0])
    n = 8000
    hs = h * (1.0 + jitter * ((np.arange(n) + 0.5) / n * 2 - 1))
    errs = H.errors_after(H.one_step(m, np.outer(hs, betas).ravel()), steps).reshape(n, -1)
    rates = [a.rate for a in H.acceptances(errs, np.ones(betas.size))]
    got = H.acceptance_at(m, betas, h, H.Trajectory(steps=steps, jitter=jitter))
    assert 0.2 < got.rate < 0.999
    assert not got.approximate and abs(got.rate - np.mean(rates)) < 1e-7, \
        (got.rate, np.mean(rates))

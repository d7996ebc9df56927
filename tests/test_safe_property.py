"""Never a false SAFE: whenever check_step says safe, 50-digit arithmetic agrees.

Generated cases (hypothesis): built-in methods, Gauss/Lobatto members, random consistent
and inconsistent splittings and random symplectic PRK tableaux; one to four modes of every
model with frequencies spread over 12 decades; steps from 1e-9 to 1e9 in z; margins. For
a SAFE verdict every mode's whole range ``[beta h, beta h / margin]`` must lie in the
preserved set: checked at 50 digits with :mod:`stepsafe.reference.highprec` (stage equations and
drift/kick products in mpmath, sharing no code with the float path) at the ends and at
interior points, and no boundary may lie in between (the float region's claim, here
re-derived from sign changes of the 50-digit constraints on a sub-grid).
"""

from __future__ import annotations

import math

import mpmath as mp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from support import method

from stepsafe.core.advice import Modes, check_step
from stepsafe.methods.exact import high_precision
from stepsafe.methods.tableaux import Composition, PartitionedRK, RungeKutta, Splitting
from stepsafe.reference import highprec as R

DPS = 50
SETTINGS = settings(max_examples=60, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
BUILTIN = ["verlet", "pefrl", "yoshida4", "bcss3", "mclachlan2-min", "kahan-li6", "ruth3",
           "symplectic-euler", "midpoint", "blanes-moan6"]
MODEL_NAMES = ("oscillator", "saddle", "inverted", "saddle-p")
#: |det M - 1| allowed: rounding of symplectic coefficients gives ~1e-16 times the size of
#: M's entries; a method that is not symplectic is off by far more at any z it is checked
DET_TOL = 1e-6


def _mp_function(m):
    """``Mfun(z, model)`` at the working precision: from the method's own exact definition
    where it has one (a Gauss or Lobatto member, whose float coefficients are symplectic only
    to rounding and so lose the oscillator's type near z = 1e9), else from the float
    coefficients taken as exact."""
    if getattr(m, "exact", None) is not None:
        return high_precision(m)
    if isinstance(m, Composition):
        flat = m.flattened()
        inner = _mp_function(flat.base)
        weights = [mp.mpf(float(g)) for g in flat.weights]
        return lambda z, model: R.transfer_matrix_composition(lambda x: inner(x, model),
                                                              weights, z)
    if isinstance(m, Splitting):  # the saddle models go through its PRK form (as the float
        d, k = [mp.mpf(float(x)) for x in m.drift], [mp.mpf(float(x)) for x in m.kick]
        saddle = _mp_function(m.as_prk())  # path does: the sums may differ by rounding)
        return lambda z, model: (saddle(z, model) if model.startswith("saddle") else
                                 R.transfer_matrix_splitting(d, k, z, model))
    prk = m.as_prk() if isinstance(m, RungeKutta) else m
    rows = [[[mp.mpf(float(x)) for x in r] for r in A] for A in (prk.A_q, prk.A_p)]
    return R.prk_transfer(rows[0], [mp.mpf(float(x)) for x in prk.b_q], rows[1],
                          [mp.mpf(float(x)) for x in prk.b_p])


def _preserved(Mfun, z, model) -> bool:
    """Type and orientation of the flow (the reference's constraints, all > 0), and
    det M = 1. Float coefficients are symplectic only to rounding, so det M = 1 is demanded
    to DET_TOL, not to 50 digits; that moves the boundaries by ~1e-16, inside every
    stated uncertainty."""
    try:
        M = Mfun(mp.mpf(z), model)
    except ZeroDivisionError:
        return False  # a pole: no unique step
    size = max(abs(x) for x in M)
    if size > 1:  # det M cancels products of size^2: that many more digits
        with mp.workdps(mp.mp.dps + 2 * int(mp.log10(size)) + 10):
            det = mp.det(Mfun(mp.mpf(z), model))
    else:
        det = mp.det(M)
    if not abs(det - 1) <= DET_TOL:
        return False  # a sink or a source: not the flow's type, whatever its trace
    if model == "saddle-p":  # H = -beta p q: p expands
        return bool(M[1, 1] > 1 > M[0, 0] > 0)
    return all(g > 0 for g in R.constraints(M, model))


def _confirm(m, modes: Modes, h: float, margin: float) -> None:
    Mfun = _mp_function(m)
    with mp.workdps(DPS):
        for model, betas in modes.betas.items():
            for beta in np.unique(betas):
                if beta == 0:
                    continue
                lo, hi = beta * h, beta * h / margin
                zs = {lo, hi} | ({math.sqrt(lo * hi)} if hi > lo else set())
                if hi > lo:  # a sub-grid: the status must not change inside
                    zs |= {lo + (hi - lo) * k / 8 for k in range(1, 8)}
                for z in sorted(zs):
                    assert _preserved(Mfun, z, model), (m.name, model, beta, h, margin, z)


@st.composite
def random_splitting(draw):
    n = draw(st.integers(1, 4))
    coef = st.floats(-1.5, 1.5, allow_nan=False)
    a = np.array(draw(st.lists(coef, min_size=n, max_size=n)))
    k = np.array(draw(st.lists(coef, min_size=n, max_size=n)))
    if draw(st.booleans()):  # consistent, and equal sums (a PRK form exists)
        a[-1] += 1.0 - a.sum()
        k[-1] += 1.0 - k.sum()
        return Splitting(np.append(a, 0.0), k, name="random-splitting")
    k[-1] += a.sum() - k.sum()  # equal sums only
    return Splitting(np.append(a, 0.0), k, name="random-splitting")


@st.composite
def random_prk(draw, symplectic: bool = True):
    s = draw(st.integers(1, 3))
    coef = st.floats(-1.0, 1.0, allow_nan=False)
    A_q = np.array(draw(st.lists(st.lists(coef, min_size=s, max_size=s), min_size=s,
                                 max_size=s)))
    b = np.array(draw(st.lists(st.floats(0.1, 1.0), min_size=s, max_size=s)))
    b = b / b.sum()
    A_p = b[None, :] * (1.0 - A_q.T / b[:, None])
    if not symplectic:
        A_p = A_p + np.array(draw(st.lists(st.lists(st.floats(0.01, 0.5), min_size=s,
                                                    max_size=s), min_size=s, max_size=s)))
    return PartitionedRK(A_q, b, A_p, b.copy(), name="random-prk")


@st.composite
def scaled_tableau(draw, lowest: int = -14, highest: int = 2):
    """RK4, Gauss s = 2, a random symplectic PRK or a random PRK that is not symplectic,
    with every coefficient times 10^k: the same method at another step, symplectic iff
    unscaled (RK4 times 1e-7 is not symplectic at any step)."""
    base = draw(st.one_of(st.sampled_from([("rk4",), ("gauss", 2)]).map(lambda a: method(*a)),
                          random_prk(), random_prk(symplectic=False)))
    scale = 10.0 ** draw(st.integers(lowest, highest))
    prk = base.as_prk()
    return PartitionedRK(prk.A_q * scale, prk.b_q * scale, prk.A_p * scale, prk.b_p * scale,
                         name="scaled")


methods = st.one_of(
    st.sampled_from(BUILTIN).map(method),
    st.tuples(st.sampled_from(["gauss", "lobatto3ab"]), st.integers(2, 5)).map(
        lambda fs: method(*fs)),
    random_splitting(),
    random_prk(),
)


@st.composite
def scenes(draw):
    m = draw(methods)
    n = draw(st.integers(1, 4))
    log_beta = st.floats(-6.0, 6.0)
    pairs = [(10 ** draw(log_beta), draw(st.sampled_from(MODEL_NAMES))) for _ in range(n)]
    # a step that puts the fastest mode anywhere from z = 1e-9 to z = 1e9, often near O(1)
    top = max(b for b, _ in pairs)
    z_top = 10 ** draw(st.one_of(st.floats(-9.0, 9.0), st.floats(-0.7, 0.8)))
    margin = draw(st.sampled_from([1.0, 0.9, 0.5]))
    return m, Modes.from_pairs(pairs), z_top / top, margin


@pytest.mark.slow
@SETTINGS
@given(scenes())
def test_every_safe_verdict_holds_at_50_digits(case):
    m, modes, h, margin = case
    result = check_step(m, modes, h, margin)
    if result.safe:
        _confirm(m, modes, h, margin)


@SETTINGS
@given(st.sampled_from(BUILTIN + ["gauss:3", "lobatto3ab:4"]),
       st.floats(-8.0, 12.0), st.sampled_from(MODEL_NAMES))
def test_safe_at_any_scale_of_z(name, log_z, model):
    """One mode, z = beta h from 1e-8 to 1e12 (beta 1e6, so h spans 20 decades)."""
    family, _, s = name.partition(":")
    m = method(family, int(s)) if s else method(name)
    beta = 1e6
    h = 10 ** log_z / beta
    modes = Modes.from_pairs([(beta, model)])
    result = check_step(m, modes, h)
    if result.safe:
        _confirm(m, modes, h, 1.0)
    else:  # and an UNSAFE verdict at small z, where every consistent method is safe,
        # would be a bug too
        assert log_z > -6 or model not in ("oscillator", "inverted"), result.failures


@settings(SETTINGS, max_examples=25)
@given(scaled_tableau(-14, -3), st.floats(-1.0, 0.6),
       st.sampled_from(["oscillator", "inverted"]), st.sampled_from(["structure", "stability"]))
def test_a_scaled_tableau_is_safe_only_where_the_unscaled_one_is(m, log_z, model, criterion):
    """Every coefficient times 10^k (k down to -14) at a step where the unscaled method's z
    is 0.1 to 4: RK4 there is a sink, never SAFE, however small its coefficients."""
    beta = 1e3
    h = 10 ** log_z / float(np.abs(m.b_q).max()) / beta
    modes = Modes.from_pairs([(beta, model)])
    if check_step(m, modes, h, criterion=criterion).safe:
        _confirm(m, modes, h, 1.0)


def _stable_type(Mfun, z, model) -> bool:
    """The flow's type only (``--criterion stability``): elliptic for vibrations, hyperbolic
    with positive multipliers (tr M > 2) for saddles and barriers."""
    try:
        M = Mfun(mp.mpf(z), model)
    except ZeroDivisionError:
        return False
    tr = M[0, 0] + M[1, 1]
    return bool(abs(tr) < 2) if model == "oscillator" else bool(tr > 2)


@pytest.mark.slow
@SETTINGS
@given(scenes())
def test_every_stable_verdict_holds_at_50_digits(case):
    """Under --criterion stability a SAFE verdict keeps the type at 50 digits over the
    whole margin range, and whatever is safe under structure is safe under stability."""
    m, modes, h, margin = case
    result = check_step(m, modes, h, margin, criterion="stability")
    if check_step(m, modes, h, margin).safe:
        assert result.safe
    if not result.safe:
        return
    Mfun = _mp_function(m)
    with mp.workdps(DPS):
        for model, betas in modes.betas.items():
            for beta in np.unique(betas[betas > 0]):
                lo, hi = beta * h, beta * h / margin
                zs = {lo, hi} | {lo + (hi - lo) * k / 8 for k in range(1, 8)}
                for z in sorted(zs):
                    assert _stable_type(Mfun, z, model), (m.name, model, beta, h, margin, z)

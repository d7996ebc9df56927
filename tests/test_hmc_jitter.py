"""Jittered HMC steps stay within the stability limit, checked against an independent
sampler and the 50-digit limit.

A sampler with jitter J draws each step from ``h (1 - J, 1 + J)``. The step at target keeps
``h (1 + J)`` within the stability limit unless asked otherwise (``allow_unstable_jitter``):

* an HMC simulation written here (its own drift/kick loop from the published coefficients,
  proposals drawn from the target, a fixed seed) counts divergent transitions in Stan's
  sense, an energy error above 1000 or not finite;
* the step at target over a generated set of targets (scales 1e-250 to 1e250, spreads,
  jitters, trajectory lengths) times ``1 + J``, as float64 computes it, is within the first
  z where ``|tr M| > 2`` at 50 digits;
* the fraction of unstable draws that a step past the cap has, as noted, against the same
  sampler, and for any step, jitter and limit against the 50-digit share: 0 exactly when
  the longest draw as float64 computes it is within the limit.
"""

from __future__ import annotations

import json

import mpmath as mp
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from stepsafe import hmc
from stepsafe.api.hmc import unstable_fraction
from stepsafe.exceptions import StepsafeError

#: Stan's threshold of a divergent transition: an energy error above this.
DIVERGENT = 1000.0


def _sequence(name, num):
    """The kick/drift sequence of ``name`` from its published coefficients, in the number
    type ``num`` (float or mp.mpf): Verlet (kick-drift-kick), Blanes, Casas & Sanz-Serna
    (2014) 2-stage with b = 0.21178 and 3-stage with b = 0.11888010966548,
    a = 0.29619504261126."""
    one = num(1)
    half = one / 2
    if name == "verlet":
        return [("kick", half), ("drift", one), ("kick", half)]
    if name == "bcss2":
        b = num("0.21178")
        return [("kick", b), ("drift", half), ("kick", one - 2 * b), ("drift", half),
                ("kick", b)]
    b, a = num("0.11888010966548"), num("0.29619504261126")
    return [("kick", b), ("drift", a), ("kick", half - b), ("drift", one - 2 * a),
            ("kick", half - b), ("drift", a), ("kick", b)]


def _divergent(name, sigmas, h, steps, jitter, proposals, seed):
    """How many of ``proposals`` HMC trajectories diverge (energy error above
    :data:`DIVERGENT`, or not finite) on the Gaussian of standard deviations ``sigmas``
    (unit mass), each started from an exact draw of the target and its momentum with its own
    step ``h (1 + jitter u)``, u uniform in (-1, 1), for ``steps`` steps."""
    rng = np.random.default_rng(seed)
    precision = 1.0 / np.asarray(sigmas) ** 2
    q = rng.standard_normal((proposals, precision.size)) / np.sqrt(precision)
    p = rng.standard_normal((proposals, precision.size))
    step = h * (1.0 + jitter * (2.0 * rng.random((proposals, 1)) - 1.0))
    start = 0.5 * (q * q * precision).sum(axis=1) + 0.5 * (p * p).sum(axis=1)
    with np.errstate(all="ignore"):
        for _ in range(steps):
            for kind, c in _sequence(name, float):
                if kind == "kick":
                    p = p - c * step * precision * q
                else:
                    q = q + c * step * p
        error = 0.5 * (q * q * precision).sum(axis=1) + 0.5 * (p * p).sum(axis=1) - start
    return int(np.count_nonzero(~(error <= DIVERGENT)))


def _unstable_share(h, jitter, limit):
    """The share of steps uniform in ``h (1 - jitter, 1 + jitter)`` beyond ``limit``."""
    return min(max((h * (1 + jitter) - limit) / (2 * jitter * h), 0.0), 1.0)


def _half_trace(name, z):
    """``tr M / 2`` of the oscillator's one-step matrix at z, at the working precision."""
    x = mp.matrix([[1, 0], [0, 1]])
    for kind, c in _sequence(name, mp.mpf):
        factor = (mp.matrix([[1, c * z], [0, 1]]) if kind == "drift" else
                  mp.matrix([[1, 0], [-c * z, 1]]))
        x = factor * x
    return (x[0, 0] + x[1, 1]) / 2


_LIMITS: dict[str, mp.mpf] = {}


def _stability_limit(name):
    """The first z > 0 where ``|tr M / 2|`` exceeds 1 by more than 1e-20, at 50 digits: a
    grid of step 1/512 up to 8, then bisection. A smaller excess is the rounding of the
    published coefficients, not an exit (bcss3's 14-digit coefficients dip 3.2e-27 past -1
    over a width of 1e-13 at z = 2.97632, where the exact method's M = -I; the rule both
    ``hmc`` and ``design`` state); a real exit grows linearly, by ~1e-3 at the first grid
    point past it, so the bisection locates it to ~1e-20."""
    if name not in _LIMITS:
        with mp.workdps(50):
            def out(z):
                return abs(_half_trace(name, z)) - 1 > mp.mpf("1e-20")

            lo = mp.mpf(0)
            hi = next(mp.mpf(k) / 512 for k in range(1, 8 * 512 + 1) if out(mp.mpf(k) / 512))
            lo = hi - mp.mpf(1) / 512
            for _ in range(120):
                mid = (lo + hi) / 2
                lo, hi = (lo, mid) if out(mid) else (mid, hi)
            _LIMITS[name] = lo
    return _LIMITS[name]


def test_the_50_digit_limits_are_the_published_ones():
    """The reference limits of this file: Verlet's z = 2 and the thresholds the BCSS methods
    ship (checked here, since the tests below rest on them)."""
    with mp.workdps(50):
        assert abs(_stability_limit("verlet") - 2) < mp.mpf("1e-19")
        assert abs(_stability_limit("bcss2") - mp.mpf("2.63422545")) < 1e-8
        assert abs(_stability_limit("bcss3") - mp.mpf("4.66184608")) < 1e-8
        # the rounding gap the rule passes over is there, and below the threshold
        dip = min(_half_trace("bcss3", mp.mpf("2.9763246405798") + k * mp.mpf("1e-15"))
                  for k in range(-100, 101)) + 1
        assert -mp.mpf("1e-20") < dip < 0


SIGMAS = np.linspace(0.1, 1.0, 10)


def test_default_jittered_step_gives_no_divergent_transitions():
    """bcss3 on ten standard deviations 0.1 .. 1, L = 20, jitter 0.2. Without the cap the
    step at target would be 0.397081, whose longest draws pass the stability limit 0.466185
    (h (1 + J) = 1.022 times it): 6.5% of the draws, and nearly as many trajectories
    diverge while the predicted acceptance is 0.84 (the step reaching the target for every
    L; for L = 20 alone it is larger still). With the cap h (1 + J) is within the
    limit: 20000 proposals of the sampler above give at most a few divergent transitions
    (the draws next to the stability edge, where L = 20 steps still give an energy error
    above 1000 for about 3e-5 of them, 32 in 10^6 with this sampler), where the uncapped
    step gives over a thousand."""
    row = hmc(["bcss3"], sigma=list(SIGMAS), trajectory_steps=20, jitter=0.2).rows[0]
    with mp.workdps(50):
        assert mp.mpf(row.h_target * 1.2) * 10 <= _stability_limit("bcss3")
    assert any("capped" in note for note in row.notes)
    assert _divergent("bcss3", SIGMAS, row.h_target, 20, 0.2, 20000, seed=3) <= 4
    loose = hmc(["bcss3"], sigma=list(SIGMAS), trajectory_steps=20, jitter=0.2,
                allow_unstable_jitter=True, target_for_every_length=True).rows[0]
    share = _unstable_share(loose.h_target, 0.2, loose.stability_h)
    assert 0.05 < share < 0.08
    assert any(f"{100 * share:.3g}% of the jittered steps" in note for note in loose.notes)
    # every divergent transition comes from an unstable draw, and most unstable draws
    # diverge within L = 20 steps (those just past the edge grow too slowly)
    n = 20000
    diverged = _divergent("bcss3", SIGMAS, loose.h_target, 20, 0.2, n, seed=4) / n
    assert 0.8 * share < diverged < share + 4 * np.sqrt(share * (1 - share) / n)


@settings(max_examples=8, deadline=None)
@given(exponent=st.floats(-250.0, 250.0), spread=st.floats(1.0, 30.0),
       count=st.integers(1, 5), jitter=st.floats(0.01, 0.9),
       steps=st.none() | st.integers(1, 60), name=st.sampled_from(["verlet", "bcss2", "bcss3"]))
# h (1 + J) within the limit in float64 while limit / h rounds below 1 + J: the fraction of
# unstable draws must come from the computed longest draw, not from limit / h
@example(exponent=-159.0, spread=1.0, count=1, jitter=0.63999, steps=None, name="bcss3")
def test_step_at_target_times_one_plus_jitter_is_within_the_50_digit_limit(
        exponent, spread, count, jitter, steps, name):
    sigmas = list(10.0 ** exponent * np.geomspace(1.0, spread, count))
    row = hmc([name], sigma=sigmas, trajectory_steps=steps, jitter=jitter).rows[0]
    assert row.h_target is not None
    longest = row.h_target * (1.0 + jitter)  # as a sampler computes its longest draw
    with mp.workdps(50):
        assert mp.mpf(longest) / mp.mpf(min(sigmas)) <= _stability_limit(name)
    assert _unstable_share(row.h_target, jitter, row.stability_h) == 0.0
    assert not any("pass the stability limit" in note for note in row.notes)


@given(h=st.floats(1e-300, 1e300), jitter=st.floats(0.001, 0.999),
       ratio=st.floats(0.0, 3.0), ulps=st.none() | st.integers(-3, 3))
# h * (1 + J) equals the limit while limit / h rounds below 1 + J
@example(h=2.842606405057488e-159, jitter=0.63999, ratio=0.0, ulps=0)
# h * (1 + J) overflows float64
@example(h=1e308, jitter=0.9, ratio=1.5, ulps=None)
def test_unstable_share_is_0_exactly_when_the_computed_longest_draw_is_within(
        h, jitter, ratio, ulps):
    """The share of draws h (1 + J u), |u| <= 1, past a limit: 0 exactly when the longest
    draw as float64 computes it, h * (1 + J), is within the limit (the rule the capped step
    keeps), 1 exactly when the shortest h * (1 - J) is past it, and otherwise positive and
    the 50-digit share (h (1 + J) - limit) / (2 J h) within a few roundings of h (1 + J).
    The limit is drawn anywhere, or within a few float64 steps of the longest draw."""
    longest = h * (1.0 + jitter)
    if ulps is None:
        limit = h * ratio
    else:
        limit = longest
        for _ in range(abs(ulps)):
            limit = float(np.nextafter(limit, np.sign(ulps) * np.inf))
    share = unstable_fraction(h, jitter, limit)
    assert (share == 0.0) == (longest <= limit)
    assert (share == 1.0) == (h * (1.0 - jitter) > limit)
    with mp.workdps(50):
        exact = min(max((mp.mpf(h) * (1 + mp.mpf(jitter)) - mp.mpf(limit))
                        / (2 * mp.mpf(jitter) * mp.mpf(h)), 0), 1)
        if 0.0 < share < 1.0:
            rounding = 4 * 2.0 ** -52 * (1 + jitter) / (2 * jitter)
            assert abs(share - exact) <= rounding


def test_unstable_jitter_is_said_in_text_json_and_help(run):
    args = ["hmc", *[a for s in SIGMAS for a in ("--sigma", repr(float(s)))], "--steps", "20",
            "--jitter", "0.2", "--methods", "bcss3"]
    code, out, err = run(*args)
    assert code == 0, err
    assert "keeps h(1 + 0.2) within the stability limit" in out and "capped" in out
    code, out, err = run(*args, "--allow-unstable-jitter", "--json")
    assert code == 0, err
    data = json.loads(out)
    assert data["allow_unstable_jitter"] is True
    assert any("pass the stability limit" in note for note in data["methods"][0]["notes"])
    code, out, _ = run(*args, "--json")
    assert json.loads(out)["allow_unstable_jitter"] is False
    code, out, _ = run("hmc", "--help")
    assert "--allow-unstable-jitter" in out and "no jittered step" in " ".join(out.split())
    with pytest.raises(StepsafeError, match="allow_unstable_jitter"):
        hmc(["verlet"], sigma=[1.0], jitter=0.1, allow_unstable_jitter="yes")

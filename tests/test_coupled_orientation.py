"""The coupled analysis decides the orientation of hyperbolic pairs, as the 1-dof models do.

Given as a system, a 1-dof saddle or barrier (coupled or not) never gets a larger safe step
than its test model: ``system: {hessian: [[0, 1], [1, 0]]}`` (H = q p) with pefrl at
h = 1.65, where q contracts and p expands (the saddle reversed), is UNSAFE as the same H
given as ``modes: saddle`` is from 1.6399, and a barrier with a 1e-9 q-p coupling is not SAFE
where its uncoupled twin is not.
"""

from __future__ import annotations

import numpy as np
import pytest

import stepsafe
from stepsafe.methods.library import FAMILIES, builtin_names

LIBRARY = [n for n in builtin_names(single_force=True) if n not in FAMILIES]


def _h_max(report) -> float:
    return np.inf if report.h_max is None else report.h_max


@pytest.mark.parametrize("name", LIBRARY)
def test_hessian_saddle_and_barrier_never_beyond_their_models(name):
    method = stepsafe.method(name)
    cases = [({"hessian": [[0.0, 1.0], [1.0, 0.0]]}, {"saddle": [1.0]}),
             ({"hessian": [[-1.0, 1e-12], [1e-12, 1.0]]}, {"inverted": [1.0]})]
    for system, modes in cases:
        try:
            model = stepsafe.advise(method, modes=modes)
        except stepsafe.StepsafeError:
            continue  # no form of this method for the model
        if getattr(method.tableau, "force_gradient", False):
            # force-gradient methods need H = T(p) + V(q): a q-p coupling is refused
            with pytest.raises(stepsafe.StepsafeError, match="separable"):
                stepsafe.advise(method, system=system)
            continue
        coupled = stepsafe.advise(method, system=system)
        assert _h_max(coupled) <= _h_max(model) * (1 + 1e-8) + 1e-300, (name, system)
        h = _h_max(coupled)
        if np.isfinite(h) and h > 0:
            assert stepsafe.check(method, 0.999 * h, system=system).safe


def test_a_reversed_saddle_given_as_a_hessian_is_unsafe_where_its_model_is():
    """H = q p with pefrl: unsafe at h = 1.65, and h_max is the saddle model's 1.6399."""
    pefrl = stepsafe.method("pefrl")
    system = {"hessian": [[0.0, 1.0], [1.0, 0.0]]}
    assert not stepsafe.check(pefrl, 1.65, system=system).safe
    assert stepsafe.advise(pefrl, system=system).h_max == pytest.approx(1.639907998996,
                                                                         rel=1e-9)


KREIN = [[0.860544, None, -0.420883, 0.0], [None, -1.070946, 0.0, 0.131125],
         [-0.420883, 0.0, 1.640329, None], [0.0, 0.131125, None, -0.527871]]


def _krein_system(eps: float) -> dict:
    """Two 1-dof blocks with elliptic pairs of opposite Krein sign whose pefrl rotation
    angles cross at h0 = 2.48728162988 (50 digits), coupled by eps."""
    return {"hessian": [[eps if x is None else x for x in row] for row in KREIN]}


@pytest.mark.parametrize("eps", [1e-9, 1e-11, 1e-6, 1e-2])
def test_krein_collision_is_never_safe(eps):
    """Where the multipliers of opposite Krein sign meet, any coupling opens a loxodromic
    band (|nu| > 1): the crossing is not certified, and the interval from 0 ends before
    it; below that, the map is elliptic (float64 eigenvalues on the circle)."""
    from stepsafe.systems.coupled import one_step_matrix

    pefrl = stepsafe.method("pefrl")
    system = _krein_system(eps)
    assert not stepsafe.check(pefrl, 2.4872816298802696, system=system).safe
    h_max = stepsafe.advise(pefrl, system=system).h_max
    assert h_max < 2.4872816298802696
    S = np.array(system["hessian"])
    for h in np.linspace(0.05, h_max, 60)[:-1]:
        nu = np.linalg.eigvals(one_step_matrix(pefrl.tableau, S, h))
        assert np.abs(nu).max() - 1 < 1e-12, (eps, h)


@pytest.mark.parametrize("scale", [1e-200, 1e-40, 1e40, 1e200])
@pytest.mark.parametrize("name", ["pefrl", "yoshida4", "bcss2"])
def test_coupled_saddle_at_every_scale(name, scale):
    """S scaled by c: the same verdicts at h / c (only z = beta h matters), for the
    coupled saddle whose reversal the orientation check catches."""
    method = stepsafe.method(name)
    base = {"hessian": [[0.0, 1.0], [1.0, 0.0]]}
    scaled = {"hessian": [[0.0, scale], [scale, 0.0]]}
    h_max = stepsafe.advise(method, system=base).h_max
    assert stepsafe.advise(method, system=scaled).h_max == pytest.approx(h_max / scale,
                                                                        rel=1e-9)
    for factor in (0.999, 1.001, 1.01):
        assert (stepsafe.check(method, factor * h_max / scale, system=scaled).safe
                == stepsafe.check(method, factor * h_max, system=base).safe)
    assert not stepsafe.check(method, 1.001 * h_max / scale, system=scaled).safe

"""stepsafe's methods and step advice run by BlackJAX (``pip install 'stepsafe[blackjax]'``).

* Every symmetric splitting of the library and designed members, exported as BlackJAX
  coefficient lists: one BlackJAX step on a 1-D Gaussian is stepsafe's transfer matrix
  M(z) to 1e-14.
* BlackJAX's own HMC kernel with the exported integrator and the recommended step: on a
  Gaussian its measured acceptance matches the exact Gaussian prediction of
  :mod:`stepsafe.core.hmc` within 3 standard errors (with and without a jittered step);
  on the banana it matches stepsafe's estimate on the target within 3 standard errors.

Without jax and blackjax these tests are skipped; the refusal that names the extra is
tested either way.
"""

from __future__ import annotations

import importlib.util
import sys

import numpy as np
import pytest
from support import method

from stepsafe.core import hmc as gaussian
from stepsafe.core.design import family_member
from stepsafe.core.hmc import Trajectory
from stepsafe.core.hmc_target.statistics import chain_mean
from stepsafe.core.transfer import transfer_matrix
from stepsafe.exceptions import StepsafeError
from stepsafe.methods.families import is_symmetric
from stepsafe.methods.library import builtin_names
from stepsafe.methods.tableaux import Composition, Processed, Splitting
from stepsafe.systems import blackjax_bridge as bridge


def test_a_missing_blackjax_is_refused_naming_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "blackjax", None)  # import blackjax raises ImportError
    with pytest.raises(StepsafeError, match=r"pip install 'stepsafe\[blackjax\]'"):
        bridge.integrator("verlet")


def _exportable() -> list[str]:
    names = []
    for name in builtin_names(single_force=True):
        try:
            m = method(name)
        except StepsafeError:
            continue
        flat = m.as_splitting() if isinstance(m, Composition) and isinstance(
            m.flattened().base, Splitting) else m
        if isinstance(flat, Splitting) and not flat.force_gradient and is_symmetric(flat):
            names.append(name)
    return names


EXPORTABLE = _exportable()


def test_the_library_has_symmetric_splittings_to_export():
    assert {"verlet", "bcss2", "bcss3", "mclachlan2-min", "yoshida4", "pefrl"} <= set(
        EXPORTABLE)


@pytest.mark.parametrize("name", ["blanes-casas-ros764", "chin-4a", "symplectic-euler",
                                  "rk4", "midpoint"])
def test_what_blackjax_cannot_run_is_refused(name):
    m = method(name)
    assert isinstance(m, Processed) or not isinstance(m, Splitting) or m.force_gradient \
        or not is_symmetric(m)
    with pytest.raises(StepsafeError):
        bridge.coefficients(m)


def test_coefficient_lists_start_with_a_kick_and_are_palindromes():
    for name in EXPORTABLE:
        c = bridge.coefficients(method(name)).coefficients
        assert len(c) % 2 == 1
        np.testing.assert_allclose(c, c[::-1], rtol=1e-12, atol=1e-15)
        # kicks (even places) and drifts (odd places) each sum to 1
        assert sum(c[0::2]) == pytest.approx(1.0, abs=1e-12)
        assert sum(c[1::2]) == pytest.approx(1.0, abs=1e-12)


#: the tests that run jax and blackjax (skipped cleanly without them)
needs_blackjax = pytest.mark.skipif(
    importlib.util.find_spec("jax") is None or importlib.util.find_spec("blackjax") is None,
    reason="jax and blackjax are not installed (pip install 'stepsafe[blackjax]')")


def _jax():
    import jax

    return jax


def _one_step_matrix(factory, z: float) -> np.ndarray:
    """The 2x2 matrix of one BlackJAX step at step size z on log pi = -q^2/2 (unit mass),
    column by column from (q, p) = (1, 0) and (0, 1), in float64."""
    jax = _jax()
    import jax.numpy as jnp
    from blackjax.mcmc.integrators import new_integrator_state
    from blackjax.mcmc.metrics import default_metric

    with jax.enable_x64(True):
        def logdensity(q):
            return -0.5 * jnp.sum(q * q)

        step = factory(logdensity, default_metric(jnp.ones(1)).kinetic_energy)
        cols = []
        for q, p in ((1.0, 0.0), (0.0, 1.0)):
            out = step(new_integrator_state(logdensity, jnp.array([q]), jnp.array([p])), z)
            cols.append([float(out.position[0]), float(out.momentum[0])])
    return np.array(cols).T


DESIGNED = [family_member(2, (0.2093,), "designed-b"), family_member(3, (0.11, 0.29),
                                                                   "designed-ba")]


@pytest.mark.parametrize("m", [method(n) for n in EXPORTABLE] + DESIGNED,
                         ids=EXPORTABLE + ["designed-2", "designed-3"])
@pytest.mark.blackjax
@needs_blackjax
def test_one_blackjax_step_is_the_transfer_matrix(m):
    factory = bridge.integrator(m)
    for z in (0.05, 0.7, 1.9):
        got = _one_step_matrix(factory, z)
        want = transfer_matrix(m, [z])[0]
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-14 * max(1.0, np.abs(want).max()))


@pytest.mark.parametrize("stages", [2, 3])
def test_a_design_exports_its_member_from_the_report_and_its_method_file(tmp_path, stages):
    """The report of stepsafe.design and the method file it writes export the same list,
    the designed member's kick/drift coefficients in BlackJAX's order, every digit."""
    from stepsafe import design

    report = design(sigma=[1.0, 0.5], step=0.5, stages=stages)
    path = tmp_path / "mine.yaml"
    path.write_text(report.method_file)
    from_report, from_file = bridge.coefficients(report), bridge.coefficients(str(path))
    p = report.params
    want = ((p["b"], 0.5, 1 - 2 * p["b"], 0.5, p["b"]) if stages == 2 else
            (p["b"], p["a"], 0.5 - p["b"], 1 - 2 * p["a"], 0.5 - p["b"], p["a"], p["b"]))
    assert from_report.coefficients == pytest.approx(want, rel=1e-15, abs=1e-16)
    assert from_file.coefficients == pytest.approx(want, rel=1e-15, abs=1e-16)
    assert from_report.gradients_per_step == from_report.blackjax_gradients_per_step == stages


@pytest.mark.blackjax
@needs_blackjax
def test_a_designed_report_runs_as_its_transfer_matrix_in_blackjax():
    from stepsafe import design

    report = design(sigma=[1.0, 0.5], step=0.5, stages=3)
    member = family_member(3, (report.params["b"], report.params["a"]))
    factory = bridge.integrator(report)
    for z in (0.3, 1.4):
        want = transfer_matrix(member, [z])[0]
        np.testing.assert_allclose(_one_step_matrix(factory, z), want, rtol=0,
                                   atol=1e-14 * max(1.0, np.abs(want).max()))


def test_blackjax_counts_a_gradient_per_drift():
    assert bridge.coefficients("verlet").blackjax_gradients_per_step == 1
    position_form = bridge.coefficients("mclachlan2-min")
    assert position_form.coefficients[0] == 0.0 == position_form.coefficients[-1]
    assert (position_form.gradients_per_step, position_form.blackjax_gradients_per_step) == \
        (2, 3)


SIGMA = np.linspace(0.5, 2.0, 10)


def _gaussian_logdensity(q):
    import jax.numpy as jnp

    return -0.5 * jnp.sum((q / SIGMA) ** 2)


@pytest.mark.slow
@pytest.mark.blackjax
@needs_blackjax
@pytest.mark.parametrize("name, jitter", [("bcss2", 0.1), ("verlet", 0.0)])
def test_blackjax_acceptance_on_a_gaussian_is_the_prediction(name, jitter):
    settings = bridge.blackjax_hmc(_gaussian_logdensity, np.ones(10), method=name,
                                   trajectory_steps=10, jitter=jitter, target_accept=0.75)
    assert settings.method == name and settings.num_integration_steps == 10
    predicted = gaussian.acceptance_at(method(name), 1.0 / SIGMA, settings.step_size,
                                       Trajectory(steps=10, jitter=jitter))
    rng = np.random.default_rng(3)
    run = bridge.sample(settings, _gaussian_logdensity, rng.standard_normal((64, 10)) * SIGMA,
                        150, seed=4)
    measured = chain_mean(run.acceptance)
    assert 0.5 < predicted.rate < 0.97
    assert abs(measured.value - predicted.rate) < 3 * measured.se, (measured, predicted)
    # stepsafe's estimate on the target agrees with the exact figure too
    assert abs(settings.acceptance - predicted.rate) < 3 * settings.acceptance_se
    # no jittered step passes the stability limit of the fastest mode
    assert not run.divergent.any()


def _banana_logdensity(q):
    x, y = q[0], q[1]
    return -0.5 * x * x - 0.5 * (y - 0.3 * x * x) ** 2


@pytest.mark.slow
@pytest.mark.blackjax
@needs_blackjax
def test_blackjax_acceptance_on_the_banana_is_the_estimate():
    settings = bridge.blackjax_hmc(_banana_logdensity, np.array([0.1, 0.2]),
                                   method="verlet", trajectory_steps=10)
    assert settings.verified, settings.report.unverified
    rng = np.random.default_rng(5)
    x = rng.standard_normal(256)
    start = np.stack([x, 0.3 * x * x + rng.standard_normal(256)], axis=1)  # exact draws
    run = bridge.sample(settings, _banana_logdensity, start, 40, seed=6)
    measured = chain_mean(run.acceptance)
    se = np.hypot(measured.se, settings.acceptance_se)
    assert abs(measured.value - settings.acceptance) < 3 * se, (measured, settings.acceptance)


@pytest.mark.blackjax
@needs_blackjax
def test_draws_that_fail_a_diagnostic_give_unverified_settings_or_a_refusal():
    """Chains of N(0, 1) draws shifted 3 apart fail R-hat: the settings say they are not
    verified (naming R-hat), and require_converged=True refuses them naming R-hat."""
    from stepsafe.exceptions import NotConverged

    def logdensity(q):
        return -0.5 * (q * q).sum()

    draws = (np.random.default_rng(11).normal(size=(8, 200, 1))
             + 3.0 * np.arange(8)[:, None, None])
    settings = bridge.blackjax_hmc(logdensity, np.zeros(1), method="verlet",
                                   trajectory_steps=5, draws=draws)
    assert not settings.verified and "R-hat" in settings.report.unverified
    with pytest.raises(NotConverged, match="R-hat"):
        bridge.blackjax_hmc(logdensity, np.zeros(1), method="verlet", trajectory_steps=5,
                            draws=draws, require_converged=True)


@pytest.mark.slow
@pytest.mark.blackjax
@needs_blackjax
def test_the_hmc_guide_blackjax_example_prints_what_it_shows(monkeypatch, capsys):
    """The HMC guide's BlackJAX block (docs/guides/hmc.md) runs as written and prints the
    text block after it."""
    import re
    import textwrap
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    readme = (root / "docs" / "guides" / "hmc.md").read_text()
    (code, shown), = [(c, t) for c, t in re.findall(
        r"```python\n(.*?)```\n\n```text\n(.*?)```", readme, flags=re.S)
        if "import blackjax" in c]
    monkeypatch.chdir(root)
    exec(compile(textwrap.dedent(code), "docs/guides/hmc.md", "exec"), {})
    assert capsys.readouterr().out == shown


@pytest.mark.blackjax
@needs_blackjax
@pytest.mark.parametrize("kwargs, where", [
    ({"jitter": 1.0}, "jitter"), ({"jitter": 1.5}, "jitter"), ({"jitter": -0.5}, "jitter"),
    ({"jitter": float("nan")}, None), ({"jitter": float("inf")}, None),
    ({"jitter": 10.0}, "jitter"), ({"seed": -3}, "seed"), ({"seed": 2**63}, "seed"),
    ({"seed": 1.5}, "seed"), ({"seed": True}, "seed"),
])
def test_blackjax_hmc_refuses_a_jitter_outside_0_1_and_a_bad_seed(kwargs, where):
    """The jitter J draws steps h (1 + J u), u in (-1, 1): J must be in [0, 1) (J >= 1
    gives steps down to 0 or negative), as stepsafe.hmc requires; the seed an integer in
    [0, 2^63). A StepsafeError before any work, never a raw exception."""
    with pytest.raises(StepsafeError) as caught:
        bridge.blackjax_hmc(lambda q: -0.5 * (q * q).sum(), np.zeros(2), trajectory_steps=10,
                            method="verlet", **kwargs)
    assert where is None or caught.value.where == where
    assert ("jitter" if "jitter" in kwargs else "seed") in str(caught.value)


def _vector_logdensity(q):
    return -0.5 * q**2  # no sum: a vector


def _branching_logdensity(q):
    if q[0] > 0:  # a Python branch on a traced value
        return -0.5 * (q * q).sum()
    return -(q * q).sum()


def _numpy_logdensity(q):
    return -0.5 * float(np.sum(np.asarray(q) ** 2))  # numpy on a traced value


@pytest.mark.blackjax
@needs_blackjax
@pytest.mark.parametrize("logdensity, match", [
    (_vector_logdensity, "must return a scalar"),
    (_branching_logdensity, "TracerBoolConversionError"),
    (_numpy_logdensity, "TracerArrayConversionError"),
])
def test_a_jax_logdensity_that_cannot_be_traced_is_refused_naming_logdensity(logdensity, match):
    """A JAX log-density that returns a vector or fails when JAX traces it is refused with a
    StepsafeError naming ``logdensity``, from blackjax_hmc and from stepsafe.hmc alike."""
    from stepsafe import hmc

    for call in (lambda: bridge.blackjax_hmc(logdensity, np.zeros(2), trajectory_steps=5),
                 lambda: hmc(["verlet"], logdensity=logdensity, start=np.zeros(2),
                             trajectory_steps=5)):
        with pytest.raises(StepsafeError, match=match) as caught:
            call()
        assert caught.value.where == "logdensity"

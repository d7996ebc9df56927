"""The Python API refuses wrong-typed arguments with StepsafeError, never another exception.

Generated: every argument of every public function gets values of the wrong kind (None,
text, bytes, complex, huge ints, arrays of the wrong shape or dtype, mappings, objects).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import stepsafe

PENDULUM = str(Path(__file__).resolve().parent.parent / "examples" / "pendulum.yaml")

JUNK = st.one_of(
    st.none(), st.booleans(), st.text(max_size=8), st.binary(max_size=4),
    st.complex_numbers(allow_nan=False, allow_infinity=False, max_magnitude=1e3),
    st.integers(-10**400, 10**400), st.floats(allow_nan=True, allow_infinity=True),
    st.just(np.array([1.0, 2.0])), st.just(np.array([[1.0], [2.0, 3.0]], dtype=object)),
    st.just(np.array([1 + 1j])), st.just({}), st.just({"saddle": "x"}), st.just([[1, 2], [3]]),
    st.just(object()), st.just("a\x00b.yaml"), st.just([("saddle", [1.0])]),
)

CALLS = {
    "method.name": lambda v: stepsafe.method(v),
    "method.stages": lambda v: stepsafe.method("gauss", stages=v),
    "method.base": lambda v: stepsafe.method("yoshida4", base=v),
    "region.model": lambda v: stepsafe.region("verlet", v),
    "region.zmax": lambda v: stepsafe.region("verlet", "oscillator", zmax=v),
    "region.verify": lambda v: stepsafe.region("verlet", "oscillator", zmax=1.0, verify=v),
    "advise.beta": lambda v: stepsafe.advise("verlet", v),
    "advise.saddle": lambda v: stepsafe.advise("verlet", [1.0], saddle_beta=v),
    "advise.modes": lambda v: stepsafe.advise("verlet", modes=v),
    "advise.margin": lambda v: stepsafe.advise("verlet", [1.0], margin=v),
    "advise.zmax": lambda v: stepsafe.advise("verlet", [1.0], zmax=v),
    "advise.tol_phase": lambda v: stepsafe.advise("verlet", [1.0], tol_phase=v),
    "advise.wavenumber": lambda v: stepsafe.advise("verlet", wavenumber=v, time_unit="fs"),
    "advise.time_unit": lambda v: stepsafe.advise("verlet", [1.0], time_unit=v),
    "advise.scene": lambda v: stepsafe.advise(scene=v),
    "advise.problem": lambda v: stepsafe.advise(problem=v),
    "check.h": lambda v: stepsafe.check("verlet", v, [1.0]),
    "check.verify": lambda v: stepsafe.check("verlet", 0.1, [1.0], verify=v),
    "check.system": lambda v: stepsafe.check("verlet", 0.1, system={"hessian": v}),
    "errors.z": lambda v: stepsafe.errors("verlet", v),
    "errors.model": lambda v: stepsafe.errors("verlet", [0.1], v),
    "transfer.z": lambda v: stepsafe.transfer_matrices("verlet", v),
    "compare.methods": lambda v: stepsafe.compare(v, [1.0]),
    "load_scene": lambda v: stepsafe.load_scene(v),
    "advise.stiffness": lambda v: stepsafe.advise("verlet", system={"stiffness": [[v]]}),
    "measure.scene": lambda v: stepsafe.measure("verlet", [0.5], scene=v, time=1.0),
    "refine.quantity": lambda v: stepsafe.refine("verlet", v, 1e-3, scene=PENDULUM),
    "design.stages": lambda v: stepsafe.design(sigma=[1.0], step=1.0, stages=v),
    "design.jitter": lambda v: stepsafe.design(sigma=[1.0], step=1.0, jitter=v),
    "hmc.jitter": lambda v: stepsafe.hmc(["verlet"], sigma=[1.0], trajectory_steps=4, jitter=v),
    "hmc.target_accept": lambda v: stepsafe.hmc(["verlet"], sigma=[1.0], trajectory_steps=4,
                                                target_accept=v),
    "impulse_advice.pairs": lambda v: stepsafe.impulse_advice("respa-verlet", pairs=v),
}


#: a valid energy or start runs an integration: these take the wrong kinds only
NOT_NUMBERS = ["abc", 10**400, -10**400, True, [1.0], 1 + 2j, float("nan"), float("inf"),
               np.array([1.0, 2.0]), None, b"1"]


@pytest.mark.parametrize("value", NOT_NUMBERS, ids=repr)
def test_measure_refuses_a_start_that_is_not_a_number(value):
    for start in ({"energy": value}, {"initial": [value, 0.0]}):
        if value is None and "energy" in start:
            continue  # (no energy given: the scene's own start)
        with pytest.raises(stepsafe.StepsafeError):
            stepsafe.measure("verlet", [0.5], scene=PENDULUM, time=1.0, **start)


@pytest.mark.parametrize("where", sorted(CALLS))
@settings(max_examples=30, deadline=None, suppress_health_check=list(HealthCheck))
@given(value=JUNK)
def test_wrong_arguments_raise_stepsafe_error(where, value):
    try:
        CALLS[where](value)
    except stepsafe.StepsafeError:
        pass


def test_hmc_and_design_refuse_unknown_arguments_and_flat_directions():
    """An unknown keyword is a StepsafeError naming it, in every function that builds a
    problem (never a TypeError); a zero frequency (sigma = inf) is an improper target."""
    import stepsafe
    from stepsafe import hmc

    with pytest.raises(stepsafe.StepsafeError, match="unknown argument 'foo'"):
        hmc(["verlet"], sigma=[1.0], foo=1)
    with pytest.raises(stepsafe.StepsafeError, match="unknown argument 'bar'"):
        stepsafe.design(sigma=[1.0], step=0.1, bar=2)
    with pytest.raises(stepsafe.StepsafeError, match="unknown argument 'baz'"):
        stepsafe.advise("verlet", [1.0], baz=3)
    with pytest.raises(stepsafe.StepsafeError, match="unknown argument 'qux'"):
        stepsafe.check("verlet", 0.1, [1.0], qux=4)
    with pytest.raises(stepsafe.StepsafeError, match="flat direction"):
        hmc(["verlet"], beta=[0.0, 1.0])


NOT_REAL = st.one_of(
    st.complex_numbers(allow_nan=False, allow_infinity=False, max_magnitude=1e3).filter(
        lambda c: c.imag != 0),
    st.text(max_size=6), st.none(), st.lists(st.floats(-1, 1), max_size=2), st.binary(max_size=3),
    st.just(np.complex128(1 + 2j)), st.just(object()), st.booleans(),
)


@settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck))
@given(value=NOT_REAL, combined=st.booleans(), call=st.sampled_from(["advise", "measure"]))
def test_a_hamiltonian_function_that_is_not_real_is_an_input_error(value, combined, call):
    """A Python Hamiltonian that returns, or combines q and p with, something that is not
    a real number (a complex, a text, None, a list, a bool) is a StepsafeError naming
    system.hamiltonian, never a TypeError from inside the analysis."""
    def H(q, p, ops):
        return p[0] ** 2 / 2 + q[0] ** 2 / 2 + value if combined else value

    system = {"hamiltonian": H, "q": ["x"], "p": ["px"], "box": {"x": [-1, 1], "px": [-1, 1]}}
    with pytest.raises(stepsafe.StepsafeError) as caught:
        if call == "advise":
            stepsafe.advise("verlet", system=system)
        else:
            stepsafe.measure("verlet", [0.1], system=system, time=1.0, initial=[0.1, 0.0])
    assert caught.value.where == "system::$.system.hamiltonian"

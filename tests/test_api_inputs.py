"""The Python API refuses wrong-typed arguments with StepsafeError, never another exception.

Generated: every argument of every public function gets values of the wrong kind (None,
text, bytes, complex, huge ints, arrays of the wrong shape or dtype, mappings, objects).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import stepsafe

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
    "method.stages": lambda v: stepsafe.method("gauss", v),
    "method.base": lambda v: stepsafe.method("yoshida4", base=v),
    "region.model": lambda v: stepsafe.region("verlet", v),
    "region.zmax": lambda v: stepsafe.region("verlet", "oscillator", v),
    "region.verify": lambda v: stepsafe.region("verlet", "oscillator", 1.0, v),
    "advise.frequencies": lambda v: stepsafe.advise("verlet", v),
    "advise.saddle": lambda v: stepsafe.advise("verlet", [1.0], saddle=v),
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
}


@pytest.mark.parametrize("where", sorted(CALLS))
@settings(max_examples=30, deadline=None, suppress_health_check=list(HealthCheck))
@given(value=JUNK)
def test_wrong_arguments_raise_stepsafe_error(where, value):
    try:
        CALLS[where](value)
    except stepsafe.StepsafeError:
        pass

"""A stage that ends at the step's q (Lobatto IIIA's last) hands its force to the next
step's first stage, decided on the coefficients as meant, and counted alike by the solver
model (``compare``) and the integration engine (``measure``)."""

from __future__ import annotations

from pathlib import Path

import mpmath as mp
import numpy as np
import pytest

import stepsafe
from stepsafe.core.integrator import Engine
from stepsafe.core.solver import fixed_point_cost
from stepsafe.methods.tableaux import step_end_stage
from stepsafe.reference import highprec as R
from stepsafe.systems.dynamics import linear_system

LOBATTO3 = {"A_q": [["0", "0", "0"], ["5/24", "1/3", "-1/24"], ["1/6", "2/3", "1/6"]],
            "b_q": ["1/6", "2/3", "1/6"],
            "A_p": [["1/6", "-1/6", "0"], ["1/6", "1/3", "0"], ["1/6", "5/6", "0"]],
            "b_p": ["1/6", "2/3", "1/6"]}


def _write(path: Path, coefficients: dict) -> Path:
    def text(value):
        if isinstance(value, list):
            return "[" + ", ".join(text(v) for v in value) + "]"
        return f'"{value}"'

    lines = ["name: written", "kind: prk", "order: 4", "source: test"]
    lines += [f"{key}: {text(value)}" for key, value in coefficients.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("s", [2, 3, 4, 5, 6])
def test_the_family_lobatto_stage_ends_at_the_step(s):
    """Lobatto IIIA's last row is b exactly (checked on the 50-digit tableau), and the
    float family says so for every s (its float rows once differed from b by 1e-17)."""
    with mp.workdps(50):
        A, b, _ = R.lobatto_IIIA_tableau(s)
        assert all(A[s - 1, j] == b[j] for j in range(s))
    prk = stepsafe.method("lobatto3ab", stages=s).tableau.as_prk()
    assert step_end_stage(prk) == s - 1
    assert step_end_stage(stepsafe.method("gauss", stages=min(s, 4)).tableau.as_prk()) is None


def _forces(tableau, steps: int, z: float) -> int:
    engine = Engine(tableau, linear_system(np.eye(2)))
    q, p = np.array([[1.0]]), np.array([[0.0]])
    for _ in range(steps):
        q, p = engine.step(q, p, z)
    return engine.force_evaluations


@pytest.mark.parametrize("perturbation, reused", [("", True), (" + 1e-17", False),
                                                   (" + 1e-30", False)])
def test_a_method_file_reuses_the_force_only_when_written_so(tmp_path, perturbation, reused):
    """The last row written as b reuses the force; written ``1/6 + 1e-17`` (a different
    number whose float is the same) it does not, though the floats are equal. The engine
    then pays the fixed stage's force at every step, and the model counts it alike."""
    coefficients = {**LOBATTO3, "A_q": [*LOBATTO3["A_q"][:2],
                                        ["1/6" + perturbation, "2/3", "1/6"]]}
    integrator = stepsafe.method(str(_write(tmp_path / "m.yaml", coefficients)))
    prk = integrator.tableau.as_prk()
    assert np.array_equal(prk.A_q[2], prk.b_q)  # the floats cannot tell
    assert (step_end_stage(prk) == 2) is reused
    z = 0.5
    fixed = 0 if reused else 1
    model = fixed_point_cost(integrator.tableau, z)
    with_reuse = model.evaluations if reused else model.evaluations - fixed
    # the engine: the model's varying-stage forces (its iterations vary with the state's
    # phase, at most the model's), the fixed stage's force once, or at every step
    steps = 12
    total = _forces(integrator.tableau, steps, z)
    fixed_forces = 1 if reused else steps
    varying = (total - fixed_forces) / steps
    assert varying <= with_reuse and varying >= with_reuse - 2
    family = _forces(stepsafe.method("lobatto3ab", stages=3).tableau, steps, z)
    assert total - family == (0 if reused else steps - 1)


def test_measure_and_compare_count_lobatto_alike():
    """On the oscillator at Lobatto IIIA-IIIB s = 3's accurate step for phase <= 1e-6 (h =
    0.2316), measure's forces per step from the worse unit state are compare's count: 7
    passes of 2 varying stages, the fixed stage's force reused (the first step pays it)."""
    from stepsafe.api.linear import compare

    row = compare(["lobatto3ab:3"], [1.0], tol_phase=1e-6, solver="fixed-point").rows[0]
    tableau = stepsafe.method("lobatto3ab", stages=3).tableau
    worst = 0
    for q0, p0 in ((1.0, 0.0), (0.0, 1.0)):
        engine = Engine(tableau, linear_system(np.eye(2)))
        engine.step(np.array([[q0]]), np.array([[p0]]), row.h)
        worst = max(worst, engine.force_evaluations - 1)  # (the first step's fixed force)
    assert worst == row.evaluations == 14 and row.solver_iterations == 7

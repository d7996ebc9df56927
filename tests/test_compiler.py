"""The expression compiler: values, gradients and Hessians of generated expressions against
an independent reference (the expression text evaluated by mpmath at 50 digits, its
derivatives by mpmath's high-precision finite differences), in the numpy and mpmath
backends; Python functions traced into the same graph."""

from __future__ import annotations

import re

import mpmath as mp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from stepsafe.files.expressions import ExpressionError, parse
from stepsafe.systems.compiler import FUNCTIONS, Compiled, from_tree, to_text, trace

DIGITS = 50

_LEAVES = st.sampled_from(["x", "y", "0.5", "2", "3", "1e-3", "0.7", "pi"])


def _extend(inner):
    return st.one_of(
        st.tuples(inner, inner).map(lambda t: f"({t[0]} + {t[1]})"),
        st.tuples(inner, inner).map(lambda t: f"({t[0]} - {t[1]})"),
        st.tuples(inner, inner).map(lambda t: f"({t[0]} * {t[1]})"),
        st.tuples(inner, inner).map(lambda t: f"({t[0]} / (1 + ({t[1]})**2))"),
        st.tuples(inner, st.sampled_from(["2", "3", "4", "1"])).map(
            lambda t: f"({t[0]})**{t[1]}"),
        st.tuples(inner, inner).map(lambda t: f"(1 + ({t[0]})**2)**sin({t[1]})"),
        st.tuples(inner, st.sampled_from(["0.5", "1.5", "-0.5"])).map(
            lambda t: f"(2 + sin({t[0]}))**{t[1]}"),
        inner.map(lambda a: f"-({a})"),
        inner.map(lambda a: f"({a})**(4/2)"),
        st.tuples(st.sampled_from(["sin", "cos", "tanh", "sinh", "cbrt"]), inner).map(
            lambda t: f"{t[0]}({t[1]})"),
        inner.map(lambda a: f"exp(-({a})**2)"),
        inner.map(lambda a: f"cosh(0.3*({a}))"),
        inner.map(lambda a: f"log(1 + ({a})**2)"),
        inner.map(lambda a: f"sqrt(2 + cos({a}))"),
    )


_EXPRESSIONS = st.recursive(_LEAVES, _extend, max_leaves=8)


def expressions():
    """Random expressions in x and y of the scene language, defined and smooth on the
    whole plane (cbrt aside, which is singular where its argument is 0)."""
    return _EXPRESSIONS


def _compiled(text: str) -> Compiled:
    e = parse(text, FUNCTIONS)
    return Compiled(from_tree(e.tree, e.text, ("x", "y")), ("x", "y"))


def _mp_function(text: str):
    """The text evaluated by mpmath (independent of the compiler's graph)."""
    namespace = {name: getattr(mp, name) for name in FUNCTIONS}
    namespace["pi"] = mp.pi
    code = compile(re.sub(r"(?<![\w.])(\d+\.?\d*(?:e-?\d+)?)", r"mpf('\1')", text),
                   "<test>", "eval")

    def f(x, y):
        return eval(code, {"mpf": mp.mpf, "__builtins__": {}}, {**namespace, "x": x, "y": y})

    return f


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(text=expressions(), x=st.floats(-2, 2), y=st.floats(-2, 2))
def test_gradient_and_hessian_agree_with_high_precision_differences(text, x, y):
    """d/dx, d/dy and the second derivatives of the compiled graph (mpmath backend, 50
    digits) agree with mpmath's finite differences of the text to 1e-25 relative; the
    numpy backend agrees with them to 1e-9 of their size."""
    f = _mp_function(text)
    c = _compiled(text)
    with mp.workdps(DIGITS):
        X, Y = mp.mpf(x), mp.mpf(y)
        try:
            reference_value = f(X, Y)
            ref_g = [mp.diff(f, (X, Y), (1, 0)), mp.diff(f, (X, Y), (0, 1))]
            ref_h = [[mp.diff(f, (X, Y), (2, 0)), mp.diff(f, (X, Y), (1, 1))],
                     [mp.diff(f, (X, Y), (1, 1)), mp.diff(f, (X, Y), (0, 2))]]
        except (ZeroDivisionError, ValueError):
            return
        if any(isinstance(v, mp.mpc) for v in [reference_value, *ref_g, *ref_h[0],
                                                *ref_h[1]]):
            return
        try:
            v, g, H = c.mp_jet([X, Y])
        except ExpressionError:
            return
        scale = max(mp.mpf(1), *(abs(t) for t in [reference_value, *ref_g, *ref_h[0],
                                                    *ref_h[1]]))
        if scale > 1e12:
            return
        assert abs(v - reference_value) <= mp.mpf(10) ** -40 * scale, text
        for a, b in zip(g + H[0] + H[1], ref_g + ref_h[0] + ref_h[1]):
            assert abs(a - b) <= mp.mpf(10) ** -25 * scale, (text, a, b)
    with mp.workdps(16):  # float64's precision: an ill-conditioned value (cos(1.8e10))
        try:              # is not float64's to get right; only the graph is compared then
            rough = f(mp.mpf(x), mp.mpf(y))
        except (ZeroDivisionError, ValueError):
            return
    if isinstance(rough, mp.mpc) or abs(rough - reference_value) > 1e-10 * scale:
        return
    point = np.array([[x, y]])
    fv, fg = c.energy_gradient(point)
    fh = c.hessian(point)
    floats = [float(fv[0]), *fg[0], *fh[0].ravel()]
    exact = [reference_value, *ref_g, *ref_h[0], *ref_h[1]]
    for a, b in zip(floats, exact):
        assert abs(a - float(b)) <= 1e-9 * float(scale) * 1e3, (text, a, b)


@given(text=expressions())
@settings(max_examples=30, deadline=None)
def test_the_numpy_backend_is_vectorised_over_a_batch_of_states(text):
    """Values over a batch of states equal the values state by state (to the ulp or two
    by which numpy's vectorised kernels may differ from its scalar ones)."""
    c = _compiled(text)
    X = np.random.default_rng(1).uniform(-1.5, 1.5, (5, 2))
    v, g = c.energy_gradient(X)
    h = c.hessian(X)
    for k in range(5):
        vk, gk = c.energy_gradient(X[k])
        for a, b in ((np.asarray(vk), v[k]), (gk, g[k]), (c.hessian(X[k]), h[k])):
            np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-300)


def test_derivatives_of_powers_are_exact_at_zero():
    """q^2 differentiates to 2 q and the constant 2 (no 0 * inf at q = 0); q^1 to 1."""
    c = _compiled("x**2 + y")
    assert to_text(c.gradient_nodes[0]) == "(2 * x)"
    assert c.hessian(np.zeros(2))[0, 0] == 2.0
    assert to_text(_compiled("x**1").gradient_nodes[0]) == "1.0"


def test_a_python_function_traces_into_the_same_graph():
    def H(q, p, ops):
        return (p[0] ** 2 + p[1] ** 2) / 2 - ops.cos(q[0]) + 0.5 * q[1] ** 2 * q[0]

    node = trace(H, ["a", "b"], ["pa", "pb"])
    e = parse("(pa**2 + pb**2)/2 - cos(a) + 0.5*b**2*a", FUNCTIONS)
    same = from_tree(e.tree, e.text, ("a", "b", "pa", "pb"))
    names = ("a", "b", "pa", "pb")
    X = np.random.default_rng(2).uniform(-1, 1, (4, 4))
    np.testing.assert_allclose(Compiled(node, names).gradient(X),
                               Compiled(same, names).gradient(X), rtol=1e-15, atol=1e-15)


def test_domain_errors_are_not_finite_in_numpy_and_raise_in_mpmath():
    c = _compiled("log(x) + y")
    assert not np.isfinite(c.energy(np.array([-1.0, 0.0])))
    with pytest.raises(ExpressionError):
        c.mp_jet([mp.mpf(-1), mp.mpf(0)])

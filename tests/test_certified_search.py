"""The certified equilibrium search: interval enclosures hold, and a search that says
"complete" has found every equilibrium of the box (narrow wells drawn at random, checked
against an independent dense search at 50 digits written here)."""

from __future__ import annotations

import mpmath as mp
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from test_compiler import expressions

import stepsafe
from stepsafe.files.expressions import ExpressionError, parse
from stepsafe.systems.compiler import FUNCTIONS, Compiled, from_tree
from stepsafe.systems.intervals import certified_equilibria, evaluate

DIGITS = 50


def _compiled(text: str, names: tuple[str, ...]) -> Compiled:
    e = parse(text, FUNCTIONS)
    return Compiled(from_tree(e.tree, e.text, names), names)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(text=expressions(), lo=st.floats(-3, 3), width=st.floats(1e-6, 2),
       lo2=st.floats(-3, 3), width2=st.floats(1e-6, 2))
def test_interval_enclosures_contain_every_value_and_derivative(text, lo, width, lo2,
                                                                 width2):
    """For a random expression in (x, y) and a random box, H, its gradient and Hessian at
    points of the box (at 50 digits, where defined) lie in their interval enclosures."""
    c = _compiled(text, ("x", "y"))
    box_lo = np.array([lo, lo2])
    box_hi = np.array([lo + width, lo2 + width2])
    outputs = [c.H, *c.gradient_nodes, *(h for row in c.hessian_nodes for h in row)]
    enclosures = evaluate(outputs, c.names, box_lo[None, :], box_hi[None, :])
    rng = np.random.default_rng(0)
    for t in np.vstack([rng.uniform(0, 1, (6, 2)), [[0, 0], [1, 1], [0, 1], [1, 0]]]):
        with mp.workdps(DIGITS):
            x = [mp.mpf(float(box_lo[i])) + mp.mpf(float(t[i])) * (mp.mpf(float(box_hi[i]))
                 - mp.mpf(float(box_lo[i]))) for i in range(2)]
            try:
                v, g, Hm = c.mp_jet(x)
            except (stepsafe.exceptions.StepsafeError, ExpressionError):
                continue  # not defined there (a derivative of cbrt at 0, a pole)
            values = [v, *g, *(h for row in Hm for h in row)]
        for value, box in zip(values, enclosures):
            if box.empty[0]:
                raise AssertionError(f"{text}: defined at {x} but the enclosure is empty")
            assert mp.mpf(float(box.lo[0])) <= value <= mp.mpf(float(box.hi[0])), \
                (text, x, value, box.lo, box.hi)


def _well_truth(a: float, b: float, depth: float, width: float) -> list[tuple[float, float,
                                                                              bool]]:
    """Equilibria of V = (x^2 + y^2)/2 - depth exp(-((x - a)^2 + (y - b)^2)/width) in
    [-1, 1]^2, found independently: grad V = 0 gives x (y - b) = y (x - a), so every
    equilibrium lies on the line through 0 and the centre c = (a, b); along it
    (x, y) = s c/|c| and s + (2 depth/width)(s - |c|) exp(-(s - |c|)^2/width) = 0. That
    1-dof equation is scanned for sign changes on a grid 1/400 of the well's width apart
    and each root refined at 50 digits; each comes with whether it is a simple zero
    (Hessian eigenvalues above 1e-6 in size)."""
    with mp.workdps(DIGITS):
        A, B, D, W = (mp.mpf(v) for v in (a, b, depth, width))
        r = mp.sqrt(A * A + B * B)
        ux, uy = A / r, B / r

        def f(s):
            return s + 2 * D / W * (s - r) * mp.exp(-(s - r) ** 2 / W)

        reach = float(mp.sqrt(2))
        grid = np.unique(np.concatenate([np.linspace(-reach, reach, 4001),
                                         float(r) + np.sqrt(width) * np.linspace(-8, 8, 6401)]))
        grid = grid[np.abs(grid) <= reach]
        values = [f(mp.mpf(float(s))) for s in grid]
        roots = []
        for s0, s1, f0, f1 in zip(grid, grid[1:], values, values[1:]):
            if f0 == 0 or f0 * f1 < 0:
                roots.append(mp.findroot(f, (mp.mpf(float(s0)), mp.mpf(float(s1))),
                                         solver="anderson"))
        out = []
        for s in roots:
            x, y = s * ux, s * uy
            if max(abs(x), abs(y)) > 1:
                continue
            e = mp.exp(-((x - A) ** 2 + (y - B) ** 2) / W)
            k = 2 * D / W * e
            dx, dy = x - A, y - B
            V = mp.matrix([[1 + k * (1 - 2 * dx * dx / W), -k * 2 * dx * dy / W],
                           [-k * 2 * dx * dy / W, 1 + k * (1 - 2 * dy * dy / W)]])
            eig = mp.eigsy(V)[0]
            out.append((float(x), float(y), min(abs(v) for v in eig) > 1e-6))
        return out


@st.composite
def narrow_wells(draw):
    a = draw(st.floats(-0.9, 0.9).filter(lambda v: v == 0 or abs(v) > 1e-6))
    b = draw(st.floats(-0.9, 0.9).filter(lambda v: v == 0 or abs(v) > 1e-6))
    assume(a * a + b * b > 0.01)
    width = 10 ** draw(st.floats(-4, -1))
    depth = draw(st.floats(0.05, 2.0))
    return (float(f"{a:.4g}"), float(f"{b:.4g}"), float(f"{depth:.3g}"),
            float(f"{width:.3g}"))


@settings(max_examples=3, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(well=narrow_wells())
def test_a_complete_search_finds_every_equilibrium_of_a_narrow_well(well):
    _check_narrow_well(well)


@pytest.mark.slow
@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(well=narrow_wells())
def test_a_complete_search_finds_every_equilibrium_of_many_narrow_wells(well):
    _check_narrow_well(well)


def _check_narrow_well(well) -> None:
    """A Gaussian well of random centre, width (1e-4 to 1e-1) and depth on a 2-dof
    harmonic background, box +-1 in all four variables, default starts: when the search
    says complete, its equilibria are exactly those of the independent dense search (so
    no minimum is missed), and every minimum's frequencies are reported."""
    a, b, depth, width = well
    truth = _well_truth(a, b, depth, width)
    assume(all(simple for _, _, simple in truth))
    assume(all(min(1 - abs(x), 1 - abs(y)) > 1e-3 for x, y, _ in truth))
    assume(all(max(abs(x0 - x1), abs(y0 - y1)) > 1e-4
               for i, (x0, y0, _) in enumerate(truth) for x1, y1, _ in truth[i + 1:]))
    text = (f"(px**2 + py**2)/2 + (x**2 + y**2)/2 - {depth!r}*exp(-((x - ({a!r}))**2 + "
            f"(y - ({b!r}))**2)/{width!r})")
    report = stepsafe.check("verlet", 0.01, system={
        "hamiltonian": text, "q": ["x", "y"], "p": ["px", "py"],
        "box": {"x": [-1, 1], "y": [-1, 1], "px": [-1, 1], "py": [-1, 1]}})
    record = report.record["system"]
    if not record["search"]["complete"]:
        assert record["search"]["gaps"]
        return
    found = [(item["x"][0], item["x"][1]) for item in record["items"]]
    assert len(found) == len(truth), (found, truth, record["search"])
    for tx, ty, _ in truth:
        assert any(abs(fx - tx) <= 1e-7 and abs(fy - ty) <= 1e-7 for fx, fy in found), \
            (found, truth)
    for item in record["items"]:
        assert all(abs(v) < 1e-12 for v in item["x"][2:])


def test_the_narrow_well_behind_the_saddle_is_proved_and_unsafe(tmp_path, run):
    """The well of beta = 44.73 at (0.69965, 0.29985) behind a saddle, from the default
    starts: the branch and bound finds it, so Verlet at h = 0.05 (limit 2/44.73) is UNSAFE
    and the search is complete."""
    scene = tmp_path / "well.yaml"
    scene.write_text('method: verlet\nh: 0.05\nsystem:\n  hamiltonian: "(px**2+py**2)/2+'
                     '(x**2+y**2)/2-exp(-((x-0.7)**2+(y-0.3)**2)/1e-3)"\n  q: [x, y]\n'
                     "  p: [px, py]\n  box: {x: [-1, 1], y: [-1, 1], px: [-1, 1], "
                     "py: [-1, 1]}\n")
    code, out, _ = run("check", str(scene))
    assert code == 1 and "UNSAFE" in out and ": complete" in out
    code, out, _ = run("check", str(scene), "--require-complete-search")
    assert code == 1
    truth = _well_truth(0.7, 0.3, 1.0, 1e-3)
    report = stepsafe.check(scene=str(scene))
    found = sorted((i["x"][0], i["x"][1]) for i in report.record["system"]["items"])
    expected = sorted((x, y) for x, y, _ in truth)
    assert len(found) == len(expected) == 3
    assert np.allclose(found, expected, rtol=0, atol=1e-7)
    assert report.record["system"]["search"]["found_by_bound"] >= 1


def test_a_degenerate_equilibrium_leaves_the_search_incomplete():
    """q^4 has a zero of the gradient with a singular Hessian at 0: no Krawczyk test
    settles a box around it, so the bound is not complete and says where."""
    c = _compiled("p**2/2 + q**4", ("q", "p"))
    result = certified_equilibria(c, np.array([-1.0, -1.0]), np.array([1.0, 1.0]),
                                  max_boxes=2000)
    assert not result.complete and result.undecided > 0
    assert np.abs(np.array(result.where)).max() < 0.1


def test_the_budget_bounds_the_boxes_evaluated():
    c = _compiled("(px**2+py**2)/2+(x**2+y**2)/2-exp(-((x-0.7)**2+(y-0.3)**2)/1e-3)",
                  ("x", "y", "px", "py"))
    result = certified_equilibria(c, -np.ones(4), np.ones(4), max_boxes=100)
    assert not result.complete and result.boxes <= 100 and "budget" in result.reason


def test_an_incomplete_search_is_printed_as_incomplete_and_fails_on_request(tmp_path, run):
    """A degenerate equilibrium (V' = q (q - 1/2)^2: V'' = 0 at 1/2) beside a regular
    minimum at 0 leaves the bound undecided: the Search line says
    INCOMPLETE, never the sentence that defines a complete search, and
    --require-complete-search turns the verdict into exit 1 even at a safe step."""
    scene = tmp_path / "quartic.yaml"
    scene.write_text('method: verlet\nh: 0.1\nsystem:\n  hamiltonian: "p**2/2 + q**4 + q**2"\n'
                     "  box: {q: [-1, 1], p: [-1, 1]}\n")
    code, out, _ = run("check", str(scene))
    assert "Search:" in out, out
    if ": complete" in out:  # q^4 + q^2 is regular: proved, and said so
        assert "(complete: interval arithmetic" in out and code == 0
    degenerate = tmp_path / "degenerate.yaml"
    degenerate.write_text('method: verlet\nh: 0.1\nsystem:\n  hamiltonian: '
                          '"p**2/2 + q**4/4 - q**3/3 + q**2/8"\n'
                          "  box: {q: [-1, 1], p: [-1, 1]}\n")
    code, out, err = run("check", str(degenerate))
    assert "INCOMPLETE" in out, (out, err)
    assert "(complete: interval arithmetic" not in out
    code, out, err = run("check", str(degenerate), "--require-complete-search")
    assert code != 0, (out, err)

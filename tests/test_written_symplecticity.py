"""A method file's RK/PRK tableau is symplectic only to the precision its digits carry.

Every verdict is checked against the symplecticity condition ``b_q,i a_p,ij + a_q,ji b_p,j -
b_q,i b_p,j = 0`` evaluated here at 50 digits on the exact values of the written texts, each
entry (and each of ``b_q - b_p``) against twice the first-order bound that the rounding of
the written digits puts on it: a text printed to 17 or 30 digits carries a residual of its
own (1.7e-17 for Lobatto IIIA-IIIB s = 4 at 17 digits), which is not a defect.
"""

from __future__ import annotations

import re
from pathlib import Path

import mpmath as mp
import pytest
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from stepsafe.files.yamlio import load_yaml
from stepsafe.methods.library import builtin_dir, builtin_names, resolve
from stepsafe.methods.residuals import residuals
from stepsafe.reference import highprec as R

#: tableaux written as exact expressions: (kind, {key: texts})
EXACT = {
    "midpoint": ("rk", {"A": [["1/2"]], "b": ["1"]}),
    "gauss2": ("rk", {"A": [["1/4", "1/4 - sqrt(3)/6"], ["1/4 + sqrt(3)/6", "1/4"]],
                      "b": ["1/2", "1/2"]}),
    "lobatto3ab3": ("prk", {"A_q": [["0", "0", "0"], ["5/24", "1/3", "-1/24"],
                                    ["1/6", "2/3", "1/6"]],
                            "b_q": ["1/6", "2/3", "1/6"],
                            "A_p": [["1/6", "-1/6", "0"], ["1/6", "1/3", "0"],
                                    ["1/6", "5/6", "0"]],
                            "b_p": ["1/6", "2/3", "1/6"]}),
}


def _family(name: str, s: int) -> tuple[str, dict]:
    """The family member's exact tableau at 60 digits (the mpmath reference)."""
    with mp.workdps(60):
        if name == "gauss":
            A, b, _ = R.gauss_tableau(s)
            return "rk", {"A": [[A[i, j] for j in range(s)] for i in range(s)], "b": list(b)}
        A, b, _ = R.lobatto_IIIA_tableau(s)
        B, _, _ = R.lobatto_IIIB_tableau(s)
        return "prk", {"A_q": [[A[i, j] for j in range(s)] for i in range(s)], "b_q": list(b),
                       "A_p": [[B[i, j] for j in range(s)] for i in range(s)], "b_p": list(b)}


def _written(value, digits: int):
    """Decimal texts: 17 digits of the float64 nearest (``repr``), or ``digits`` digits."""
    if isinstance(value, list):
        return [_written(v, digits) for v in value]
    return repr(float(value)) if digits == 17 else mp.nstr(value, digits, min_fixed=-1,
                                                            max_fixed=1)


FAMILIES = [("gauss", s) for s in (1, 3, 5)] + [("lobatto3ab", s) for s in (2, 4, 5)]


def _tableaux() -> dict[str, tuple[str, dict]]:
    out = dict(EXACT)
    for name, s in FAMILIES:
        kind, exact = _family(name, s)
        for digits in (17, 30):
            out[f"{name}{s}-{digits}digits"] = (kind, {k: _written(v, digits)
                                                       for k, v in exact.items()})
    return out


TABLEAUX = _tableaux()


def _write(path: Path, kind: str, coefficients: dict) -> Path:
    def text(value):
        if isinstance(value, list):
            return "[" + ", ".join(text(v) for v in value) + "]"
        return f'"{value}"'

    lines = ["name: written", f"kind: {kind}", "order: 1", "source: test"]
    lines += [f"{key}: {text(value)}" for key, value in coefficients.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


def _defects(kind: str, coefficients: dict) -> tuple[mp.mpf, mp.mpf]:
    """(max |condition entry|, max |b_q - b_p|) of the texts' exact values, at 50 digits."""
    from stepsafe.files.expressions import mpmath_backend, value_of

    with mp.workdps(50):
        values = {k: [[value_of(x, None, mpmath_backend()) for x in row] if isinstance(row, list)
                      else value_of(row, None, mpmath_backend()) for row in v]
                  for k, v in coefficients.items()}
        if kind == "rk":
            values = {"A_q": values["A"], "b_q": values["b"], "A_p": values["A"],
                      "b_p": values["b"]}
        Aq, bq, Ap, bp = (values[k] for k in ("A_q", "b_q", "A_p", "b_p"))
        s = len(bq)
        sep = max(abs(bq[i] * Ap[i][j] + Aq[j][i] * bp[j] - bq[i] * bp[j])
                  for i in range(s) for j in range(s))
        return sep, max(abs(bq[i] - bp[i]) for i in range(s))


@pytest.mark.parametrize("name", sorted(TABLEAUX))
def test_a_symplectic_tableau_written_exactly_or_to_its_digits_is_symplectic(name, tmp_path,
                                                                             run):
    """Exact expressions, 17 digits of float64 and 30 digits all pass, and the step where a
    centre stays a centre is certified."""
    kind, coefficients = TABLEAUX[name]
    path = _write(tmp_path / "m.yaml", kind, coefficients)
    code, out, _ = run("validate", str(path))
    assert code == 0 and "warning" not in out, out
    assert residuals(resolve(str(path))[0]).symplectic
    code, out, _ = run("check", "--method", str(path), "--beta", "1", "--step", "0.5")
    assert code == 0 and out.startswith("SAFE"), out


def _allowance(text: str) -> mp.mpf:
    """How far the value meant may lie from a text of these tableaux, as the method-file
    format states it: a decimal of 10 or more significant digits is a rounding to its last
    digit or to 4 ulps of float64, whichever is coarser; shorter decimals and the exact
    expressions are exact."""
    if not re.fullmatch(r"-?(\d+\.?\d*|\.\d+)(e[+-]?\d+)?", text.lower()):
        return mp.mpf(0)
    mantissa, _, exponent = text.lower().lstrip("-").partition("e")
    if len(mantissa.replace(".", "").lstrip("0") if "." in mantissa else
           mantissa.strip("0")) < 10:
        return mp.mpf(0)
    decimals = len(mantissa.partition(".")[2])
    return max(mp.mpf(10) ** (int(exponent or 0) - decimals) / 2,
               4 * mp.mpf(2) ** -52 * abs(mp.mpf(text)))


def _beyond_digits(kind: str, written: dict, perturbed: dict) -> tuple[mp.mpf, mp.mpf]:
    """How far the texts ``perturbed`` (``written`` with a term added to one) are from
    passing, at 50 digits: the largest over the entries of the symplecticity condition, and
    over those of ``b_q - b_p``, of the residual over twice the first-order bound that the
    allowances of the ``written`` texts put on it (above 1: beyond what the written digits
    can explain; inf for a residual where the texts are exact)."""
    from stepsafe.files.expressions import mpmath_backend, value_of

    def each(tree, f):
        return {k: [[f(x) for x in row] if isinstance(row, list) else f(row) for row in v]
                for k, v in tree.items()}

    def ratio(residual, allow):
        if abs(residual) < mp.mpf("1e-45"):  # the 50-digit evaluation's own rounding
            return mp.mpf(0)
        return abs(residual) / (2 * allow) if allow else mp.inf

    with mp.workdps(50):
        values = each(perturbed, lambda x: value_of(x, None, mpmath_backend()))
        allow = each(written, _allowance)
        if kind == "rk":
            values, allow = ({"A_q": t["A"], "b_q": t["b"], "A_p": t["A"], "b_p": t["b"]}
                             for t in (values, allow))
        Aq, bq, Ap, bp = (values[k] for k in ("A_q", "b_q", "A_p", "b_p"))
        dAq, dbq, dAp, dbp = (allow[k] for k in ("A_q", "b_q", "A_p", "b_p"))
        s = len(bq)
        sep = max(ratio(bq[i] * Ap[i][j] + Aq[j][i] * bp[j] - bq[i] * bp[j],
                        sum(abs(x) * dy + dx * abs(y) + dx * dy for x, dx, y, dy in (
                            (bq[i], dbq[i], Ap[i][j], dAp[i][j]),
                            (Aq[j][i], dAq[j][i], bp[j], dbp[j]),
                            (bq[i], dbq[i], bp[j], dbp[j]))))
                  for i in range(s) for j in range(s))
        return sep, max(ratio(bq[i] - bp[i], dbq[i] + dbp[i]) for i in range(s))


def _entries(coefficients: dict) -> list[tuple[str, int, int | None]]:
    """Every coefficient's place: (key, row, column or None)."""
    return [(k, i, j) for k in sorted(coefficients) for i, row in enumerate(coefficients[k])
            for j in (range(len(row)) if isinstance(row, list) else [None])]


def _perturbed(coefficients: dict, where: tuple[str, int, int | None], delta: mp.mpf,
               sign: str) -> dict:
    """The texts with ``sign delta`` (4 digits, exact) written after the one at ``where``."""
    key, i, j = where
    term = f"{sign} {float(delta):.3e}"
    perturbed = {k: [list(r) if isinstance(r, list) else r for r in v]
                 for k, v in coefficients.items()}
    if j is None:
        perturbed[key][i] = f"{perturbed[key][i]} {term}"
    else:
        perturbed[key][i][j] = f"{perturbed[key][i][j]} {term}"
    return perturbed


#: how far below its tolerance the perturbation of a coefficient may be written
PERTURBED = settings(max_examples=40, deadline=None,
                     suppress_health_check=[HealthCheck.too_slow,
                                            HealthCheck.function_scoped_fixture])


@PERTURBED
@given(name=st.sampled_from(sorted(TABLEAUX)), which=st.integers(0, 10 ** 6),
       exponent=st.floats(-14, -6), sign=st.sampled_from(["+", "-"]))
# Lobatto IIIB's last column is 0 and IIIA's last row is b, so the last b_p is in no entry
# of the separable condition: that condition stays at its 17-digit rounding (1.7e-17,
# within the digits) and only b_q = b_p is lost
@example(name="lobatto3ab4-17digits", which=35, exponent=-6.0, sign="+")
@example(name="lobatto3ab5-17digits", which=54, exponent=-14.0, sign="-")
def test_a_tableau_perturbed_beyond_its_digits_is_refused(name, which, exponent, sign,
                                                           tmp_path, run):
    """One coefficient (``which`` of them, modulo their count) plus or minus delta (1e-14
    ... 1e-6, written as an exact expression beside the text): whether
    each condition's entries lie within twice the first-order bound that the written digits
    put on them is decided here at 50 digits. Not symplectic where the separable condition
    is beyond its digits; symplectic only for separable H where only ``b_q = b_p`` is (a
    coefficient that no entry of the separable condition depends on); check refuses the
    step on the model that needs what is lost."""
    kind, coefficients = TABLEAUX[name]
    places = _entries(coefficients)
    where = places[which % len(places)]
    perturbed = _perturbed(coefficients, where, mp.mpf(10) ** exponent, sign)
    sep, weights = _beyond_digits(kind, coefficients, perturbed)
    assert sep > 1 or weights > 1  # beyond the written digits, at 50 digits
    assume(abs(sep - 1) > 1e-6)  # not at the edge, where the 50 digits decide nothing
    path = _write(tmp_path / "p.yaml", kind, perturbed)
    code, out, _ = run("validate", str(path))
    assert code == 0
    res = residuals(resolve(str(path))[0])
    assert not res.symplectic
    if sep > 1:
        assert "not symplectic" in out and not res.symplectic_for_separable, out
        code, out, _ = run("check", "--method", str(path), "--beta", "1", "--step", "0.5")
        assert code == 1 and "never preserved" in out, out
    else:
        assert "symplectic only for separable H" in out and res.symplectic_for_separable, out
        code, out, _ = run("check", "--method", str(path), "--saddle-beta", "1", "--step",
                           "0.5")
        assert code == 1 and "never preserved" in out, out


def _rounded_places(name: str) -> list[tuple[str, int, int | None]]:
    """The places of ``name``'s coefficients whose texts carry a rounding."""
    coefficients = TABLEAUX[name][1]
    return [(k, i, j) for k, i, j in _entries(coefficients) if _allowance(
        coefficients[k][i] if j is None else coefficients[k][i][j])]


@PERTURBED
@given(name=st.sampled_from(sorted(n for n in TABLEAUX if _rounded_places(n))),
       which=st.integers(0, 10 ** 6), exponent=st.floats(-22, -17),
       sign=st.sampled_from(["+", "-"]))
def test_a_tableau_perturbed_within_its_digits_passes(name, which, exponent, sign, tmp_path,
                                                      run):
    """A tableau printed to 17 or 30 digits with a rounded coefficient c (``which`` of them,
    modulo their count) plus or minus ``|c| delta`` (delta 1e-22 ... 1e-17, below the 4 ulps
    of float64 its digits may carry): every entry of both conditions stays within twice
    the first-order bound of the written digits at 50 digits, and validate and check pass
    it as they pass the tableau as printed."""
    kind, coefficients = TABLEAUX[name]
    places = _rounded_places(name)
    key, i, j = where = places[which % len(places)]
    text = coefficients[key][i] if j is None else coefficients[key][i][j]
    with mp.workdps(50):
        size = abs(mp.mpf(text))
    perturbed = _perturbed(coefficients, where, size * mp.mpf(10) ** exponent, sign)
    sep, weights = _beyond_digits(kind, coefficients, perturbed)
    assert sep < 1 and weights < 1  # within the written digits, at 50 digits
    path = _write(tmp_path / "p.yaml", kind, perturbed)
    code, out, _ = run("validate", str(path))
    assert code == 0 and "warning" not in out, out
    assert residuals(resolve(str(path))[0]).symplectic
    code, out, _ = run("check", "--method", str(path), "--beta", "1", "--step", "0.5")
    assert code == 0 and out.startswith("SAFE"), out


def test_the_midpoint_rule_off_by_1e_12_is_a_sink_and_never_safe(tmp_path, run):
    """a = 1/2 + 1e-12: det M - 1 = -2e-12 z^2 / (1 + a^2 z^2) at 50 digits (a centre
    becomes a slow sink), so no step keeps the centre; 1/2 itself is safe at that step."""
    z = mp.mpf("1.0483953384532054")
    with mp.workdps(50):
        a = mp.mpf(1) / 2 + mp.mpf("1e-12")
        R_ = (1 + (1 - a) * 1j * z) / (1 - a * 1j * z)  # the stability function at i z
        assert abs(abs(R_) ** 2 - 1 - (-2e-12 * z ** 2 / (1 + a ** 2 * z ** 2))) < 1e-22
        assert abs(R_) ** 2 - 1 < mp.mpf("-1.7e-12")
    for text, code_expected in (("1/2 + 1e-12", 1), ("1/2", 0)):
        path = _write(tmp_path / "m.yaml", "rk", {"A": [[text]], "b": ["1"]})
        code, out, _ = run("check", "--method", str(path), "--beta", "1", "--step",
                           "1.0483953384532054")
        assert code == code_expected, out
    code, out, _ = run("validate", str(tmp_path / "m.yaml"))
    assert "warning" not in out
    _write(tmp_path / "m.yaml", "rk", {"A": [["1/2 + 1e-12"]], "b": ["1"]})
    code, out, _ = run("validate", str(tmp_path / "m.yaml"))
    assert code == 0 and "not symplectic" in out


def test_gauss2_off_by_1e_13_is_not_symplectic(tmp_path, run):
    """Gauss s = 2 with 1e-13 added to a_11: entry (1, 1) of the condition is 2 b_1 1e-13
    = 1e-13 at 50 digits; validate says not symplectic and check refuses the step that the
    exact tableau keeps."""
    kind, exact = EXACT["gauss2"]
    perturbed = {"A": [["1/4 + 1e-13", exact["A"][0][1]], exact["A"][1]], "b": exact["b"]}
    sep, _ = _defects(kind, perturbed)
    with mp.workdps(50):
        assert abs(sep - mp.mpf("1e-13")) < mp.mpf("1e-40")
    for coefficients, verdict in ((exact, 0), (perturbed, 1)):
        path = _write(tmp_path / "g.yaml", kind, coefficients)
        code, out, _ = run("check", "--method", str(path), "--beta", "1", "--step", "1")
        assert code == verdict, out
    code, out, _ = run("validate", str(path))
    assert "not symplectic" in out


def test_decimals_of_ten_digits_or_more_carry_their_rounding():
    """The written digits decide the allowance: a 10-digit literal is a rounding (half its
    last digit), a short one is exact, a 17-digit one carries 4 ulps of float64."""
    from stepsafe.files.expressions import EPS, significant_digits, written_rounding

    assert [significant_digits(t) for t in ("0.0250", "1e-12", "1000", "1000.", "0.5",
                                            "1234567891")] == [3, 1, 1, 4, 1, 10]
    assert written_rounding("0.5") == written_rounding("1e-12") == 0.0
    assert written_rounding("0.1234567891") == pytest.approx(5e-11)
    assert written_rounding("1.234567891e-3") == pytest.approx(5e-13)
    assert written_rounding("0.21132486540518713") == pytest.approx(4 * EPS * 0.2113248654)


@pytest.mark.parametrize("name", [n for n in builtin_names() if n not in ("gauss", "lobatto3ab")])
def test_every_library_file_is_symplectic_exactly_when_its_condition_holds(name):
    """For the RK/PRK files the condition is computed here at 50 digits from the texts;
    every other kind is symplectic by construction (a composition as its base), but for
    the Langevin splittings, whose friction step contracts (det M = exp(-gamma h))."""
    method = resolve(name)[0]
    tree = load_yaml(builtin_dir() / f"{name}.yaml")
    res = residuals(method)
    if tree["kind"] in ("rk", "prk"):
        keys = ("A", "b") if tree["kind"] == "rk" else ("A_q", "b_q", "A_p", "b_p")
        sep, weights = _defects(tree["kind"], {k: tree[k] for k in keys})
        assert res.symplectic_for_separable == (sep < mp.mpf("1e-40"))
        assert res.symplectic == (sep < mp.mpf("1e-40") and weights < mp.mpf("1e-40"))
    elif tree["kind"] == "langevin":
        assert not res.symplectic_for_separable
    elif tree["kind"] != "composition":
        assert res.symplectic

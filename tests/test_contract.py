"""The command-line contract on generated hostile input (hypothesis).

Every invocation exits 0, 1 (check: unsafe) or 2 (bad input) -- never 3, never a
traceback; an error is exactly one line on stderr; ``--json`` prints one valid JSON
document. Inputs are generated, not listed: scene files with random keys, modes and
systems at extreme magnitudes, method files with hostile coefficients, Hamiltonians built
from a small grammar with coefficients from 1e-300 to 1e300, modes CSV files.
"""

from __future__ import annotations

import json
import math

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from stepsafe.cli import main

SETTINGS = settings(max_examples=40, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                           HealthCheck.function_scoped_fixture])


def _invoke(*args: str):
    result = CliRunner().invoke(main, list(args), catch_exceptions=True)
    return result.exit_code, result.stdout, result.stderr, result.exception


def _assert_contract(code, out, err, exc, as_json: bool) -> None:
    assert exc is None or isinstance(exc, SystemExit), repr(exc)
    assert code in (0, 1, 2), (code, err)
    assert "Traceback" not in out + err
    assert "Warning" not in err, err
    if code == 2:
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("stepsafe: error:"), err
    elif as_json:
        json.loads(out)


# -- numbers from 1e-300 to 1e300, and the awkward ones ---------------------------------
extreme = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False, width=64).filter(lambda x: x != 0),
    st.sampled_from([0.0, -0.0, 1e-300, 1e300, -1e-300, 5e-324, 1.7976931348623157e308]),
    st.integers(-5, 5).map(float),
)
yaml_number = st.one_of(extreme.map(repr), st.sampled_from(
    ["nan", ".nan", "inf", "-.inf", "1e999", "1_0", "'3'", "0x10", "²", "٣", "true", "~", "[]",
     "{}", "'[red]x[/red]'", "1/2"]))


@st.composite
def modes_yaml(draw) -> str:
    items = []
    for _ in range(draw(st.integers(0, 4))):
        model = draw(st.sampled_from(["oscillator", "saddle", "inverted", "saddle-p", "bogus"]))
        items.append(f"{{beta: {draw(yaml_number)}, model: {model}}}")
    return "[" + ", ".join(items) + "]"


@st.composite
def matrix_yaml(draw) -> str:
    n = draw(st.integers(1, 3))
    rows = [[draw(yaml_number) for _ in range(draw(st.sampled_from([n, n, n + 1])))]
            for _ in range(n)]
    return "[" + ", ".join("[" + ", ".join(r) + "]" for r in rows) + "]"


@st.composite
def hamiltonian(draw) -> str:
    """H from a grammar: sums of coefficient * monomial or elementary function."""
    coef = draw(st.sampled_from(["1e-300", "1e300", "1e-6", "1e6", "2", "-1", "0", "1e-32"]))
    terms = [f"{coef}*p**2"]
    for _ in range(draw(st.integers(1, 3))):
        c = draw(st.sampled_from(["1e-300", "1e300", "1e-6", "1e6", "3", "-0.5", "1e-32", "0"]))
        f = draw(st.sampled_from(["q**2", "q**4", "q**3", "cos(q)", "sin(q)/q", "exp(q)",
                                  "q*p", "log(q)", "sqrt(q)", "q**2*p", "exp(1000*q)",
                                  "1/q", "tanh(q)", "cosh(q)"]))
        terms.append(f"{c}*{f}")
    return " + ".join(terms)


@st.composite
def scene_text(draw) -> str:
    lines = []
    method = draw(st.sampled_from(["verlet", "pefrl", "midpoint", "nosuch", "{name: gauss, "
                                   "stages: 2}", "{name: gauss}", "{name: lobatto3ab, stages: "
                                   "'²'}", "[verlet]", "''", "yoshida4"]))
    lines.append(f"method: {method}")
    if draw(st.booleans()):
        lines.append(f"h: {draw(yaml_number)}")
    if draw(st.booleans()):
        lines.append(f"margin: {draw(yaml_number)}")
    if draw(st.booleans()):
        lines.append(f"zmax: {draw(yaml_number)}")
    kind = draw(st.sampled_from(["modes", "stiffness", "hessian", "hamiltonian", "both",
                                 "none", "junk"]))
    if kind in ("modes", "both"):
        lines.append(f"modes: {draw(modes_yaml())}")
    if kind in ("stiffness", "both"):
        lines.append(f"system: {{stiffness: {draw(matrix_yaml())}}}")
    if kind == "hessian":
        lines.append(f"system: {{hessian: {draw(matrix_yaml())}}}")
    if kind == "hamiltonian":
        lines.append(f'system: {{hamiltonian: "{draw(hamiltonian())}", box: {{q: [-1, 1], '
                     f'p: [-1, 1]}}}}')
    if kind == "junk":
        lines.append(draw(st.sampled_from(["springs: 3", "modes: 3", "system: [1, 2]",
                                           "- a", "modes: [{beta: 1, colour: red}]"])))
    return "\n".join(lines) + "\n"


@SETTINGS
@given(text=scene_text(), as_json=st.booleans(), command=st.sampled_from(["check", "advise"]))
def test_scene_files_keep_the_contract(tmp_path_factory, text, as_json, command):
    path = tmp_path_factory.mktemp("scene") / "scene.yaml"
    path.write_text(text)
    args = [command, str(path)] + (["--step", "0.1"] if command == "check" and
                                   "h:" not in text else []) + (["--json"] if as_json else [])
    _assert_contract(*_invoke(*args), as_json)


@st.composite
def method_text(draw) -> str:
    kind = draw(st.sampled_from(["splitting", "rk", "prk", "composition", "bogus"]))
    n = draw(st.integers(1, 3))

    def vector(k: int) -> str:
        return "[" + ", ".join(draw(yaml_number) for _ in range(k)) + "]"

    def square(k: int) -> str:
        return "[" + ", ".join(vector(k) for _ in range(k)) + "]"

    title = draw(st.sampled_from(["t", "'[red]x[/red]'", "'[/]'", '"\\e[31mred\\e]0;pwn\\a"',
                                  "'\u009b2J'"]))
    head = f"name: gen\nkind: {kind}\norder: {draw(st.sampled_from(['2', '²', '-1', 'x']))}\n" \
           f"source: {title}\ntitle: {title}\n"
    body = {
        "splitting": f"drift: {vector(n + 1)}\nkick: {vector(n)}\n",
        "rk": f"A: {square(n)}\nb: {vector(n)}\n",
        "prk": f"A_q: {square(n)}\nb_q: {vector(n)}\nA_p: {square(n)}\nb_p: {vector(n)}\n",
        "composition": "base: " + draw(st.sampled_from(["verlet", "midpoint", "nosuch"]))
                       + "\n" + draw(st.sampled_from([f"weights: {vector(n)}\n",
                                                      "recipe: triple-jump\n",
                                                      "recipe: bogus\n"])),
        "bogus": "drift: [1]\n",
    }[kind]
    return head + body


@SETTINGS
@given(text=method_text(), command=st.sampled_from(["region", "show", "validate", "check"]),
       as_json=st.booleans())
def test_method_files_keep_the_contract(tmp_path_factory, text, command, as_json):
    path = tmp_path_factory.mktemp("method") / "gen.yaml"
    path.write_text(text)
    if command == "check":
        args = ["check", "--method", str(path), "--step", "0.3", "--beta", "1",
                "--inverted-beta", "2"]
    elif command == "region":
        args = ["region", str(path), "--zmax", "6"]
    else:
        args = [command, str(path)]
    if as_json and command != "validate":
        args.append("--json")
    code, out, err, exc = _invoke(*args)
    _assert_contract(code, out, err, exc, as_json and command != "validate")
    if code == 0 and command in ("region", "show") and not as_json:
        # file text is printed literally: no terminal control characters pass through
        assert not any(ch in out for ch in "\x1b\x07\x9b"), out


@SETTINGS
@given(st.lists(st.tuples(st.one_of(extreme, st.sampled_from(
    ["x", "", "1_0", "nan", "-1", "1e999"])).map(str),
    st.sampled_from(["oscillator", "saddle", "inverted", "Oscillator", ""])),
    min_size=0, max_size=6), st.booleans())
def test_modes_csv_keeps_the_contract(tmp_path_factory, rows, header):
    path = tmp_path_factory.mktemp("modes") / "modes.csv"
    text = ("beta,model\n" if header else "") + "".join(f"{b},{m}\n" for b, m in rows)
    path.write_text(text)
    _assert_contract(*_invoke("check", "--method", "verlet", "--step", "0.01", "--modes",
                              str(path), "--json"), True)


@pytest.mark.slow
@SETTINGS
@given(beta=extreme, h=extreme, zmax=st.one_of(st.none(), extreme),
       margin=st.one_of(st.none(), st.floats(-1, 2, allow_nan=False)),
       model=st.sampled_from(["--beta", "--saddle-beta", "--inverted-beta"]),
       name=st.sampled_from(["verlet", "gauss", "kahan-li8", "midpoint", "symplectic-euler"]))
def test_command_line_numbers_keep_the_contract(beta, h, zmax, margin, model, name):
    args = ["check", "--method", name, model, repr(beta), "--step", repr(h), "--json"]
    if name == "gauss":
        args += ["-s", "3"]
    if zmax is not None:
        args += ["--zmax", repr(zmax)]
    if margin is not None:
        args += ["--margin", repr(margin)]
    code, out, err, exc = _invoke(*args)
    _assert_contract(code, out, err, exc, True)
    if code in (0, 1):
        data = json.loads(out)
        assert data["safe"] == (code == 0)
        assert math.isfinite(beta) and math.isfinite(h)


@pytest.mark.slow
@SETTINGS
@given(name=st.sampled_from(["verlet", "pefrl", "yoshida4", "bcss2", "midpoint", "ruth3",
                             "symplectic-euler", "kahan-li8"]),
       betas=st.lists(st.tuples(st.floats(-6, 6), st.sampled_from(["--beta", "--saddle-beta",
                                                                    "--inverted-beta"])),
                      min_size=1, max_size=3),
       margin=st.sampled_from(["1", "0.9"]))
def test_printed_limits_are_steps_check_accepts(name, betas, margin):
    """advise prints 'Safe: 0 < h < X' (X rounded down): check --step X must pass, and a
    step at the JSON h_max itself (the open end) must not."""
    args = [a for log_beta, opt in betas for a in (opt, repr(10 ** log_beta))]
    code, out, err, exc = _invoke("advise", "--method", name, *args, "--margin", margin)
    _assert_contract(code, out, err, exc, False)
    if "Safe: 0 < h < " not in out:
        return
    shown = out.split("Safe: 0 < h < ")[1].split(",")[0].split()[0].strip()
    code, _, err, exc = _invoke("check", "--method", name, *args, "--margin", margin,
                                "--step", shown)
    assert code == 0, (shown, err)
    data = json.loads(_invoke("advise", "--method", name, *args, "--margin", margin,
                              "--json")[1])
    code, _, _, _ = _invoke("check", "--method", name, *args, "--margin", margin, "--step",
                            repr(data["h_max"]))
    assert code == 1


# ------------------------------------------------- scene values at and beyond their ranges

EDGE_SCENES = [
    # (scene text, expected exit code, text the one-line error must contain)
    ("method: verlet\nh: 0\nmodes: [{beta: 1}]\n", 2, "::$.h: must be > 0"),
    ("method: verlet\nh: -1\nmodes: [{beta: 1}]\n", 2, "::$.h: must be > 0"),
    ("method: verlet\nh: 1e-400\nmodes: [{beta: 1}]\n", 2, "::$.h"),
    ("method: verlet\nh: 0.1\nmargin: 0\nmodes: [{beta: 1}]\n", 2, "::$.margin"),
    ("method: verlet\nh: 0.1\nmargin: 1.5\nmodes: [{beta: 1}]\n", 2, "::$.margin"),
    ("method: verlet\nh: 0.1\nzmax: 0\nmodes: [{beta: 1}]\n", 2, "::$.zmax"),
    ("method: verlet\nh: 0.1\nzmax: -5\nmodes: [{beta: 1}]\n", 2, "::$.zmax"),
    ("method: verlet\nh: 0.1\nmargin: 5e-324\nmodes: [{beta: 1}]\n", 2, "margin"),
    ("method: verlet\nh: 0.1\nsystem: {hessian: [[0, 0], [0, 0]]}\n", 2, "zero"),
    ("method: verlet\nh: 0.1\nsystem: {hamiltonian: '1e-320*q*p', "
     "box: {q: [-1, 1], p: [-1, 1]}}\n", 0, ""),
    ("method: verlet\nh: 0.1\nsystem: {hamiltonian: '1e300*p**2 + 1e300*q**2', "
     "box: {q: [-1, 1], p: [-1, 1]}}\n", 1, ""),
]


def test_scene_values_out_of_range_or_beyond_float64(tmp_path):
    """Out-of-range scene values name the file and key; a zero Hessian is nothing to
    analyse (exit 2, never SAFE); limits beyond float64 are null in --json, never inf."""
    for k, (text, expected, message) in enumerate(EDGE_SCENES):
        path = tmp_path / f"s{k}.yaml"
        path.write_text(text)
        for as_json in (False, True):
            code, out, err, exc = _invoke("check", str(path), *(["--json"] if as_json else []))
            _assert_contract(code, out, err, exc, as_json)
            assert code == expected, (text, code, err)
            assert message in err, (text, err)


def test_closed_stderr_keeps_the_exit_code(tmp_path):
    """With stderr closed (2>&-) a bad input is still exit 2, not an internal error."""
    import subprocess
    import sys

    script = ("import sys\nfrom stepsafe.cli import main\n"
              "main(['check', '--method', 'nope', '--step', '3', '--beta', '1'])\n")
    result = subprocess.run(["bash", "-c", f'"{sys.executable}" -c "$0" 2>&-', script],
                            capture_output=True, text=True)
    assert result.returncode == 2


def test_family_without_stages_in_a_scene_names_the_key(tmp_path):
    path = tmp_path / "g.yaml"
    path.write_text("method: gauss\nh: 0.1\nmodes: [{beta: 1}]\n")
    code, out, err, exc = _invoke("check", str(path))
    _assert_contract(code, out, err, exc, False)
    assert code == 2 and "g.yaml::$.method" in err and "stages:" in err


@pytest.mark.slow
@settings(max_examples=25, deadline=None)
@example(name="sofroniou-spaletta10", log_betas=[math.log10(13350.168537322375)],
         margin=1.0)
@example(name="bcss2", log_betas=[math.log10(12468.303216891742)], margin=1.0)
@given(name=st.sampled_from(["verlet", "pefrl", "yoshida4", "bcss2", "blanes-moan6",
                             "kahan-li8", "midpoint", "rk4", "chin-4a",
                             "sofroniou-spaletta10"]),
       log_betas=st.lists(st.floats(-6.0, 6.0), min_size=1, max_size=4),
       margin=st.sampled_from([1.0, 0.9, 0.5]))
def test_the_float_just_below_h_max_passes_check_and_h_max_does_not(name, log_betas,
                                                                   margin):
    """The JSON/API h_max is the open end of the safe interval: check passes the next
    float below it (beta h rounded up must not reach the uncertainty band of the boundary,
    which bcss2 and sofroniou-spaletta10 come close to) and fails h_max itself."""
    import stepsafe

    betas = [10.0 ** x for x in log_betas]
    advice = stepsafe.advise(name, betas, margin=margin)
    assume(advice.h_max_limited_by == "boundary")
    below = math.nextafter(advice.h_max, 0.0)
    assert stepsafe.check(name, below, betas, margin=margin).safe
    assert not stepsafe.check(name, advice.h_max, betas, margin=margin).safe

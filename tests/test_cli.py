"""The CLI through click's runner: JSON shape, human output, errors and exit codes."""

from __future__ import annotations

import json
import math

import pytest


def test_region_json_shape(run_json):
    data = run_json("region", "lobatto3ab", "-s", "3")
    assert data["method"] == "lobatto3ab-s3" and data["kind"] == "prk"
    assert data["stages"] == 3 and data["symplectic"] is True
    osc = data["models"]["oscillator"]
    assert abs(osc["first_boundary"] - math.sqrt(8)) < 1e-12
    # the interval stops the boundary's float64 uncertainty short of it
    assert osc["intervals"] == [[0.0, osc["first_boundary"]
                                 - osc["first_boundary_uncertainty"]]]
    assert osc["islands"][0]["orientation"] == "reversed"
    assert set(data["models"]) == {"oscillator", "saddle", "inverted"}
    assert data["models"]["saddle"]["intervals"] == [[0.0, None]]
    assert data["models"]["saddle"]["first_boundary"] is None
    inv = data["models"]["inverted"]
    assert inv["poles"] == [inv["first_boundary"]] and inv["first_boundary_kind"] == "pole"


def test_region_base_swap_is_the_papers_midpoint_composition(run_json):
    data = run_json("region", "yoshida4", "--base", "midpoint", "--model", "saddle")
    saddle = data["models"]["saddle"]
    assert saddle["first_boundary_kind"] == "resonance"  # M = +I: R(z) returns to 1
    assert 1.13 < saddle["first_boundary"] < 1.14


def test_region_human_output(run):
    code, out, _ = run("region", "gauss", "-s", "2", "--model", "oscillator")
    assert code == 0
    assert "3.46410161514" in out and "M = -I" in out and "reversed" in out


def test_non_symplectic_reports_classical_interval(run_json):
    data = run_json("region", "rk4", "--model", "oscillator")
    osc = data["models"]["oscillator"]
    assert data["symplectic"] is False and osc["intervals"] == []
    assert abs(osc["classical_intervals"][0][1] - 2 * math.sqrt(2)) < 1e-12


def test_methods_lists_the_required_names(run_json):
    rows = run_json("methods")
    names = {r["name"] for r in rows}
    for required in ("symplectic-euler", "verlet", "midpoint", "gauss -s N", "lobatto3ab -s N",
                     "yoshida4", "triple-jump6", "suzuki4", "rk4"):
        assert required in names
    rk4 = next(r for r in rows if r["name"] == "rk4")
    assert rk4["symplectic"] is False


def test_show_reports_residuals(run_json):
    data = run_json("show", "gauss", "-s", "3")
    assert data["symplectic"] and data["residuals"]["symplecticity"] < 1e-15
    assert data["order"] == 6 and len(data["coefficients"]["A"]) == 3
    rk4 = run_json("show", "rk4")
    assert rk4["symplectic"] is False and rk4["residuals"]["symplecticity"] > 0.01


@pytest.mark.parametrize("args, message", [
    (["region", "verlte"], "did you mean verlet"),
    (["region", "gauss"], "give the stage count"),
    (["region", "gauss", "-s", "0"], "-s must be between 1"),
    (["region", "lobatto3ab", "-s", "1"], "-s must be between 2"),
    (["region", "gauss", "-s", "100000"], "-s must be between"),
    (["region", "verlet", "-s", "3"], "applies only to the families"),
    (["region", "verlet", "--zmax", "nan"], "zmax must be a positive finite number"),
    (["region", "verlet", "--zmax", "0"], "zmax must be a positive finite number"),
    (["region", "verlet", "--zmax", "-2"], "zmax must be a positive finite number"),
    (["region", "verlet", "--zmax", "inf"], "zmax must be a positive finite number"),
    (["region", "verlet", "--base", "midpoint"], "applies to compositions"),
    (["region", "missing/file.yaml"], "no such file"),
    (["show", "nothing-like-this"], "unknown method"),
])
def test_bad_input_is_one_line_exit_2(run, args, message):
    code, out, err = run(*args)
    assert code == 2
    assert message in err and "Traceback" not in err + out
    assert len(err.strip().splitlines()) == 1


def test_bad_option_type_exit_2(run):
    code, _, err = run("region", "gauss", "-s", "three")
    assert code == 2 and "Traceback" not in err


def test_base_can_be_a_family_member(run_json, run):
    data = run_json("region", "yoshida4", "--base", "gauss:2", "--model", "saddle", "--verify")
    assert data["stages"] == 6 and data["verify"]["ok"]
    code, _, err = run("region", "yoshida4", "--base", "lobatto3ab")
    assert code == 2 and "lobatto3ab:N" in err


# --- usage errors: one line, exit 2; -h is never help ------------------------------------

ROOT = __import__("pathlib").Path(__file__).resolve().parent.parent


def _stepsafe(*args, **kwargs):
    """The real process (``python -m stepsafe``): exit codes, pipes and streams as in CI."""
    import subprocess
    import sys

    if "stdout" not in kwargs:
        kwargs.setdefault("capture_output", True)
    return subprocess.run([sys.executable, "-m", "stepsafe", *args], cwd=ROOT, text=True,
                          timeout=120, **kwargs)


def _one_error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("stepsafe: error: ") and "Traceback" not in err
    return lines[0]


def test_dash_h_is_an_error_not_help_in_the_real_process():
    """The CI trap: with -h as help, this unsafe step passed with exit 0."""
    proc = _stepsafe("check", "--method", "verlet", "--beta", "0.697", "-h", "3")
    assert proc.returncode == 2 and proc.stdout == ""
    line = _one_error_line(proc.stderr)
    assert "--step" in line and "--help" in line
    assert _stepsafe("check", "--method", "verlet", "--beta", "0.697", "--step", "3"
                     ).returncode == 1
    assert _stepsafe("check", "--help").returncode == 0


@pytest.mark.parametrize("args", [
    ["check", "--method", "verlet", "--beta", "1", "-h", "3"],
    ["check", "-h"], ["check", "-H", "3"], ["check", "--H", "3"],
    ["advise", "--method", "verlet", "--beta", "1", "-h"], ["region", "verlet", "-h"],
    ["show", "verlet", "-h"], ["methods", "-h"], ["compare", "-h"], ["error", "-h"],
    ["plot", "-h"], ["validate", "-h"], ["schema", "-h"], ["-h"], ["-h", "check"],
])
def test_dash_h_is_a_usage_error_everywhere(run, args):
    code, out, err = run(*args)
    assert code == 2 and out == ""
    line = _one_error_line(err)
    assert "is not an option" in line and "--help" in line
    assert ("--step" in line) == (args[0] == "check")


@pytest.mark.parametrize("flag", ["--step", "--h"])
def test_step_option_and_its_alias(run, flag):
    assert run("check", "--method", "verlet", "--beta", "1", flag, "0.1")[0] == 0
    assert run("check", "--method", "verlet", "--beta", "1", flag, "3")[0] == 1


@pytest.mark.parametrize("args, message", [
    ([], "missing command (one of: advise, check,"),
    (["--debug"], "missing command"),
    (["bogus"], "No such command 'bogus'"),
    (["region"], "Missing argument 'METHOD'"),
    (["validate"], "Missing argument"),
    (["plot", "verlet", "-o"], "requires an argument"),
    (["region", "verlet", "--model", "bogus"], "'bogus' is not one of"),
    (["region", "gauss", "-s", "three"], "'three' is not a valid integer"),
    (["check", "--method", "verlet", "--beta", "1", "--step"], "requires an argument"),
    (["check", "--method", "verlet", "--beta", "x", "--step", "1"], "'x' is not a valid float"),
    (["check", "--bogus"], "No such option"),
    (["schema", "nothing"], "is not one of"),
    (["--nope"], "No such option"),
])
def test_usage_errors_are_one_line_exit_2(run, args, message):
    code, out, err = run(*args)
    assert code == 2 and out == ""
    line = _one_error_line(err)
    assert message in line and "--help')" in line
    assert "Usage:" not in err


def test_usage_error_names_the_command():
    proc = _stepsafe("check", "--method", "verlet", "--beta", "1", "--step")
    assert proc.returncode == 2
    assert "(see 'stepsafe check --help')" in _one_error_line(proc.stderr)
    proc = _stepsafe()  # bare stepsafe: a usage error too, not 34 lines of help
    assert proc.returncode == 2 and proc.stdout == ""
    assert "missing command" in _one_error_line(proc.stderr)


def test_unknown_options_of_any_spelling_are_one_line(run):
    from hypothesis import given, settings
    from hypothesis import strategies as st

    names = st.text(st.characters(codec="utf-8", categories=("L", "N", "P", "S", "Cc")),
                    min_size=1, max_size=12)

    @settings(max_examples=40, deadline=None)
    @given(command=st.sampled_from(["check", "advise", "region", "show", "compare", "error"]),
           name=names)
    def prop(command, name):
        code, out, err = run(command, "--zz" + name)
        assert code == 2 and out == ""
        line = _one_error_line(err)
        assert all(ch == "\t" or ch.isprintable() for ch in line), line

    prop()


# --- output that cannot be written: a closed pipe, a full disk ----------------------------

MANY_BETAS = [a for i in range(1, 301) for a in ("--beta", str(i))]


@pytest.mark.parametrize("args, code", [
    (["check", "--method", "verlet", "--step", "3", *MANY_BETAS], 1),
    (["check", "--method", "verlet", "--step", "3", "--json", *MANY_BETAS], 1),
    (["check", "--method", "verlet", "--step", "1e-4", *MANY_BETAS], 0),
    (["check", "examples/scene.yaml", "examples/paper-section3.yaml"], 1),
    (["region", "lobatto3ab", "-s", "3"], 0),
    (["show", "kahan-li8"], 0),
    (["methods"], 0),
    (["check", "--help"], 0),
])
def test_closed_pipe_exits_with_the_commands_own_code(args, code):
    """| head -1: the reader is gone before stepsafe writes. The verdict stands: exit 1 for
    an unsafe step, 0 for a safe one or another command; never 3, never a made-up 1."""
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-m", "stepsafe", *args], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # the read end: every write now fails with EPIPE
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == code, err
    assert err == ""


def test_scene_with_an_unsafe_step_is_unsafe():
    # the multi-scene pipe case above relies on this: the first scene is safe, the second not
    assert _stepsafe("check", "examples/scene.yaml").returncode == 0
    assert _stepsafe("check", "examples/paper-section3.yaml").returncode == 1


@pytest.mark.skipif(not __import__("os").path.exists("/dev/full"), reason="needs /dev/full")
@pytest.mark.parametrize("args", [
    ["check", "--method", "verlet", "--step", "0.1", "--beta", "1"],
    ["check", "--method", "verlet", "--step", "3", "--beta", "1", "--json"],
    ["region", "verlet"], ["region", "verlet", "--json"], ["methods"], ["check", "--help"],
])
def test_full_disk_is_one_line_exit_2(args):
    with open("/dev/full", "w") as full:
        proc = _stepsafe(*args, stdout=full, stderr=__import__("subprocess").PIPE)
    assert proc.returncode == 2
    assert _one_error_line(proc.stderr) == \
        "stepsafe: error: cannot write output: No space left on device"


# --- integers are written with the ASCII digits 0-9 ---------------------------------------

def _non_ascii_digit_strings():
    """Strings that str.isdigit() or int() may accept but that are not ASCII digits:
    superscripts, other scripts' digits (Arabic-Indic, Devanagari, fullwidth), mixed in
    with ASCII digits."""
    from hypothesis import strategies as st

    foreign = st.characters(categories=("Nd", "No", "Nl"), exclude_characters="0123456789")
    return st.builds(lambda a, f, b: a + f + b, st.text("0123456789", max_size=2),
                     st.text(foreign, min_size=1, max_size=3), st.text("0123456789", max_size=2))


METHOD_FILE = """\
name: m
kind: {kind}
order: {order}
{extra}source: test
{body}
"""


@pytest.mark.parametrize("field", ["order", "evaluations", "base.stages"])
def test_unicode_digits_in_method_file_integers_are_refused(run, tmp_path, field):
    from hypothesis import given, settings

    @settings(max_examples=30, deadline=None)
    @given(text=_non_ascii_digit_strings())
    def prop(text):
        quoted = '"' + text + '"'
        if field == "base.stages":
            body = "base: {name: gauss, stages: " + quoted + "}\nweights: [1]"
            src = METHOD_FILE.format(kind="composition", order=2, extra="", body=body)
        else:
            src = METHOD_FILE.format(
                kind="splitting", order=quoted if field == "order" else 2,
                extra=f"evaluations: {quoted}\n" if field == "evaluations" else "",
                body='drift: [0, 1]\nkick: ["1/2", "1/2"]')
        path = tmp_path / "m.yaml"
        path.write_text(src, encoding="utf-8")
        code, out, err = run("validate", str(path))
        assert code == 2 and out == "", (text, err)
        line = _one_error_line(err)
        assert f"{path}::$.{field}: must be a whole number written with the digits 0-9" in line

    prop()


def test_signed_and_quoted_ascii_integers_are_read_as_integers(run, tmp_path):
    path = tmp_path / "m.yaml"
    path.write_text(METHOD_FILE.format(kind="composition", order=" +4", extra="",
                                       body='base: {name: gauss, stages: "2"}\nweights: [1]'))
    code, out, err = run("validate", str(path))
    assert code == 0 and "order 4" in out, err


def test_unicode_digits_on_the_command_line_are_refused(run):
    from hypothesis import given, settings

    @settings(max_examples=30, deadline=None)
    @given(text=_non_ascii_digit_strings())
    def prop(text):
        for args in (["region", "yoshida4", "--base", f"gauss:{text}"],
                     ["region", "gauss", "-s", text],
                     ["check", "--method", "verlet", "--step", "0.1", "--beta", text],
                     ["compare", "--methods", f"gauss:{text}", "--beta", "1"]):
            code, out, err = run(*args)
            assert code == 2 and out == "", (args, err)
            assert "digits 0-9" in _one_error_line(err) or "bad stage count" in err

    prop()


def test_ascii_whole_numbers():
    from stepsafe.text import ascii_whole

    assert ascii_whole(" +12 ") == 12 and ascii_whole("007") == 7
    for bad in ("²", "٣", "３", "1²", "-1", "1.0", "1_0", "", " ", "+", None, 3, "9" * 5000):
        assert ascii_whole(bad) is None, bad


# --- compositions, recipes and huge tableaux: exit 2, not 3 -------------------------------

def _method_file(tmp_path, body: str, name: str = "m.yaml") -> str:
    path = tmp_path / name
    path.write_text("name: m\norder: 2\nsource: test\n" + body)
    return str(path)


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize("weights", ["[0, 1, 0]", "[1, 0]", "[0, 1]"])
def test_a_zero_weight_among_others_is_an_identity_substep(run_json, tmp_path, weights):
    """Allowed: the substep with weight 0 is the identity, the composition is the rest."""
    path = _method_file(tmp_path, f"kind: composition\nbase: midpoint\nweights: {weights}\n")
    data = run_json("region", path)
    ref = run_json("region", "midpoint")
    for model in ("oscillator", "saddle", "inverted"):
        ours, theirs = (d["models"][model]["first_boundary"] for d in (data, ref))
        assert ours == theirs or ours == pytest.approx(theirs, rel=1e-12), model


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize("command", [["region", "--model", "oscillator"],
                                     ["check", "--step", "1", "--beta", "1", "--method"]])
def test_rk_coefficients_too_large_are_refused_cleanly(run, tmp_path, command):
    path = _method_file(tmp_path, "kind: rk\nA: [[1e200, 0], [0, 1e-200]]\nb: [0.5, 0.5]\n")
    code, out, err = run(*command, path)
    assert code == 2 and out == ""
    assert "coefficients A, b too large to analyse" in _one_error_line(err)
    if command[0] == "region":  # --model all analyses the models it can and says so
        code, out, err = run("region", path, "--json")
        assert code == 0, err
        models = json.loads(out)["models"]
        assert "too large to analyse" in models["oscillator"]["not_analysed"]
        assert models["saddle"]["intervals"] == []  # not symplectic: never preserved


# --- text from files is printed literally ------------------------------------------------

HOSTILE_TEXT = ["[red]x[/red]", "[/]", "[bold]B", "[link=http://x]L[/link]", "\\[i]",
                "a\\", "\x1b[31mRED\x1b[0m", "\x1b]0;pwned\x07", "\x9b31m", "\u202eevil",
                "x\u200by", "\ud800", "line\nbreak", "\x00\x7f", "[1]", "\\\\[b]", "a\\",
                ":smile:", "\\["]


def _titled(tmp_path, title: str, source: str = "test") -> str:
    import json

    path = tmp_path / "t.yaml"
    path.write_text(f"name: m\nkind: splitting\norder: 2\ntitle: {json.dumps(title)}\n"
                    f"source: {json.dumps(source)}\ndrift: [0, 1]\nkick: [0.5, 0.5]\n",
                    encoding="utf-8", errors="surrogatepass")
    return str(path)


def _no_control_characters(out: str) -> None:
    import unicodedata

    bad = [ch for ch in out if ch not in "\n\t" and unicodedata.category(ch) in
           ("Cc", "Cf", "Cs", "Zl", "Zp")]
    assert not bad, (bad, out)


def test_printable_makes_controls_visible():
    from stepsafe.text import printable

    assert printable("a\x1b[31mb") == "a\\x1b[31mb"
    assert printable("\x9b\u202e\ud800\t") == "\\x9b\\u202e\\ud800\t"
    assert printable("plain [red] ²٣ é") == "plain [red] ²٣ é"


def test_file_text_is_shown_literally(run, tmp_path):
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from stepsafe.text import printable

    pieces = st.sampled_from(HOSTILE_TEXT) | st.text(
        st.sampled_from("[]/\\=#@:ab \x1b\x9b\x07\u202e\u2028"), max_size=8)
    texts = st.lists(pieces, min_size=1, max_size=3).map("".join)

    @settings(max_examples=40, deadline=None)
    @given(title=texts, source=texts)
    def prop(title, source):
        path = _titled(tmp_path, title, source)
        code, out, err = run("show", path)
        assert code == 0 and err == "", err
        _no_control_characters(out)
        assert f"m — {printable(title)}" == out.splitlines()[0]
        code, out, err = run("region", path, "--model", "oscillator")
        assert code == 0 and err == "", err
        _no_control_characters(out)
        assert printable(title) in out.replace("\n", "")
        import json

        data = json.loads(run("show", path, "--json")[1])
        assert (data["title"], data["source"]) == (title, source)  # --json: exact

    prop()


@pytest.mark.parametrize("text", HOSTILE_TEXT)
def test_source_in_the_show_table_is_literal(run, tmp_path, text):
    from stepsafe.text import printable

    code, out, err = run("show", _titled(tmp_path, "t", text))
    assert code == 0 and err == ""
    _no_control_characters(out)
    row = next(line for line in out.splitlines() if "source" in line)
    assert printable(text).strip() in row


def test_swapped_base_name_is_not_markup(run):
    code, out, _ = run("advise", "--method", "yoshida4", "--base", "midpoint", "--beta", "1")
    assert code == 0 and out.splitlines()[0].startswith("yoshida4[midpoint]")


def test_unknown_order_after_base_swap(run):
    code, out, _ = run("region", "yoshida4", "--base", "gauss:3", "--model", "oscillator")
    assert code == 0 and "order unknown" in " ".join(out.split()) and "None" not in out


def test_a_tab_in_file_text_is_kept(run, tmp_path):
    code, out, err = run("show", _titled(tmp_path, "a\tb", "tab\tok"))
    assert code == 0 and err == "" and out.startswith("m — a")


# --- plot -o writes exactly PATH or refuses ----------------------------------------------

@pytest.mark.parametrize("output, message", [
    ("out", "no extension"), ("out.xyz", "unknown format .xyz"), ("out.txt", "unknown format"),
    ("-", "not standard output"), (".png", "no extension"), ("plotdir", "a directory"),
    ("plotdir/", "a directory"), ("missing/x.png", "cannot write missing/x.png"),
])
def test_plot_refuses_what_it_would_not_write_exactly(run, tmp_path, monkeypatch, output,
                                                      message):
    pytest.importorskip("matplotlib")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "plotdir").mkdir()
    code, out, err = run("plot", "verlet", "-o", output)
    assert code == 2 and out == ""
    line = _one_error_line(err)
    assert message in line and "Traceback" not in err
    if "format" in message or "extension" in message:
        assert "png, ps" in line and "svg" in line and "pdf" in line  # lists the formats
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["plotdir"]


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize("output", ["out.png", "out.PNG", "out.eps", "out.svg", "out.pdf",
                                    "dots.in.name.jpg"])
def test_plot_writes_exactly_the_path_given(run, tmp_path, monkeypatch, output):
    pytest.importorskip("matplotlib")
    monkeypatch.chdir(tmp_path)
    code, out, err = run("plot", "verlet", "--phase", "-o", output)
    assert code == 0 and err == ""  # no matplotlib warnings (eps has no transparency)
    assert out.strip() == f"wrote {output}"
    assert [p.name for p in tmp_path.iterdir()] == [output]
    assert (tmp_path / output).stat().st_size > 0


# --- numpy warnings never reach stderr; overflow is reported as such ----------------------

@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize("model", ["oscillator", "saddle", "inverted"])
@pytest.mark.parametrize("method", [["verlet"], ["yoshida4"], ["gauss", "-s", "3"],
                                    ["lobatto3ab", "-s", "3"]])
def test_error_at_huge_z_says_overflow_without_warnings(run, run_json, method, model):
    data = run_json("error", *method, "--model", model, "--z", "0.5", "--z", "1e10",
                    "--z", "1e160", "--z", "1e300")
    rows = data["rows"]
    assert rows[0]["overflow"] is False and rows[0]["phase_error"] is not None
    for row in rows:
        if row["overflow"]:
            assert row["phase_error"] is None and row["energy_error"] is None
    if method == ["verlet"] and model != "saddle":  # M ~ z^2: 1e160, 1e300 overflow float64
        assert [r["overflow"] for r in rows] == [False, False, True, True]
        code, out, err = run("error", *method, "--model", model, "--z", "1e300")
        assert code == 0 and err == "" and "overflow" in out


# --- every frequency source is used; --zmax and --margin are checked everywhere -----------

def _modes_csv(tmp_path, rows: str) -> str:
    path = tmp_path / "modes.csv"
    path.write_text("beta,model\n" + rows)
    return str(path)


def test_compare_uses_a_modes_file_alone_and_with_betas(run_json, tmp_path):
    modes = _modes_csv(tmp_path, "2,oscillator\n0.5,saddle\n")
    alone = run_json("compare", "--modes", modes, "--methods", "verlet,pefrl")
    assert alone["modes"] == {"oscillator": 1, "saddle": 1}
    both = run_json("compare", "--modes", modes, "--beta", "4", "--beta", "1",
                    "--methods", "verlet")
    assert both["modes"] == {"oscillator": 3, "saddle": 1}
    # the largest beta (4, from the command line) limits verlet: h < 2/4
    assert both["methods"][0]["h_max"] == pytest.approx(0.5, rel=1e-9)
    every = run_json("compare", "--modes", modes, "--all")
    assert len(every["methods"]) > 10


@pytest.mark.parametrize("command", [["check", "--step", "0.1"], ["advise"]])
def test_modes_file_with_betas_and_saddle_p(run_json, tmp_path, command):
    modes = _modes_csv(tmp_path, "2,oscillator\n0.5,saddle-p\n")
    data = run_json(*command, "--method", "verlet", "--modes", modes, "--beta", "5")
    limits = data["models"] if "models" in data else None
    if limits is not None:
        assert limits["oscillator"]["count"] == 2 and "saddle-p" in limits
    else:
        assert data["checks"][0]["modes"] == 3


ZMAX_COMMANDS = [
    ["check", "--method", "verlet", "--beta", "1", "--step", "0.1"],
    ["check", "examples/scene.yaml"],
    ["advise", "--method", "verlet", "--beta", "1"],
    ["advise", "examples/scene.yaml"],
    ["compare", "--beta", "1", "--methods", "verlet"],
    ["region", "verlet"],
    ["plot", "verlet", "-o", "never-written.png"],
]


@pytest.mark.parametrize("value", ["0", "-1", "inf", "nan", "-0"])
@pytest.mark.parametrize("command", ZMAX_COMMANDS)
def test_zmax_must_be_positive_and_finite_everywhere(run, command, value):
    code, out, err = run(*command, "--zmax", value)
    assert code == 2 and out == ""
    assert "zmax must be a positive finite number" in _one_error_line(err)


@pytest.mark.parametrize("value", ["0", "-0.5", "1.5", "inf", "nan"])
@pytest.mark.parametrize("command", [c for c in ZMAX_COMMANDS if c[0] in ("check", "advise",
                                                                         "compare")])
def test_margin_must_be_in_0_1_everywhere(run, command, value):
    code, out, err = run(*command, "--margin", value)
    assert code == 2 and out == ""
    assert "margin must be in (0, 1]" in _one_error_line(err)


def test_error_range_is_checked(run):
    code, _, err = run("error", "verlet", "--zmin", "0", "--zmax", "0")
    assert code == 2 and "need 0 < zmin < zmax" in _one_error_line(err)


def test_compare_and_advise_with_tolerance_use_zmax(run_json):
    far = run_json("advise", "--method", "midpoint", "--beta", "1", "--tol-phase", "1",
                   "--zmax", "50")
    near = run_json("advise", "--method", "midpoint", "--beta", "1", "--tol-phase", "1")
    assert far["horizon"] == pytest.approx(50) and near["horizon"] == pytest.approx(10)


def test_error_range_points_are_bounded(run):
    code, _, err = run("error", "verlet", "--zmin", "1", "--zmax", "2", "--n", "100000000")
    assert code == 2 and "at most 100000 points" in _one_error_line(err)


@pytest.mark.filterwarnings("error")
def test_plot_far_out_has_no_warnings(run, tmp_path, monkeypatch):
    pytest.importorskip("matplotlib")
    monkeypatch.chdir(tmp_path)
    code, out, err = run("plot", "verlet", "--zmax", "1e308", "--phase", "-o", "far.svg")
    assert code == 0 and err == "" and (tmp_path / "far.svg").is_file()


def test_validate_keeps_its_exit_code_when_the_reader_stops_early(tmp_path):
    """'validate good.yaml bad.yaml | head -1' must not pass because the pipe closed."""
    import subprocess
    import sys

    bad = tmp_path / "bad.yaml"
    bad.write_text("name: m\nkind: splitting\norder: two\nsource: x\ndrift: [1]\nkick: [1]\n")
    args = [sys.executable, "-m", "stepsafe", "validate", "methods/verlet.yaml", str(bad)]
    proc = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 2
    assert "$.order: must be a whole number" in _one_error_line(err)
    done = _stepsafe("validate", "methods/verlet.yaml", str(bad))
    assert done.returncode == 2 and done.stdout.startswith("ok: methods/verlet.yaml")


@pytest.mark.parametrize("text", ["\\[", "\\[1]", ":smile:", ":warning: [b]x[/b] :cross_mark:",
                                  "\\\\[red]", "a\\"])
def test_no_rich_processing_of_file_text(run, tmp_path, text):
    """Backslash escapes and :emoji: codes are rich markup too: shown as typed."""
    code, out, _ = run("show", _titled(tmp_path, text, text))
    assert code == 0 and out.splitlines()[0] == f"m — {text}"
    assert any(line.split("│")[2].strip() == text for line in out.splitlines()
               if "│ source" in line)


def test_validate_names_a_scene_file(run):
    code, _, err = run("validate", str(ROOT / "examples" / "scene.yaml"))
    assert code == 2 and "this is a scene file" in err and "stepsafe check" in err


def test_methods_lists_aliases(run_json):
    rows = {r["name"]: r for r in run_json("methods", "--json")}
    assert "blanes-casas-sanz-serna2" in rows["bcss2"]["aliases"]


def test_piped_tables_are_never_cut(run):
    """Through a pipe (CliRunner is one) every number is printed whole: no ellipsis."""
    code, out, _ = run("compare", "--all", "--beta", "1", "--tol-phase", "1e-6")
    assert code == 0 and "…" not in out


def test_shell_completion_offers_method_names():
    import os
    import subprocess
    import sys

    env = {**os.environ, "_STEPSAFE_COMPLETE": "bash_complete",
           "COMP_WORDS": "stepsafe check --method pef", "COMP_CWORD": "3"}
    out = subprocess.run([sys.executable, "-c", "from stepsafe.cli import main; main()"],
                         env=env, capture_output=True, text=True)
    assert out.returncode == 0 and "plain,pefrl" in out.stdout.split()

"""Coefficient expressions, the strict YAML reader and broken method files."""

from __future__ import annotations

import math
import time

import pytest

from stepsafe.expressions import ExpressionError, mpmath_backend, value_of

GOOD = {
    "1/2": 0.5, "sqrt(3)/6": math.sqrt(3) / 6, "1/(2-2**(1/3))": 1 / (2 - 2 ** (1 / 3)),
    "cbrt(2)": 2 ** (1 / 3), "-pi/4": -math.pi / 4, "1e-3": 1e-3, "2.5E+2": 250.0,
    "  7 ": 7.0, ".5": 0.5, "(1+2)*3": 9.0, "-2**2": -4.0,
}


@pytest.mark.parametrize("text, value", GOOD.items())
def test_expressions_evaluate(text, value):
    assert value_of(text) == pytest.approx(value, rel=1e-15)


def test_mpmath_backend_reads_decimals_exactly():
    import mpmath

    with mpmath.workdps(50):
        x = value_of("0.1786178958448091", backend=mpmath_backend())
        assert x == mpmath.mpf("0.1786178958448091")
        y = value_of("1/(2-cbrt(2))", backend=mpmath_backend())
        assert abs(y - 1 / (2 - mpmath.cbrt(2))) < mpmath.mpf(10) ** -48


@pytest.mark.parametrize("text", [
    "__import__('os')", "os.system('true')", "(1).real", "lambda: 1", "[1][0]", "'1'",
    "1j", "True", "0x10", "1_000", "exp(1)", "sqrt(1, 2)", "sqrt(x=1)", "9**9**9**9",
    "1e400", "1/0", "sqrt(-1)", "(-8)**(1/3)", "undefined_name", "1 if 1 else 2", "",
    "(" * 300 + "1" + ")" * 300, "1+" * 600 + "1", "a.b", "[x for x in y]", "{1: 2}",
])
def test_hostile_expressions_are_refused_quickly(text):
    start = time.perf_counter()
    with pytest.raises(ExpressionError):
        value_of(text)
    assert time.perf_counter() - start < 1.0


def _write(tmp_path, text: str | bytes, name: str = "m.yaml"):
    path = tmp_path / name
    (path.write_bytes if isinstance(text, bytes) else path.write_text)(text)
    return str(path)


VALID = """\
name: my-verlet
kind: splitting
order: 2
source: test
drift: [0, 1]
kick: ["1/2", 0.5]
"""

BROKEN = {
    "missing key": (VALID.replace("order: 2\n", ""), "$.order: missing"),
    "unknown key": (VALID + "colour: red\n", "$.colour: unknown key"),
    "wrong kind": (VALID.replace("splitting", "magic"), "$.kind: must be one of"),
    "wrong shape": (VALID.replace("drift: [0, 1]", "drift: [0, 1, 2, 3]"), "$.drift: has 4"),
    "non-numeric": (VALID.replace('"1/2"', "half"), "$.kick[0]: unknown name 'half'"),
    "function call": (VALID.replace('"1/2"', '"exp(1)"'), "$.kick[0]: only sqrt"),
    "import": (VALID.replace('"1/2"', "\"__import__('os')\""), "$.kick[0]"),
    "nan": (VALID.replace('"1/2"', ".nan"), "$.kick[0]"),
    "inf": (VALID.replace('"1/2"', "1e400"), "$.kick[0]: the value is not a finite"),
    "list not matrix": (VALID.replace("kind: splitting", "kind: rk").replace(
        "drift: [0, 1]\nkick: [\"1/2\", 0.5]\n", "A: [1, 2]\nb: [1, 2]\n"),
        "$.A[0]: must be a row"),
    "not a mapping": ("- 1\n- 2\n", "must be a mapping"),
    "empty": ("", "empty file"),
    "duplicate key": (VALID + "order: 3\n", "duplicate key 'order'"),
    "bad order": (VALID.replace("order: 2", "order: two"), "$.order: must be a whole number"),
    "bad yaml": ("name: [unclosed\n", "line"),
    "alias bomb": ('a: &a ["x","x","x","x","x","x","x","x","x"]\n'
                   'b: &b [*a,*a,*a,*a,*a,*a,*a,*a,*a]\n'
                   'c: &c [*b,*b,*b,*b,*b,*b,*b,*b,*b]\nd: [*c,*c,*c,*c,*c,*c,*c,*c,*c]\n',
                   "anchors are not allowed"),
    "huge list": (VALID.replace("drift: [0, 1]", "drift: [" + ", ".join(["0"] * 10**6) + "]"),
                  "bytes"),
    "deep nesting": ("a: " + "[" * 100 + "]" * 100 + "\n", "nested deeper"),
}


@pytest.mark.parametrize("case", BROKEN, ids=list(BROKEN))
def test_validate_broken_files(run, tmp_path, case):
    text, message = BROKEN[case]
    path = _write(tmp_path, text)
    start = time.perf_counter()
    code, out, err = run("validate", path)
    assert time.perf_counter() - start < 1.0
    assert code == 2, out + err
    assert message in err and path in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_validate_binary_and_non_utf8_and_directory(run, tmp_path):
    for content, message in ((b"\x00\x01\x02", "binary"), (b"name: \xff\xfe\n", "not UTF-8")):
        code, _, err = run("validate", _write(tmp_path, content))
        assert code == 2 and message in err
    code, _, err = run("validate", str(tmp_path) + "/")
    assert code == 2 and "directory" in err


def test_validate_good_file_and_symmetric_expansion(run, tmp_path):
    from stepsafe.library import resolve

    path = _write(tmp_path, VALID)
    code, out, _ = run("validate", path)
    assert code == 0 and "ok:" in out
    half = VALID.replace("drift: [0, 1]", "symmetric: true\ndrift: [0, 1]").replace(
        'kick: ["1/2", 0.5]', 'kick: ["1/2"]')
    m, _ = resolve(_write(tmp_path, half, "half.yaml"))
    assert m.drift.tolist() == [0.0, 1.0, 0.0] and m.kick.tolist() == [0.5, 0.5]


def test_validate_warns_on_non_symplectic(run, tmp_path):
    rk = ("name: explicit-euler\nkind: rk\norder: 1\nsource: test\nA: [[0]]\nb: [1]\n")
    code, out, _ = run("validate", _write(tmp_path, rk))
    assert code == 0 and "warning" in out and "not symplectic" in out


def test_every_shipped_file_validates(run):
    from stepsafe.library import builtin_dir

    files = sorted(str(p) for p in builtin_dir().glob("*.yaml"))
    code, out, err = run("validate", *files)
    assert code == 0, err
    assert out.count("ok:") == len(files)


# --- Hostile files, run in a subprocess: a FIFO read in-process would hang the test run. ---

def _cli(*args: str, cwd=None):
    """Run ``python -m stepsafe`` (the timeout only detects a hang; it is not a benchmark)."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "stepsafe", *args], capture_output=True,
                          text=True, cwd=cwd, timeout=120)
    return proc.returncode, proc.stdout, proc.stderr


def _assert_input_error(code: int, out: str, err: str, *needles: str) -> None:
    """The bad-input contract: exit 2, one line 'stepsafe: error: ...', no traceback."""
    assert code == 2, (code, out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("stepsafe: error: "), err
    assert "Traceback" not in out + err and "Warning" not in err, err
    for needle in needles:
        assert needle in err, (needle, err)


def _fifo(tmp_path, name: str) -> str:
    import os

    if not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs on this platform")
    path = tmp_path / name
    os.mkfifo(path)
    return str(path)


def test_fifos_are_refused_not_read(tmp_path):
    """A FIFO blocks open() until a writer appears: each must be refused before opening."""
    scene = _fifo(tmp_path, "scene.yaml")
    method = _fifo(tmp_path, "method.yaml")
    modes_csv = _fifo(tmp_path, "modes.csv")
    modes_yaml = _fifo(tmp_path, "modes.yaml")
    cases = [("check", scene), ("validate", method), ("show", method),
             ("check", "--method", method, "--h", "1", "--beta", "1"),
             ("check", "--method", "verlet", "--h", "1", "--modes", modes_csv),
             ("advise", "--method", "verlet", "--modes", modes_yaml)]
    for args in cases:
        fifo = args[-1] if args[-1].startswith(str(tmp_path)) else args[2]
        _assert_input_error(*_cli(*args, cwd=tmp_path), fifo, "not a regular file (a FIFO)")


def test_devices_and_sockets_are_refused(tmp_path):
    import os
    import socket

    if os.path.exists("/dev/null"):
        _assert_input_error(*_cli("validate", "/dev/null"), "/dev/null",
                            "not a regular file (a character device)")
    path = tmp_path / "s.yaml"
    if not hasattr(socket, "AF_UNIX") or len(str(path)) > 100:
        pytest.skip("no short unix socket path here")
    with socket.socket(socket.AF_UNIX) as sock:
        sock.bind(str(path))
        _assert_input_error(*_cli("validate", str(path)), str(path),
                            "not a regular file (a socket)")

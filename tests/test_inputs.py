"""Coefficient expressions, the strict YAML reader and broken method files; hostile input
files (FIFOs and devices, matrix files, modes CSVs), system-matrix errors under the right
key, scene-relative method paths and the composition step budget."""

from __future__ import annotations

import json
import math

import pytest

from stepsafe.files.expressions import ExpressionError, mpmath_backend, value_of

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
def test_hostile_expressions_are_refused(text):
    with pytest.raises(ExpressionError):  # (9**9**9**9 and 1+1+...: refused, not evaluated)
        value_of(text)


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
    "merge key": (VALID + "!!merge <<: {kind: rk}\n", "merge keys are not allowed"),
}


@pytest.mark.parametrize("case", BROKEN, ids=list(BROKEN))
def test_validate_broken_files(run, tmp_path, case):
    text, message = BROKEN[case]
    path = _write(tmp_path, text)
    code, out, err = run("validate", path)
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
    from stepsafe.methods.library import resolve

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
    from stepsafe.methods.library import builtin_dir

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


# --- Matrix files: refused from their headers, within the documented budgets. ---

def _npy_bytes(array=None, *, shape=None, dtype=None) -> bytes:
    """An .npy image: a real array, or only a header declaring ``shape`` and ``dtype``."""
    import io

    import numpy as np
    from numpy.lib import format as npf

    buf = io.BytesIO()
    if array is not None:
        np.save(buf, array)
    else:
        npf.write_array_header_1_0(buf, {"descr": npf.dtype_to_descr(np.dtype(dtype)),
                                         "fortran_order": False, "shape": shape})
    return buf.getvalue()


def _system_scene(tmp_path, system: str) -> str:
    path = tmp_path / "scene.yaml"
    path.write_text(f"method: verlet\nh: 0.5\nsystem: {system}\n")
    return str(path)


def test_npz_bomb_refused_from_the_declared_unpacked_size(run, tmp_path):
    """A member whose zip directory declares 10 GB is refused without inflating anything."""
    import zipfile

    from stepsafe.systems.matrixfile import MAX_FILE_BYTES

    with zipfile.ZipFile(tmp_path / "K.npz", "w", allowZip64=True) as archive:
        archive.writestr("arr_0.npy", _npy_bytes(shape=(50_000, 50_000), dtype="<f8"))
        archive.filelist[0].file_size = 20_000_000_000  # what a 23000^2 zeros bomb declares
    code, out, err = run("check", _system_scene(tmp_path, "{stiffness: K.npz}"))
    assert code == 2, out + err
    assert f"K.npz: the .npz file unpacks to 20000000000 bytes, more than the " \
           f"{MAX_FILE_BYTES} allowed" in err


def test_npz_with_many_members_refused_from_the_end_record(run, tmp_path):
    """zipfile.ZipFile builds one object per member: a directory filling a 512 MiB file
    would take gigabytes, so the member count is read from the end record first."""
    import zipfile

    from stepsafe.systems.matrixfile import MAX_NPZ_MEMBERS

    with zipfile.ZipFile(tmp_path / "K.npz", "w") as archive:
        for i in range(1000):
            archive.writestr(f"a{i}.npy", b"")
    code, _, err = run("check", _system_scene(tmp_path, "{stiffness: K.npz}"))
    assert code == 2 and "K.npz: the .npz file holds 1000 members" in err
    assert f"more than the {MAX_NPZ_MEMBERS} allowed" in err


def test_npz_dense_header_over_budget(run, tmp_path):
    import zipfile

    from stepsafe.systems.matrixfile import MAX_DENSE_BYTES

    with zipfile.ZipFile(tmp_path / "K.npz", "w") as archive:
        archive.writestr("arr_0.npy", _npy_bytes(shape=(10_000, 10_000), dtype="<f4"))
    code, _, err = run("check", _system_scene(tmp_path, "{stiffness: K.npz}"))
    assert code == 2 and "$.system.stiffness: K.npz: a dense 10000 x 10000 matrix needs " \
                          f"800000000 bytes as float64, more than the {MAX_DENSE_BYTES}" in err


def _sparse_npz(path, members: dict) -> None:
    import zipfile

    with zipfile.ZipFile(path, "w") as archive:
        for name, image in members.items():
            archive.writestr(f"{name}.npy", image)


def test_sparse_npz_budgets_from_headers(run, tmp_path):
    import numpy as np

    from stepsafe.systems.matrixfile import MAX_SPARSE_DIM, MAX_SPARSE_NNZ

    nnz = MAX_SPARSE_NNZ + 1
    _sparse_npz(tmp_path / "K.npz", {
        "format": _npy_bytes(np.array(b"coo")), "shape": _npy_bytes(np.array([10, 10])),
        "row": _npy_bytes(shape=(nnz,), dtype="<i4"), "col": _npy_bytes(shape=(nnz,),
                                                                        dtype="<i4"),
        "data": _npy_bytes(shape=(nnz,), dtype="<f8")})
    code, _, err = run("check", _system_scene(tmp_path, "{stiffness: K.npz}"))
    assert code == 2 and f"{nnz} stored entries, more than the {MAX_SPARSE_NNZ} allowed" in err
    n = MAX_SPARSE_DIM + 1
    _sparse_npz(tmp_path / "K.npz", {
        "format": _npy_bytes(np.array(b"csr")), "shape": _npy_bytes(np.array([n, n])),
        "indptr": _npy_bytes(shape=(n + 1,), dtype="<i8"),
        "indices": _npy_bytes(np.zeros(1, dtype="<i4")), "data": _npy_bytes(np.ones(1))})
    code, _, err = run("check", _system_scene(tmp_path, "{stiffness: K.npz}"))
    assert code == 2 and f"a sparse {n} x {n} matrix is larger than the {MAX_SPARSE_DIM} " \
                          "rows allowed" in err


def test_sparse_npz_with_indices_out_of_range(run, tmp_path):
    import numpy as np

    _sparse_npz(tmp_path / "K.npz", {
        "format": _npy_bytes(np.array(b"csr")), "shape": _npy_bytes(np.array([2, 2])),
        "indptr": _npy_bytes(np.array([0, 1, 2])), "indices": _npy_bytes(np.array([0, 7])),
        "data": _npy_bytes(np.array([1.0, 2.0]))})
    code, _, err = run("check", _system_scene(tmp_path, "{stiffness: K.npz}"))
    assert code == 2 and "$.system.stiffness: K.npz: cannot read" in err, err


def test_mtx_sparse_dimension_budget(run, tmp_path):
    from stepsafe.systems.matrixfile import MAX_SPARSE_DIM

    n = MAX_SPARSE_DIM + 1
    (tmp_path / "K.mtx").write_text(f"%%MatrixMarket matrix coordinate real symmetric\n"
                                    f"{n} {n} 1\n1 1 1.0\n")
    code, _, err = run("check", _system_scene(tmp_path, "{stiffness: K.mtx}"))
    assert code == 2 and f"larger than the {MAX_SPARSE_DIM} rows allowed" in err


def test_special_files_as_matrices(tmp_path):
    (tmp_path / "D.npy").mkdir()
    _fifo(tmp_path, "F.npy")
    for name, message in (("D.npy", "is a directory"), ("F.npy", "not a regular file (a FIFO)"),
                          ("K.txt", "use a .npy, .npz or .mtx file")):
        scene = _system_scene(tmp_path, f"{{stiffness: {name}}}")
        _assert_input_error(*_cli("check", scene), f"{scene}::$.system.stiffness: {name}: "
                                                   f"{message}")


def test_real_matrices_of_any_width_are_read_as_float64(run_json, tmp_path):
    import numpy as np
    import scipy.io
    import scipy.sparse as sp

    K = np.array([[4, -1], [-1, 3]])
    expected = np.sort(np.sqrt(np.linalg.eigvalsh(K.astype(float))))
    files = {"i8.npy": K.astype(np.int8), "f2.npy": K.astype(np.float16),
             "f4.npy": K.astype(np.float32), "dense.npz": K.astype(np.int64)}
    for name, array in files.items():
        (np.savez if name.endswith(".npz") else np.save)(tmp_path / name, array)
    sp.save_npz(tmp_path / "coo.npz", sp.coo_matrix(K.astype(float)))
    scipy.io.mmwrite(str(tmp_path / "int.mtx"), sp.coo_matrix(K))
    for name in [*files, "coo.npz", "int.mtx"]:
        data = run_json("advise", _system_scene(tmp_path, f"{{stiffness: {name}}}"))
        betas = sorted(item["beta"] for item in data["system"]["items"])
        assert betas == pytest.approx(expected, rel=1e-12), name


REFUSED_KINDS = {"c": "complex values are not allowed", "b": "boolean values are not allowed",
                 "U": "text values are not allowed", "S": "text values are not allowed",
                 "O": "Python objects are not allowed", "M": "date/time values are not allowed",
                 "m": "date/time values are not allowed",
                 "V": "structured (record) values are not allowed"}
DTYPES = ["<f8", "<f4", "<f2", "<i1", "<u2", "<i8", "<u8", "|b1", "<c16", "<c8", "<U3",
          "|S2", "|O", "<M8[s]", "<m8[s]", [("a", "<f8"), ("b", "<i4")], [("x", "<f8")]]


def _hostile_array(data):
    import numpy as np
    from hypothesis import strategies as st

    dtype = np.dtype(data.draw(st.sampled_from(DTYPES), label="dtype"))
    shape = tuple(data.draw(st.lists(st.integers(0, 4), max_size=3), label="shape"))
    values = np.arange(int(np.prod(shape, dtype=np.int64)), dtype=np.int64).reshape(shape)
    if dtype.kind == "c":
        tiny = data.draw(st.sampled_from([1e-300, 0.0, 1.0]), label="imaginary part")
        return values.astype(dtype) + tiny * 1j
    if dtype.kind == "O":
        return values.astype(object)
    if dtype.fields is not None:
        return np.zeros(shape, dtype=dtype)
    return values.astype(dtype)


def _expected_refusal(array) -> str | None:
    kind = "V" if array.dtype.fields is not None else array.dtype.kind
    if kind in REFUSED_KINDS:
        return REFUSED_KINDS[kind]
    if array.ndim == 0:
        return "holds a single number (a 0-d array), not a matrix"
    if array.ndim != 2:
        return "not a 2-D matrix"
    if array.shape[0] != array.shape[1] or array.size == 0:
        return "the matrix must be square and non-empty"
    return None


def test_hostile_npy_and_npz_dtypes_and_shapes(tmp_path):
    """Any dtype and shape in .npy or dense .npz: a float64 square matrix with the same values
    for real dtypes, otherwise a StepsafeError naming the file and the reason; never a
    truncation of complex values, never another exception."""
    import numpy as np
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    from stepsafe.exceptions import StepsafeError
    from stepsafe.systems.matrixfile import read_matrix

    @settings(max_examples=120, deadline=None, suppress_health_check=[
        HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
    @given(st.data(), st.sampled_from([".npy", ".npz"]))
    def check(data, suffix):
        array = _hostile_array(data)
        path = tmp_path / f"K{suffix}"
        if suffix == ".npy":
            np.save(path, array, allow_pickle=True)
        else:
            np.savez(path, array)
        refusal = _expected_refusal(array)
        try:
            got = read_matrix(path, path.name, sparse_ok=data.draw(st.booleans()))
        except StepsafeError as exc:
            assert refusal is not None and refusal in str(exc), (array.dtype, array.shape, exc)
            assert str(exc).startswith(f"{path.name}: ")
            return
        assert refusal is None, (array.dtype, array.shape)
        assert got.dtype == np.float64 and np.array_equal(got, array.astype(np.float64))

    check()


@pytest.mark.parametrize("field, symmetry, message", [
    ("complex", "general", "complex values are not allowed"),
    ("complex", "hermitian", "complex values are not allowed"),
    ("pattern", "general", "a pattern matrix (positions without values) is not allowed"),
    ("real", "general", None), ("integer", "symmetric", None), ("double", "general", None),
])
def test_mtx_fields(run, tmp_path, field, symmetry, message):
    values = {"complex": " 4.0 0.5", "pattern": ""}.get(field, " 4")
    (tmp_path / "K.mtx").write_text(f"%%MatrixMarket matrix coordinate {field} {symmetry}\n"
                                    f"2 2 2\n1 1{values}\n2 2{values}\n")
    for key in ("stiffness", "mass"):
        system = "{stiffness: K.mtx}" if key == "stiffness" else \
            "{stiffness: [[1, 0], [0, 1]], mass: K.mtx}"
        code, out, err = run("check", _system_scene(tmp_path, system))
        if message is None:
            assert code in (0, 1), err
        else:
            assert code == 2 and f"$.system.{key}: K.mtx: {message}" in err, err


# --- System matrices: the right key, and definiteness independent of scale. ---

def test_positive_definite_whatever_the_scale():
    import numpy as np
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from stepsafe.systems.linear import is_positive_definite

    @settings(max_examples=80, deadline=None)
    @given(st.integers(1, 6), st.integers(0, 2**32 - 1), st.booleans())
    def check(n, seed, definite):
        rng = np.random.default_rng(seed)
        B = rng.normal(size=(n, n))
        A = B @ B.T + 0.5 * np.eye(n)
        if not definite:
            v = rng.normal(size=n)
            A = A - (2.0 * np.linalg.eigvalsh(A).max() + 1.0) * np.outer(v, v) / (v @ v)
        d = 10.0 ** rng.uniform(-150, 150, size=n)
        assert is_positive_definite(d[:, None] * A * d[None, :]) == definite

    check()
    assert is_positive_definite(np.diag([1e-300, 1e300]))
    assert not is_positive_definite(np.array([[1e-300, 1e300], [1e300, 1e300]]))
    assert not is_positive_definite(np.array([[0.0, 0.0], [0.0, 1.0]]))


def test_badly_scaled_mass_is_analysed(run_json, tmp_path):
    """M = diag(1e-300, 1e300) is positive definite; with K = diag(4e-300, 1e300) the
    frequencies are exactly 2 and 1."""
    data = run_json("advise", _system_scene(
        tmp_path, "{stiffness: [[4e-300, 0], [0, 1e300]], mass: [[1e-300, 0], [0, 1e300]]}"))
    assert sorted(item["beta"] for item in data["system"]["items"]) == pytest.approx([1, 2])


def test_large_sparse_system_mass_errors_name_the_mass(run, tmp_path):
    import scipy.sparse as sp

    n = 2500
    K = sp.diags([2.0] * n) - sp.eye(n, k=1) - sp.eye(n, k=-1)
    sp.save_npz(tmp_path / "K.npz", K.tocsr())
    for M, message in ((sp.diags([1.0] * (n - 1) + [-1.0]), "mass must be positive definite"),
                       (K, "a large sparse system needs a diagonal (lumped) mass"),
                       (sp.eye(n + 1), f"mass is {n + 1}x{n + 1} but stiffness is {n}x{n}")):
        sp.save_npz(tmp_path / "M.npz", M.tocsr())
        code, _, err = run("check", _system_scene(tmp_path, "{stiffness: K.npz, mass: M.npz}"))
        assert code == 2 and f"$.system.mass: {message}" in err, err


# --- Modes CSV files: numpy speed, exact messages naming the line, a row budget. ---

def _modes_csv(tmp_path, content: str | bytes) -> str:
    path = tmp_path / "modes.csv"
    (path.write_bytes if isinstance(content, bytes) else path.write_text)(content)
    return str(path)


@pytest.mark.parametrize("content, message", [
    ("beta,model\n1_0,oscillator\n", "$.line 2.beta: is not a number: '1_0'"),
    ("beta,model\n\"3\",oscillator\n", "$.line 2.beta: is not a number: '\"3\"'"),
    ("beta,model\n0x10,oscillator\n", "$.line 2.beta: is not a number: '0x10'"),
    ("beta,model\n\u0663,oscillator\n", "$.line 2.beta: is not a number: '\u0663'"),
    ("beta,model\n,oscillator\n", "$.line 2.beta: is not a number: ''"),
    ("beta,model\nnan,oscillator\n", "$.line 2.beta: must be a finite number >= 0, got nan"),
    ("beta,model\n1e400,oscillator\n", "$.line 2.beta: must be a finite number >= 0, got 1e400"),
    ("beta\n1\n# note\n\n-2.5\n", "$.line 5.beta: must be a finite number >= 0, got -2.5"),
    ("beta,model\n3,Oscillator\n", "$.line 2.model: must be one of oscillator, saddle, "
                                   "inverted, saddle-p, got 'Oscillator'"),
    ("beta,model\n3,oscillator,x\n", "$.line 2: has 3 columns, the header 2"),
    ("beta,model\n3\n", "$.line 2: has 1 columns, the header 2"),
    ("3,oscillator\n", "the CSV header must name one frequency column"),
    ("beta,beta\n3,4\n", "the CSV header must name one frequency column"),
    ("beta,model\n", "no rows after the header"),
    ("# only a comment\n\n", "empty CSV file"),
    (b"beta\n\x003\n", "binary file (contains NUL bytes)"),
    (b"beta,label\n3,\xff\n", "not UTF-8 text (byte 13)"),
])
def test_bad_modes_csv(run, tmp_path, content, message):
    path = _modes_csv(tmp_path, content)
    code, out, err = run("check", "--method", "verlet", "--h", "0.1", "--modes", path)
    assert code == 2 and f"{path}" in err and message in err, err
    assert len(err.strip().splitlines()) == 1
    assert "np.str_" not in err and "np.float64" not in err and "np.bytes_" not in err


@pytest.mark.parametrize("content", [
    "beta,model\n3,oscillator\n1,inverted\n",
    "beta,model\r\n3,oscillator\r\n1,inverted\r\n",  # Windows line ends
    "beta,model\r3,oscillator\r1,inverted",  # old Mac line ends, no final newline
    "\ufeffbeta,model\n3,oscillator\n1,inverted\n",  # byte order mark (spreadsheets)
    " beta , model \n 3 , oscillator \n\t1\t,\tinverted\n",
    "# frequencies\n\nmodel,label,beta\noscillator,a,3\n\n# barrier\ninverted,b,1 # top\n",
])
def test_modes_csv_variants(tmp_path, content):
    from stepsafe.systems.scene import load_modes

    got = load_modes(_modes_csv(tmp_path, content))
    assert {k: v.tolist() for k, v in got.betas.items()} == {"oscillator": [3.0],
                                                             "inverted": [1.0]}
    if "label" in content:
        assert got.labels == {"oscillator": ("a",), "inverted": ("b",)}


def test_modes_csv_labels_follow_their_rows(tmp_path):
    """Labels stay with their rows across models, blank lines and comments; an empty label
    field is no label, and a model whose rows have none has no labels."""
    from stepsafe.systems.scene import load_modes

    text = ("beta,label,model\n1,slow bend,oscillator\n# comment\n2,,oscillator\n\n"
            "3,the top,inverted\n4,fast stretch,oscillator\n5,,saddle\n")
    got = load_modes(_modes_csv(tmp_path, text))
    assert got.betas["oscillator"].tolist() == [1.0, 2.0, 4.0]
    assert got.labels == {"oscillator": ("slow bend", None, "fast stretch"),
                          "inverted": ("the top",)}


def test_modes_file_labels_reach_the_verdict(run, tmp_path):
    """A labelled mode from --modes (CSV or YAML) is named in check's failures, after
    the --beta frequencies given on the command line."""
    csv_file = _modes_csv(tmp_path, "beta,label\n1,slow bend\n40,fast stretch\n")
    yaml_file = tmp_path / "modes.yaml"
    yaml_file.write_text("- {beta: 1, label: slow bend}\n- {beta: 40, label: fast stretch}\n")
    for path in (csv_file, yaml_file):
        code, out, err = run("check", "--method", "verlet", "--step", "0.1", "--beta", "15",
                             "--modes", str(path), "--json")
        assert code == 1, err
        failures = json.loads(out)["checks"][0]["failures"]
        assert [(f["beta"], f.get("label")) for f in failures] == [(40.0, "fast stretch")]


def test_modes_csv_row_budget_checked_before_parsing(run, tmp_path):
    from stepsafe.systems.scene import MAX_CSV_ROWS

    path = _modes_csv(tmp_path, b"beta\n" + b"1\n" * (MAX_CSV_ROWS + 1))
    code, _, err = run("check", "--method", "verlet", "--h", "0.1", "--modes", path)
    assert code == 2 and f"has {MAX_CSV_ROWS + 2} lines, more than the {MAX_CSV_ROWS} rows " \
                          "(and a header) allowed" in err, err


def _reference_csv(lines: list[str]):
    """The documented CSV semantics, line by line: (grouped betas) or (line, field)."""
    import re

    from stepsafe.core.models import MODELS

    number = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?", re.ASCII)
    grouped: dict[str, list[float]] = {}
    for n, line in enumerate(lines[1:], 2):
        text = line.split("#", 1)[0]
        if not text.strip():
            continue
        fields = text.split(",")
        if len(fields) != 2:
            return (n, "")
        beta, model = fields[0].strip(), fields[1].strip()
        if not number.fullmatch(beta) or not 0 <= float(beta) < math.inf:
            return (n, ".beta")
        if model not in MODELS:
            return (n, ".model")
        grouped.setdefault(model, []).append(float(beta))
    return grouped


def test_modes_csv_fast_and_exact_readers_agree(tmp_path, monkeypatch):
    """np.loadtxt reads the file; on any doubt the exact reader decides, bisecting the file.
    With tiny bisection blocks, random files of good and hostile lines must give what the
    documented semantics give: the same frequencies, or the first bad line."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    import stepsafe.systems.scene as scene
    from stepsafe.exceptions import StepsafeError

    monkeypatch.setattr(scene, "_CSV_ROW_BY_ROW", 2)
    good = ["3,oscillator", "0.5,inverted", " 1e-3 , saddle ", "2.,saddle-p", ".25,oscillator",
            "7,oscillator # comment", "", "# comment", "   ",
            "4," + " " * 40 + "inverted" + " " * 40]  # wider than the fast reader's field
    bad = ["1_0,oscillator", "-1,oscillator", "nan,saddle", "inf,saddle", "1e400,saddle",
           "x,oscillator", "3,wobble", "3,oscillatorX", "3", "3,saddle,1", "\"3\",saddle",
           "\u0663,saddle", "3,Oscillator", "0x1p3,saddle", "1e,saddle", "- 3,saddle"]
    line = st.one_of(st.sampled_from(good), st.sampled_from(good), st.sampled_from(bad))

    @settings(max_examples=150, deadline=None,
              suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(st.lists(line, min_size=0, max_size=40))
    def check(body):
        lines = ["beta,model", *body]
        expected = _reference_csv(lines)
        path = _modes_csv(tmp_path, "\n".join(lines) + "\n")
        try:
            got = scene.load_modes(path)
        except StepsafeError as exc:
            if isinstance(expected, tuple):
                assert f"::$.line {expected[0]}{expected[1]}:" in str(exc), (exc, expected)
            else:
                assert not any(expected.values()) and "no rows" in str(exc), exc
            return
        assert isinstance(expected, dict), (expected, got)
        assert {k: v.tolist() for k, v in got.betas.items()} == expected

    check()


# --- Scenes: a relative method path is next to the scene file. ---

def test_scene_method_path_is_next_to_the_scene(run, tmp_path, monkeypatch):
    """From any working directory, 'method: m.yaml' is the file next to the scene, even when
    the working directory holds another m.yaml."""
    sub = tmp_path / "sub"
    sub.mkdir()
    (sub / "m.yaml").write_text(VALID)  # a Verlet step: first boundary z = 2
    (tmp_path / "m.yaml").write_text(VALID.replace("drift: [0, 1]", 'drift: [0, "1/2"]')
                                     .replace('kick: ["1/2", 0.5]', 'kick: ["1/4", "1/4"]'))
    (sub / "c.yaml").write_text("name: c\nkind: composition\norder: 2\nsource: t\n"
                                "base: m.yaml\nweights: [0.5, 0.5]\n")
    monkeypatch.chdir(tmp_path)
    def h_max(*args):
        code, out, err = run("advise", *args, "--json")
        assert code == 0, err
        return json.loads(out)["h_max"]

    assert h_max("--method", "m.yaml", "--beta", "1") == pytest.approx(4.0)  # the cwd file
    for method, target in (("m.yaml", "m.yaml"), ("./m.yaml", "m.yaml"),
                           ("{name: m.yaml}", "m.yaml"), ("c.yaml", "c.yaml")):
        (sub / "scene.yaml").write_text(f"method: {method}\nmodes: [{{beta: 1}}]\n")
        assert h_max("sub/scene.yaml") == h_max("--method", str(sub / target), "--beta", "1")
    assert h_max("--method", str(sub / "m.yaml"), "--beta", "1") == pytest.approx(2.0)
    (sub / "scene.yaml").write_text("method: {name: c.yaml, base: m.yaml}\nh: 1\n"
                                    "modes: [{beta: 1}]\n")
    assert run("check", "sub/scene.yaml")[0] == 0
    (sub / "scene.yaml").write_text("method: missing.yaml\nh: 1\nmodes: [{beta: 1}]\n")
    code, _, err = run("check", "sub/scene.yaml")
    assert code == 2 and "missing.yaml: no such file" in err


# --- Nested compositions: the flattened step count is bounded before anything is built. ---

def test_nested_composition_budget_counts_without_flattening():
    from support import method

    from stepsafe.exceptions import MethodError
    from stepsafe.methods.tableaux import MAX_BASE_STEPS, Composition

    verlet = method("verlet")
    inner = Composition(verlet, [1 / 40] * 40)
    assert Composition(inner, [1 / 25] * 25).flattened().weights.size == MAX_BASE_STEPS
    with pytest.raises(MethodError, match=f"1200 steps of the base method .* more than the "
                                          f"{MAX_BASE_STEPS} allowed"):
        Composition(inner, [1 / 30] * 30)


def test_a_composition_over_a_long_splitting_is_bounded(run, tmp_path):
    """A composition's work is its steps times its base's drifts and kicks: 399 steps of
    a 799-operation splitting exceed the bound and are refused at once, exit 2, while the
    library's largest (105 operations) and 5 steps of that splitting (3995) are analysed."""
    from stepsafe.methods.tableaux import MAX_COMPOSED_OPERATIONS

    values = ", ".join(['"0.0025"'] * 200)
    (tmp_path / "long.yaml").write_text(
        f"name: long\nkind: splitting\norder: 1\nsource: test\nsymmetric: true\n"
        f"drift: [{values}]\nkick: [{values}]\n")
    for steps, code in ((5, 0), (6, 2)):
        weights = ", ".join([f'"1/{steps}"'] * steps)
        path = tmp_path / f"c{steps}.yaml"
        path.write_text(f"name: c{steps}\nkind: composition\norder: 1\nsource: test\n"
                        f"base: long.yaml\nweights: [{weights}]\n")
        got, _, err = run("check", "--method", str(path), "--beta", "1", "--step", "0.01")
        assert got in ((0, 1) if code == 0 else (2,)), err
        if code == 2:
            assert f"more than the {MAX_COMPOSED_OPERATIONS} analysed" in err


def test_nested_composition_files_are_refused_from_their_counts(tmp_path):
    """Four nested files of 100 weights would flatten to 10^8 steps (gigabytes): refused
    while the second level is built, naming the file and the budget."""
    from stepsafe.methods.tableaux import MAX_BASE_STEPS

    weights = ", ".join(["0.01"] * 100)
    base = "verlet"
    for level in range(1, 5):
        (tmp_path / f"nest{level}.yaml").write_text(
            f"name: nest{level}\nkind: composition\norder: 2\nsource: t\nbase: {base}\n"
            f"weights: [{weights}]\n")
        base = f"nest{level}.yaml"
    for command in (("region", "nest4.yaml"), ("validate", "nest4.yaml"),
                    ("check", "--method", "nest3.yaml", "--h", "1", "--beta", "1"),
                    ("region", "nest1.yaml", "--base", "nest1.yaml")):
        code, out, err = _cli(*command, cwd=tmp_path)
        _assert_input_error(code, out, err, f"10000 steps of the base method once the nested "
                                            f"compositions are multiplied out, more than the "
                                            f"{MAX_BASE_STEPS} allowed")
        if command[-1] != "nest1.yaml":
            assert "nest2.yaml: nest2: " in err


def test_cancelling_coefficient_expressions_are_evaluated_exactly(run, tmp_path):
    """A drift written as ((1e16 + 0.25) - 1e16) + 0.75 is exactly 1 (plain Verlet): float64
    evaluation would give 0.75 and a boundary at sqrt(16/3) instead of 2."""
    path = tmp_path / "cancel.yaml"
    path.write_text('name: cancel\nkind: splitting\norder: 2\nsource: "test"\n'
                    'drift: [0, "((1e16 + 0.25) - 1e16) + 0.75"]\nkick: [1/2, 1/2]\n')
    code, out, _ = run("check", "--method", str(path), "--step", "2.1", "--beta", "1")
    assert code == 1, out
    code, out, _ = run("region", str(path), "--model", "oscillator", "--json")
    assert code == 0
    import json

    assert json.loads(out)["models"]["oscillator"]["first_boundary"] == 2.0


def test_advise_names_the_limiting_mode_by_its_label(run, tmp_path):
    """The label of the mode that limits h reaches advise's JSON and text, literally."""
    scene = tmp_path / "labelled.yaml"
    scene.write_text("method: verlet\nmodes:\n  - {beta: 1, label: slow bend}\n"
                     "  - {beta: 7, label: \"fast [red]stretch\"}\n"
                     "  - {beta: 2, model: inverted}\n")
    code, out, err = run("advise", str(scene), "--json")
    assert code == 0, err
    data = json.loads(out)
    assert data["limiting"]["label"] == "fast [red]stretch"
    assert data["models"]["oscillator"]["label"] == "fast [red]stretch"
    assert "label" not in data["models"]["inverted"]
    code, out, err = run("advise", str(scene))
    assert "limited by fast [red]stretch (oscillator) beta = 7" in out


@pytest.mark.parametrize("name, wrong", [("pefrl", 3), ("blanes-casas-ros764", 4),
                                         ("yoshida4", 1)])
def test_validate_warns_when_the_stated_evaluations_are_not_the_coefficients(run, tmp_path,
                                                                             name, wrong):
    """A copy of a library file with another ``evaluations:`` (a splitting, a processed
    method's kernel, a composition) is valid but warned about, naming both counts."""
    from stepsafe.methods.library import builtin_dir, resolve

    text = (builtin_dir() / f"{name}.yaml").read_text()
    right = resolve(name)[1].evaluations
    path = tmp_path / f"{name}.yaml"
    path.write_text(text.replace(f"evaluations: {right}\n", f"evaluations: {wrong}\n"))
    code, out, _ = run("validate", str(path))
    assert code == 0
    assert (f"evaluations: {wrong} stated, the coefficients make {right} force evaluations"
            in out)
    path.write_text(text)
    assert "evaluations:" not in run("validate", str(path))[1]


@pytest.mark.parametrize("args", [["--beta", "1e-310"], ["--beta", "5e-324"],
                                  ["--beta", "1e-310", "--beta", "1"]])
def test_a_frequency_whose_limit_is_beyond_every_float(run, args):
    """beta ~ 1e-310 puts its boundary 2/beta past the largest float: it limits no step
    (advise says so, exit 0, JSON consistent), and check passes any finite step it allows:
    never an internal error."""
    code, out, err = run("advise", "--method", "verlet", *args)
    assert code == 0, err
    data = json.loads(run("advise", "--method", "verlet", *args, "--json")[1])
    if len(args) == 2:
        assert data["h_max"] is None and data["h_max_limited_by"] == "horizon"
        assert "Safe for every h" in out
        assert run("check", "--method", "verlet", *args, "--step", "1e300")[0] == 0
    else:
        assert data["h_max"] == pytest.approx(2.0) and data["h_max_limited_by"] == "boundary"


@pytest.mark.parametrize("tol", [["--tol-phase", "1e-3"], ["--tol-energy", "1e-3"]])
def test_a_tolerance_on_a_frequency_beyond_every_float(run, tol):
    """Its accuracy limit is past the largest float too: advise says the tolerance holds
    for every float step (never an internal error), compare leaves the method unranked
    with no step and no cost (not 'bound by accuracy' at cost 0)."""
    code, out, err = run("advise", "--method", "verlet", "--beta", "1e-310", *tol)
    assert code == 0, err
    assert "for every float step" in " ".join(out.split())
    data = json.loads(run("compare", "--beta", "1e-310", "--methods", "verlet,bcss2", *tol,
                          "--json")[1])
    rows = data["methods"]
    for row in rows:
        assert row["h"] is None and row["cost"] is None and row["rank"] is None
        assert row["bound_by"] == "nothing" and row["h_tol"] is None


def test_a_modes_file_is_read_in_its_own_time_unit(run, tmp_path):
    """A scene file given to --modes keeps its time_unit: a 9 fs period is
    2 pi / 9 rad/fs = 698.13 rad/ps, so verlet's limit is 2 / 698.13 ps = 2.8648 fs
    whatever unit the command line uses; without --time-unit the file's becomes the
    command's; keys a scene file does not have are refused."""
    path = tmp_path / "modes.yaml"
    path.write_text("time_unit: fs\nmethod: yoshida4\nmodes: [{period: 9}]\n")
    limit_fs = 2 / (2 * math.pi / 9)
    for unit, scale in (("ps", 1e-3), ("fs", 1.0), ("ns", 1e-6), (None, 1.0)):
        option = ("--time-unit", unit) if unit else ()
        for factor, code in ((0.999, 0), (1.001, 1)):
            step = repr(factor * limit_fs * scale)
            got, out, err = run("check", "--method", "verlet", "--modes", str(path),
                                "--step", step, *option)
            assert got == code, (unit, factor, out, err)
            assert f"h = {step} {unit or 'fs'}" in out, out
    path.write_text("time_unit: fs\nperiods: 9\nmodes: [{period: 9}]\n")
    code, _, err = run("check", "--method", "verlet", "--modes", str(path), "--step", "1")
    assert code == 2 and "periods" in err and "unknown key" in err, err

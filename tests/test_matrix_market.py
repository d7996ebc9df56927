"""Matrix Market files are read by their definition, strictly: never a number by a prefix."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from stepsafe.exceptions import StepsafeError
from stepsafe.systems.matrixfile import read_matrix

BANNER = "%%MatrixMarket matrix {fmt} real {sym}\n"


def _write(folder: Path, matrix: np.ndarray, fmt: str, sym: str) -> Path:
    n = matrix.shape[0]
    lines = [BANNER.format(fmt=fmt, sym=sym), "% a comment\n"]
    if fmt == "coordinate":
        entries = [(i, j, matrix[i, j]) for j in range(n) for i in range(n)
                   if matrix[i, j] != 0 and (sym == "general" or i >= j)]
        lines.append(f"{n} {n} {len(entries)}\n")
        lines += [f"{i + 1} {j + 1} {float(v)!r}\n" for i, j, v in entries]
    else:
        lines.append(f"{n} {n}\n")
        lines += [f"{float(matrix[i, j])!r}\n" for j in range(n) for i in range(n)
                  if sym == "general" or i >= j]
    path = folder / f"m-{fmt}-{sym}.mtx"
    path.write_text("".join(lines))
    return path


@settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck))
@given(n=st.integers(1, 6), seed=st.integers(0, 2**32 - 1),
       fmt=st.sampled_from(["coordinate", "array"]), sym=st.sampled_from(["general",
                                                                           "symmetric"]))
def test_every_layout_reads_back_the_matrix(tmp_path_factory, n, seed, fmt, sym):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n)) * 10.0 ** rng.integers(-300, 300)
    A = A + A.T
    A[rng.random((n, n)) < 0.3] = 0.0
    A = np.triu(A) + np.triu(A, 1).T  # symmetric with zeros
    path = _write(tmp_path_factory.mktemp("mtx"), A, fmt, sym)
    got = read_matrix(path, path.name)
    np.testing.assert_array_equal(np.asarray(got), A)


@pytest.mark.parametrize("body, message", [
    ("1 1 1\n1 1 1_000_000\n", "not a plain number"),
    ("1 1 1\n1 1 0x10\n", "not a plain number"),
    ("1 1 1\n1 1 9abc\n", "not a plain number"),
    ("1 1 1\n1 1 4e\n", "not a plain number"),
    ("1 1 1\n1 1 1 7 8\n", "fields"),
    ("2 2 2\n1 1 1\n2 2 1 5\n", "fields"),
    ("2 2 3\n1 1 1\n2 2 1\n", "declares 3"),
    ("2 2 1\n1 1 1\n2 2 1\n", "declares 1"),
    ("2 2 1\n3 1 1\n", "indices"),
    ("2 2 1\n1.5 1 1\n", "indices"),
    ("2 2 1\n0 1 1\n", "indices"),
    ("1 1 1\n1 1 nan\n", "non-finite"),
    ("2 2\n1 1 1\n", "size line"),
    ("2 x 1\n1 1 1\n", "size line"),
])
def test_malformed_entries_are_refused(tmp_path, body, message):
    path = tmp_path / "bad.mtx"
    path.write_text(BANNER.format(fmt="coordinate", sym="general") + body)
    with pytest.raises(StepsafeError, match=message):
        read_matrix(path, "bad.mtx")


@pytest.mark.parametrize("text, message", [
    ("2 2 2\n1 1 1\n2 2 1\n", "not a Matrix Market file"),
    ("%%MatrixMarket matrix coordinate complex general\n1 1 1\n1 1 1 0\n", "complex"),
    ("%%MatrixMarket matrix coordinate pattern general\n1 1 1\n1 1\n", "pattern"),
    ("%%MatrixMarket matrix coordinate real skew-symmetric\n2 2 1\n2 1 1\n", "symmetry"),
    ("%%MatrixMarket matrix coordinate real symmetric\n2 2 1\n1 2 1\n", "lower triangle"),
    ("", "not a Matrix Market file"),
])
def test_headers_are_checked(tmp_path, text, message):
    path = tmp_path / "bad.mtx"
    path.write_text(text)
    with pytest.raises(StepsafeError, match=message):
        read_matrix(path, "bad.mtx")


def test_a_typo_in_a_matrix_file_is_exit_2_not_safe(run, tmp_path):
    """1_000_000 is not a Matrix Market number: exit 2 naming the file, never read as 1
    (which would check beta 1 instead of 1000 and call the step SAFE)."""
    (tmp_path / "K.mtx").write_text(BANNER.format(fmt="coordinate", sym="general")
                                    + "1 1 1\n1 1 1_000_000\n")
    scene = tmp_path / "s.yaml"
    scene.write_text("method: verlet\nh: 0.1\nsystem: {stiffness: K.mtx}\n")
    code, out, err = run("check", str(scene))
    assert code == 2 and "K.mtx" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("body, message", [
    ("2 2 4\n1 1 1e20\n1 1 5000\n1 1 -1e20\n2 2 1\n", "more than once"),
    ("2 2 3\n1 1 4\n1 1 4\n2 2 1\n", "more than once"),
])
def test_repeated_positions_are_refused(tmp_path, body, message):
    """Each position must be written once: summing repeated entries in float64 would
    cancel 5000 between +-1e20 (a stiffer system read as a softer one)."""
    path = tmp_path / "dup.mtx"
    path.write_text(BANNER.format(fmt="coordinate", sym="general") + body)
    with pytest.raises(StepsafeError, match=message):
        read_matrix(path, "dup.mtx")


def test_integer_field_holds_integers(tmp_path):
    path = tmp_path / "int.mtx"
    path.write_text("%%MatrixMarket matrix coordinate integer general\n1 1 1\n1 1 0.5\n")
    with pytest.raises(StepsafeError, match="not an integer"):
        read_matrix(path, "int.mtx")


@pytest.mark.parametrize("length", [1023, 1024, 1025, 5000, 100_000])
def test_long_comment_lines_are_comments(tmp_path, length):
    """A comment line longer than the size line's read is skipped whole."""
    path = tmp_path / "k.mtx"
    path.write_text("%%MatrixMarket matrix coordinate real symmetric\n%" + "x" * length
                    + "\n% short\n2 2 2\n1 1 4.0\n2 2 9.0\n")
    matrix = read_matrix(path, "k.mtx")
    dense = matrix.toarray() if hasattr(matrix, "toarray") else np.asarray(matrix)
    np.testing.assert_array_equal(dense, [[4.0, 0.0], [0.0, 9.0]])

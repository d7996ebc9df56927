"""The hostile-input corpus (tests/corpus): every file fails with one clear line.

Method files go through ``stepsafe validate``, scene files through ``stepsafe check``. Each
must exit 2, print one line naming the file (and the key, where there is one) with the
expected message, print no traceback and write nothing. Bounded time is not asserted with a
wall clock (CI machines are loaded): the messages name the budget that refused the input
before any large work, and the subprocess timeout only detects a hang. Files too large to
keep in the repository (100 MB, a 10^6-element list) are made on the fly.
"""

from __future__ import annotations

import errno
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

CORPUS = Path(__file__).resolve().parent / "corpus"
EXPECTED = json.loads((CORPUS / "expected.json").read_text())


def _run(args, cwd):
    # the timeout is a hang detector, not a benchmark
    return subprocess.run([sys.executable, "-m", "stepsafe", *args], capture_output=True,
                          text=True, cwd=cwd, timeout=120)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_corpus_file_fails_cleanly(name, tmp_path):
    path = CORPUS / name
    args = ["validate", str(path)] if name.startswith("method-") else ["check", str(path)]
    before = set(os.listdir(tmp_path))
    proc = _run(args, tmp_path)
    err = proc.stderr.strip()
    assert proc.returncode == 2, (proc.stdout, err)
    assert EXPECTED[name] in err, err
    assert str(path) in err or "did you mean" in err or "-s must be" in err \
        or "h must be" in err or "margin must be" in err, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err + proc.stdout
    assert set(os.listdir(tmp_path)) == before


def test_huge_and_special_files(tmp_path):
    huge = tmp_path / "huge.yaml"
    with open(huge, "wb") as fh:
        fh.truncate(100 * 2**20)  # 100 MB, sparse
    many = tmp_path / "many.yaml"
    many.write_text("name: m\nkind: splitting\norder: 2\nsource: x\ndrift: ["
                    + ", ".join(["0"] * 10**6) + "]\nkick: [1]\n")
    cases = [(huge, "bytes"), (many, "bytes"), (tmp_path / "missing.yaml", "no such file"),
             (tmp_path, "directory")]
    for path, message in cases:
        proc = _run(["validate", str(path) + ("/" if path.is_dir() else "")], tmp_path)
        assert proc.returncode == 2 and message in proc.stderr, proc.stderr
        assert "Traceback" not in proc.stderr


@pytest.mark.parametrize("command", ["validate", "check"])
def test_unreadable_file(tmp_path, monkeypatch, run, command):
    """A file its user may not read (mode 0): one line naming it, exit 2. Root (as CI
    runs) reads a file whatever its mode, so where the file is still readable the open the
    reader makes is refused as the kernel refuses it to anyone else (EACCES)."""
    path = tmp_path / "secret.yaml"
    path.write_text("name: x\n")
    path.chmod(0)
    if os.access(path, os.R_OK):
        real_open = os.open

        def refused(file, flags, *args, **kwargs):
            if os.fspath(file) == str(path):
                raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
            return real_open(file, flags, *args, **kwargs)

        monkeypatch.setattr(os, "open", refused)
    code, out, err = run(command, str(path))
    assert (code, out) == (2, "")
    assert err == f"stepsafe: error: {path}: cannot read: Permission denied\n"


def test_internal_error_exits_3_with_a_hint(run, monkeypatch):
    import stepsafe.api.linear

    def boom(*args, **kwargs):
        raise ZeroDivisionError("synthetic")

    monkeypatch.setattr(stepsafe.api.linear, "find_region", boom)
    code, out, err = run("region", "verlet")
    assert code == 3 and "internal error" in err and "--debug" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1

"""The hostile-input corpus (tests/corpus): every file fails with one clear line.

Method files go through ``stepsafe validate``, scene files through ``stepsafe check``. Each
must exit 2, print one line naming the file (and the key, where there is one) with the
expected message, print no traceback and write nothing. Bounded time is not asserted with a
wall clock (CI machines are loaded): the messages name the budget that refused the input
before any large work, and the subprocess timeout only detects a hang. The corpus runs in
one child process, each file through the command-line entry point in a folder of its own
(a hang or a crash stays in the child); a few files also run as ``python -m stepsafe``,
the real process, which must answer the same. Files too large to keep in the repository
(100 MB, a 10^6-element list) are made on the fly, each in a real process.
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


def _args(name: str) -> list[str]:
    path = str(CORPUS / name)
    return ["validate", path] if name.startswith("method-") else ["check", path]


#: Each job runs ``stepsafe ARGS`` through click's runner in its own (empty) folder and
#: records the exit code, both streams, any exception that escaped the entry point and the
#: files left in the folder.
_BATCH = """
import json, os, sys, traceback
from click.testing import CliRunner
from stepsafe.cli import main
results = {}
for name, args, cwd in json.loads(sys.stdin.read()):
    os.chdir(cwd)
    r = CliRunner().invoke(main, args)
    escaped = None
    if r.exception is not None and not isinstance(r.exception, SystemExit):
        escaped = "".join(traceback.format_exception(r.exception))
    results[name] = [r.exit_code, r.stdout, r.stderr, escaped, sorted(os.listdir(cwd))]
sys.stdout.write(json.dumps(results))
"""


@pytest.fixture(scope="module")
def corpus_results(tmp_path_factory):
    """Every corpus file's answer, from one child process (the timeout detects a hang)."""
    root = tmp_path_factory.mktemp("corpus")
    jobs = []
    for i, name in enumerate(sorted(EXPECTED)):
        cwd = root / str(i)
        cwd.mkdir()
        jobs.append((name, _args(name), str(cwd)))
    proc = subprocess.run([sys.executable, "-c", _BATCH], input=json.dumps(jobs),
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_corpus_file_fails_cleanly(name, corpus_results):
    code, out, err, escaped, left = corpus_results[name]
    path = str(CORPUS / name)
    err = err.strip()
    assert escaped is None, escaped
    assert code == 2, (out, err)
    assert EXPECTED[name] in err, err
    assert path in err or "did you mean" in err or "-s must be" in err \
        or "h must be" in err or "margin must be" in err, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err + out
    assert left == []


@pytest.mark.parametrize("name", ["method-alias-bomb.yaml", "method-latin1.yaml",
                                  "scene-matrix-huge-mtx.yaml", "scene-inf-h.yaml"])
def test_the_real_process_answers_as_the_corpus_run(name, tmp_path, corpus_results):
    """``python -m stepsafe`` on a method file, a matrix and a scene: the same exit code
    and streams as the in-process run of the corpus, and no file written."""
    proc = _run(_args(name), tmp_path)
    code, out, err, _, _ = corpus_results[name]
    assert (proc.returncode, proc.stdout, proc.stderr) == (code, out, err)
    assert os.listdir(tmp_path) == []


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

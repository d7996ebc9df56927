"""The CI recipes of the CI guide (docs/guides/ci.md) run as written: the pre-commit hook
definition and the GitHub Actions job, against a safe and an unsafe scene (run as pre-commit
and the job would run them, with the stepsafe installed here)."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
STEPSAFE = [sys.executable, "-m", "stepsafe"]


def _scenes(folder: Path) -> dict[str, Path]:
    (folder / "sub").mkdir()
    safe = folder / "safe.stepsafe.yaml"
    safe.write_text("method: verlet\nh: 0.1\nmodes: [{beta: 3, label: bond}]\n")
    unsafe = folder / "sub" / "unsafe.stepsafe.yml"
    unsafe.write_text("method: verlet\nh: 0.9\nmodes: [{beta: 3, label: bond}]\n")
    other = folder / "notes.yaml"  # not a scene: the hook must not pick it up
    other.write_text("just: notes\n")
    return {"safe": safe, "unsafe": unsafe, "other": other}


def _entry(entry: str) -> list[str]:
    words = shlex.split(entry)
    assert words[0] == "stepsafe"
    return STEPSAFE + words[1:]


def test_pre_commit_hook_definition(tmp_path):
    (hook,) = yaml.safe_load((ROOT / ".pre-commit-hooks.yaml").read_text())
    assert hook["id"] == "stepsafe-check" and hook["language"] == "python"
    files = _scenes(tmp_path)
    pattern = re.compile(hook["files"])
    chosen = sorted(str(p.relative_to(tmp_path)) for p in files.values()
                    if pattern.search(str(p.relative_to(tmp_path))))
    assert chosen == ["safe.stepsafe.yaml", "sub/unsafe.stepsafe.yml"]
    for names, code in ((chosen[:1], 0), (chosen, 1)):
        out = subprocess.run(_entry(hook["entry"]) + names, cwd=tmp_path, capture_output=True,
                             text=True)
        assert out.returncode == code, out.stderr
        assert out.stdout.startswith("safe.stepsafe.yaml: SAFE")
    assert "sub/unsafe.stepsafe.yml: UNSAFE" in out.stdout and "bond (oscillator)" in out.stdout


def test_github_actions_job(tmp_path):
    job = yaml.safe_load((ROOT / "examples" / "github-actions.yml").read_text())
    steps = job["jobs"]["step-size"]["steps"]
    (check,) = [s["run"] for s in steps if "stepsafe check" in s.get("run", "")]
    (install,) = [s["run"] for s in steps if s.get("run", "").startswith("pip install")]
    assert "vars.STEPSAFE_PIP" in install
    files = _scenes(tmp_path)
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)
    subprocess.run(["git", "add", "."], cwd=tmp_path, check=True)
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    shim = bin_dir / "stepsafe"
    shim.write_text(f"#!/bin/sh\nexec {shlex.join(STEPSAFE)} \"$@\"\n")
    shim.chmod(0o755)
    env = {"PATH": f"{bin_dir}:/usr/bin:/bin", "HOME": str(tmp_path)}
    out = subprocess.run(["bash", "-e", "-c", check], cwd=tmp_path, capture_output=True, text=True,
                         env=env)
    assert out.returncode == 1 and "sub/unsafe.stepsafe.yml: UNSAFE" in out.stdout, out.stderr
    files["unsafe"].unlink()
    subprocess.run(["git", "add", "-A"], cwd=tmp_path, check=True)
    out = subprocess.run(["bash", "-e", "-c", check], cwd=tmp_path, capture_output=True, text=True,
                         env=env)
    assert out.returncode == 0 and "safe.stepsafe.yaml: SAFE" in out.stdout, out.stderr


def _collected(probe: Path, *args: str) -> tuple[int, list[str]]:
    """The tests of ``probe`` that pytest selects under the project's configuration."""
    out = subprocess.run([sys.executable, "-m", "pytest", "-c", str(ROOT / "pyproject.toml"),
                          "--collect-only", "-p", "no:cacheprovider", *args, str(probe)],
                         capture_output=True, text=True, cwd=probe.parent)
    return out.returncode, sorted(line.split("::")[-1] for line in out.stdout.splitlines()
                                  if "::" in line)


@pytest.mark.slow
def test_the_readme_test_line_leaves_out_the_slow_tests_and_ci_runs_them(tmp_path):
    """The README's test line (plain pytest) skips the tests marked slow, `-m slow` selects
    only them and the command the README gives for the whole suite selects both; a
    misspelt marker is an error, not a test silently left out; .ci/run runs the slow tests
    after the README's line."""
    probe = tmp_path / "test_probe.py"
    probe.write_text("import pytest\n\n\n@pytest.mark.slow\ndef test_slow():\n    pass\n\n\n"
                     "def test_fast():\n    pass\n")
    assert _collected(probe) == (0, ["test_fast"])
    assert _collected(probe, "-m", "slow") == (0, ["test_slow"])
    assert _collected(probe, "-m", "slow or not slow") == (0, ["test_fast", "test_slow"])
    probe.write_text(probe.read_text().replace("mark.slow", "mark.slwo"))
    assert _collected(probe)[0] != 0
    readme = (ROOT / "README.md").read_text()
    line = readme.split("# install and run the tests\n", 1)[1].split("\n", 1)[0]
    assert line == "pip install '.[test]' && pytest -n 2"
    assert 'pytest -n 2 -m "slow or not slow"' in readme and "pytest -n 2 -m slow" in readme
    ci = (ROOT / ".ci" / "run").read_text()
    assert "# install and run the tests" in ci
    assert ci.index('eval "$cmd"') < ci.index("\npytest -n 2 -m slow\n")
    assert "'.[docs]'" in ci and "mkdocs build --strict" in ci

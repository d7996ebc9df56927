"""The built-in method files reach users of the wheel, not only of an editable install."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    if not (ROOT / "pyproject.toml").is_file():
        pytest.skip("not a source checkout")
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                    "-q", "-w", str(out), str(ROOT)], check=True, capture_output=True,
                   cwd=out)
    (path,) = out.glob("stepsafe-*.whl")
    return path


def test_wheel_contains_every_method_file(wheel):
    shipped = {p.name for p in (ROOT / "methods").glob("*.yaml")}
    with zipfile.ZipFile(wheel) as zf:
        packaged = {Path(n).name for n in zf.namelist() if n.startswith("stepsafe/methods/")}
    assert shipped and shipped <= packaged


def test_installed_wheel_resolves_builtin_methods(wheel, tmp_path):
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target",
                    str(target), str(wheel)], check=True, capture_output=True)
    code = ("import stepsafe.methods.library as L; p = L.builtin_dir(); "
            "m, e = L.resolve('pefrl'); print(p); print(m.name)")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                         text=True, cwd=tmp_path, env={"PYTHONPATH": str(target)}).stdout
    where, name = out.split()
    assert name == "pefrl" and Path(where).is_relative_to(target)

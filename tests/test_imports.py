"""Import discipline (start-up is part of the product: check runs on every commit).

Decided: ``import stepsafe`` loads none of the third-party packages below (its API is loaded
on first use). The command line imports the package's own modules at their tops, so
``import stepsafe.cli`` loads what ``check`` needs, numpy and PyYAML, and no more; ``check``
and ``advise`` on a built-in method never load scipy, mpmath, sympy, matplotlib, OpenMM or
jax (each is imported inside the function that needs it), and ``check`` does not load rich
either (its output is a few plain lines), nor ``numpy.ma`` (which numpy's set routines load:
a tenth of the start-up). Timings live in benchmarks/ (``benchmarks/startup.py``).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
HEAVY = {"numpy", "numpy.ma", "scipy", "rich", "yaml", "mpmath", "sympy", "matplotlib",
         "openmm", "jax", "blackjax"}
REPORT = ("print(json.dumps(sorted(({m.split('.')[0] for m in sys.modules} | set(sys.modules)) & "
          f"set({sorted(HEAVY)!r}))))")


def loaded_after(*argv: str, module: str = "stepsafe.cli") -> set[str]:
    """The heavy packages loaded by the command ``stepsafe ARGV`` (none: by importing
    ``module``), in a fresh interpreter."""
    code = (
        "import sys, json\n"
        f"sys.argv = ['stepsafe', *{list(argv)!r}]\n"
        "from stepsafe.cli import main\n"
        "try:\n    main()\nexcept SystemExit:\n    pass\n"
        + REPORT
        if argv else
        f"import sys, json, {module}\n" + REPORT
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         check=True).stdout
    return set(json.loads(out.strip().splitlines()[-1]))


def test_package_import_loads_no_heavy_package():
    assert loaded_after(module="stepsafe") == set()


def test_cli_import_loads_only_what_check_needs():
    assert loaded_after() <= {"numpy", "yaml"}


def test_check_loads_numpy_and_yaml_only():
    for argv in (("check", "examples/scene.yaml"),
                 ("check", "--method", "verlet", "--step", "0.5", "--beta", "1")):
        assert loaded_after(*argv) == {"numpy", "yaml"}, argv


def test_advise_and_region_never_load_scipy_or_mpmath():
    for argv in (("advise", "--method", "yoshida4", "--beta", "3.2"),
                 ("region", "lobatto3ab", "-s", "3")):
        assert not loaded_after(*argv) & {"numpy.ma", "scipy", "mpmath", "sympy", "matplotlib",
                                          "openmm", "jax", "blackjax"}

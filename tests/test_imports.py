"""Import discipline (start-up is part of the product: check runs on every commit).

Decided: ``import stepsafe.cli`` loads click only; ``check`` and ``advise`` on a built-in
method load numpy and PyYAML but never scipy, mpmath, sympy or matplotlib, and ``check``
does not load rich either (its output is a few plain lines), nor ``numpy.ma`` (which numpy's
set routines load: a tenth of the start-up). Timings live in benchmarks/.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
HEAVY = {"numpy", "numpy.ma", "scipy", "rich", "yaml", "mpmath", "sympy", "matplotlib"}
REPORT = ("print(json.dumps(sorted(({m.split('.')[0] for m in sys.modules} | set(sys.modules)) & "
          f"set({sorted(HEAVY)!r}))))")


def loaded_after(*argv: str) -> set[str]:
    code = (
        "import sys, json\n"
        f"sys.argv = ['stepsafe', *{list(argv)!r}]\n"
        "from stepsafe.cli import main\n"
        "try:\n    main()\nexcept SystemExit:\n    pass\n"
        + REPORT
        if argv else
        "import sys, json, stepsafe.cli\n" + REPORT
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         check=True).stdout
    return set(json.loads(out.strip().splitlines()[-1]))


def test_cli_import_is_light():
    assert loaded_after() == set()


def test_check_loads_numpy_and_yaml_only():
    assert loaded_after("check", "examples/scene.yaml") == {"numpy", "yaml"}


def test_advise_and_region_never_load_scipy_or_mpmath():
    for argv in (("advise", "--method", "yoshida4", "--beta", "3.2"),
                 ("region", "lobatto3ab", "-s", "3")):
        assert not loaded_after(*argv) & {"numpy.ma", "scipy", "mpmath", "sympy", "matplotlib"}

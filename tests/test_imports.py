"""Import discipline (start-up is part of the product: check runs on every commit).

Decided: ``import stepsafe`` loads none of the third-party packages below (its API is loaded
on first use). The command line loads a command's module when the command is looked up
(:data:`stepsafe.cli.group.COMMANDS`), and a module that only some inputs reach (a scene's
``system:``, a temperature, an impulse method, ``--verify``, the high-precision points) when
such an input comes (:mod:`stepsafe.lazy`). So ``check`` loads, of the third-party packages,
click, numpy and PyYAML and nothing else, and of the package's own modules none of the MD,
thermal, HMC, measurement or r-RESPA ones, nor the mpmath reference, whatever the method,
step and frequencies of a linear check; ``check`` and ``advise`` on a built-in method never
load scipy, mpmath, sympy, matplotlib, OpenMM or jax (each is imported inside the function
that needs it), and ``check`` does not load rich either (its output is a few plain lines),
nor ``numpy.ma`` (which numpy's set routines load: a tenth of the start-up); a check of an
explicit method's frequencies printed as text loads neither the modules of tolerances, error
tables, resonance orders and stage solvers nor :mod:`json`. Timings live in benchmarks/
(``benchmarks/startup.py``).
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


#: What a linear check (frequencies, a step, a method) never loads: the package's modules of
#: the other user groups and of the inputs a linear check does not have.
NOT_LINEAR = ("stepsafe.systems.loader", "stepsafe.systems.md", "stepsafe.systems.thermal",
              "stepsafe.systems.coupled", "stepsafe.api.thermal", "stepsafe.api.hmc",
              "stepsafe.core.hmc", "stepsafe.api.md", "stepsafe.api.measure",
              "stepsafe.reference", "stepsafe.cli.accuracy", "stepsafe.cli.measure",
              "stepsafe.cli.respa", "stepsafe.cli.sampling")

#: Run in a fresh interpreter: checks drawn by hypothesis (every built-in method that takes
#: frequencies, steps and frequencies over many scales, each model), then the package's
#: modules loaded and the exit codes seen.
LINEAR_CHECKS = """
import json, sys
from pathlib import Path
from click.testing import CliRunner
from hypothesis import given, settings, strategies as st
from stepsafe.cli import main
from stepsafe.methods.library import FAMILIES, builtin_names, resolve
names = [n for n in builtin_names() if n in FAMILIES or resolve(n)[0].kind != "impulse"]
scales = st.floats(-8, 8).map(lambda e: 10.0 ** e)
codes = set()

@settings(max_examples=40, deadline=None, database=None)
@given(name=st.sampled_from(names), h=scales, beta=scales,
       option=st.sampled_from(["--beta", "--saddle-beta", "--inverted-beta"]))
def run(name, h, beta, option):
    stages = ["-s", "3"] if name in FAMILIES else []
    result = CliRunner().invoke(main, ["check", "--method", name, *stages, "--step",
                                       repr(h), option, repr(beta)])
    assert result.exit_code in (0, 1, 2), result.output
    codes.add(result.exit_code)

run()
for scene in ("scene.yaml",):
    CliRunner().invoke(main, ["check", str(Path("examples") / scene)])
print(json.dumps({"modules": sorted(m for m in sys.modules if m.startswith("stepsafe")),
                  "codes": sorted(codes)}))
"""


def test_a_linear_check_loads_no_module_of_the_other_user_groups():
    """For checks drawn over every built-in method (but impulse ones, which take a scene),
    steps and frequencies from 1e-8 to 1e8 and each model, safe and unsafe, and a scene with
    modes: none loads a module of :data:`NOT_LINEAR`."""
    out = subprocess.run([sys.executable, "-c", LINEAR_CHECKS], capture_output=True,
                         text=True, cwd=ROOT, check=True).stdout
    found = json.loads(out.strip().splitlines()[-1])
    assert {0, 1} <= set(found["codes"]), found["codes"]
    assert [m for m in found["modules"] if m.startswith(NOT_LINEAR)] == []


#: What only tolerances, error tables, a resonance order, an implicit method's stage solver,
#: a Langevin splitting or ``--json`` need: a check of an explicit method's frequencies,
#: printed as text, loads none.
NOT_PLAIN_CHECK = {"stepsafe.core.accuracy", "stepsafe.core.tradeoff",
                   "stepsafe.core.resonances", "stepsafe.core.solver",
                   "stepsafe.methods.langevin", "json", "difflib"}


def test_a_plain_check_loads_no_module_of_tolerances_resonances_or_json():
    for argv in (("check", "examples/scene.yaml"),
                 ("check", "--method", "verlet", "--step", "0.5", "--beta", "1"),
                 ("check", "--method", "pefrl", "--step", "0.5", "--saddle-beta", "1")):
        code = (f"import sys\nsys.argv = ['stepsafe', *{list(argv)!r}]\n"
                "from stepsafe.cli import main\n"
                "try:\n    main()\nexcept SystemExit:\n    pass\n"
                f"print(sorted(set(sys.modules) & {NOT_PLAIN_CHECK!r}))")
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             cwd=ROOT, check=True).stdout
        assert out.strip().splitlines()[-1] == "[]", argv


#: The top-level names of the modules loaded from site-packages (third-party packages),
#: but those the interpreter loads before any command (a .pth file's import hooks).
THIRD_PARTY = ("import sys, sysconfig\n"
               "site = tuple({sysconfig.get_paths()[k] for k in ('purelib', 'platlib')})\n"
               "third = lambda: {m.split('.')[0] for m, mod in list(sys.modules.items())\n"
               "    if str(getattr(mod, '__file__', None) or '').startswith(site)}\n"
               "start = third()\n")


def test_check_loads_click_numpy_and_pyyaml_and_no_other_third_party_package():
    for argv in (("check", "examples/scene.yaml"),
                 ("check", "--method", "yoshida4", "--step", "0.5", "--beta", "1")):
        code = (THIRD_PARTY + f"sys.argv = ['stepsafe', *{list(argv)!r}]\n"
                "from stepsafe.cli import main\n"
                "try:\n    main()\nexcept SystemExit:\n    pass\n"
                "print(sorted(third() - start - {'stepsafe'}))")
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             cwd=ROOT, check=True).stdout
        assert out.strip().splitlines()[-1] in (str(["_yaml", "click", "numpy", "yaml"]),
                                                str(["click", "numpy", "yaml"])), argv


def test_each_command_is_defined_by_the_module_the_group_loads_for_it():
    """The group's table (:data:`stepsafe.cli.group.COMMANDS`) names, for each command, the
    module that defines it, and every command defined is in the table; with every command
    module loaded, ``stepsafe.cli.main`` is still the group (no module of the package is
    named ``main``)."""
    code = ("import json\nfrom stepsafe.cli.group import COMMANDS, main\n"
            "from stepsafe.lazy import loaded\n"
            "table = {n: loaded(m).__name__ for n, m in COMMANDS.items()}\n"
            "defined = {n: c.callback.__module__ for n, c in main.commands.items()}\n"
            "from stepsafe.cli import main as entry\n"
            "print(json.dumps([table, defined, entry is main]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, check=True).stdout
    table, defined, same = json.loads(out)
    assert table == defined
    assert same

"""Every command's ``--json`` output is valid against the JSON Schema that ``stepsafe
schema output COMMAND`` prints, carries ``schema_version`` first, and so does the
matching ``to_dict()``; a record that breaks its schema is caught by the validator."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

import stepsafe
from stepsafe.api.schemas import OUTPUTS
from stepsafe.core.records import SCHEMA_VERSION

jsonschema = pytest.importorskip("jsonschema")

ROOT = Path(__file__).resolve().parent.parent
SCENE = str(ROOT / "examples/scene.yaml")
PENDULUM = str(ROOT / "examples/pendulum.yaml")

#: Real invocations of each command, covering each shape of its output (a linear and an
#: impulse method, a safe and an unsafe step, a file that cannot be checked, rows and a
#: refinement).
RUNS = {
    "methods": [["methods"]],
    "show": [["show", "verlet"], ["show", "bcr764"], ["show", "respa-verlet"],
             ["show", "gauss", "-s", "2"]],
    "region": [["region", "verlet", "--model", "all"], ["region", "rk4"],
               ["region", "respa-verlet", "--ratio", "0.1"]],
    "advise": [["advise", "--method", "verlet", "--beta", "1", "--saddle-beta", "2"],
               ["advise", str(ROOT / "examples/double-well.yaml")],
               ["advise", str(ROOT / "examples/respa-water.yaml")]],
    "check": [["check", SCENE], ["check", "--method", "verlet", "--step", "3", "--beta", "1"],
              ["check", SCENE, str(ROOT / "examples/respa-water.yaml"),
               str(ROOT / "README.md")]],
    "error": [["error", "verlet", "--z", "0.5", "--z", "3"],
              ["error", "bcr764", "--z", "0.3"], ["error", "verlet", "--model", "saddle",
                                                  "--z", "0.5"]],
    "compare": [["compare", "--beta", "1", "--inverted-beta", "1", "--tol-phase", "1e-6"]],
    "hmc": [["hmc", "--sigma", "1", "--sigma", "0.1", "--steps", "5",
             "--methods", "verlet,rk4,symplectic-euler"],
            ["hmc", "--sigma", "1", "--length", "5", "--step", "0.5", "--jitter", "0.1"],
            ["hmc", str(ROOT / "examples/banana.yaml"), "--steps", "10", "--methods",
             "verlet", "--step", "0.9"]],
    "design": [["design", "--sigma", "1", "--sigma", "0.3", "--step", "0.5"],
               ["design", "--sigma", "1", "--step", "0.5", "--stages", "3"]],
    "respa": [["respa", "respa-verlet", "--fast-beta", "10", "--slow-beta", "1"],
              ["respa", "respa-verlet", "--fast-beta", "10", "--slow-beta", "1",
               "--step", "0.3"]],
    "measure": [["measure", PENDULUM, "--h", "0.1", "--h", "0.5", "--time", "5"],
                ["measure", PENDULUM, "--tol-energy", "1e-3", "--time", "5"],
                ["measure", PENDULUM, "--h", "0.5", "--time", "5", "--ensemble", "20",
                 "--kT", "0.2"],
                ["measure", PENDULUM, "--h", "0.5", "--time", "5", "--ensemble", "20",
                 "--energy", "-0.5", "--seed", "4"]],
}

CASES = [(command, args) for command, runs in RUNS.items() for args in runs]


def _validator(command):
    schema = OUTPUTS[command]
    full = stepsafe_schema(command)
    jsonschema.Draft202012Validator.check_schema(full)
    assert full["$schema"].endswith("2020-12/schema") and schema.items() <= full.items()
    return jsonschema.Draft202012Validator(full)


def stepsafe_schema(command):
    from stepsafe.api.schemas import output_schema

    return output_schema(command)


def test_every_command_with_json_has_a_schema_and_runs_here():
    """The commands that take ``--json`` are exactly those with a schema, and each has
    runs in this file."""
    import click
    from click.testing import CliRunner

    from stepsafe.cli import main

    with click.Context(main) as ctx:
        commands = {name: main.get_command(ctx, name) for name in main.list_commands(ctx)}
    with_json = {name for name, command in commands.items()
                 if any("--json" in p.opts for p in command.params)}
    assert with_json == set(OUTPUTS) == set(RUNS)
    assert CliRunner().invoke(main, ["schema", "output", "nothing"]).exit_code == 2


@pytest.mark.parametrize("command, args", CASES, ids=[" ".join(a[:3]) for _, a in CASES])
def test_json_output_is_valid_against_its_schema(run, command, args):
    code, out, err = run(*args, "--json")
    assert code in (0, 1, 2), err
    data = json.loads(out)
    records = data if isinstance(data, list) else [data]
    assert records and all(next(iter(r)) == "schema_version" for r in records)
    assert all(r["schema_version"] == SCHEMA_VERSION for r in records)
    _validator(command).validate(data)
    # the schema printed by the command is the one validated against
    code, printed, _ = run("schema", "output", command)
    assert code == 0 and json.loads(printed) == stepsafe_schema(command)


@pytest.mark.parametrize("command, args", [
    ("hmc", ["hmc", "--sigma", "1", "--steps", "5"]),
    ("check", ["check", SCENE]),
    ("design", ["design", "--sigma", "1", "--step", "0.5"]),
    ("respa", ["respa", "respa-verlet", "--fast-beta", "10", "--slow-beta", "1"]),
])
def test_schema_refuses_a_record_with_an_unknown_a_missing_or_a_mistyped_key(run, command,
                                                                           args):
    """The schemas are not vacuous: a key the schema does not state, a key taken away, a
    number or a truth value given as text, and a wrong ``schema_version`` each fail
    validation."""
    _, out, _ = run(*args, "--json")
    data = json.loads(out)
    validator = _validator(command)
    validator.validate(data)
    extra = {**data, "unexpected": 1}
    missing = {k: v for k, v in data.items() if k != list(data)[1]}
    wrong_version = {**data, "schema_version": SCHEMA_VERSION + 1}
    mistyped = copy.deepcopy(data)
    scalar = next(k for k, v in data.items() if isinstance(v, (int, float))
                  and k != "schema_version")
    mistyped[scalar] = str(mistyped[scalar])
    for bad in (extra, missing, wrong_version, mistyped):
        assert not validator.is_valid(bad), bad


@pytest.mark.parametrize("command, call", [
    ("show", lambda: stepsafe.method("verlet").to_dict()),
    ("region", lambda: stepsafe.region("verlet").to_dict()),
    ("advise", lambda: stepsafe.advise("verlet", [1.0]).to_dict()),
    ("check", lambda: stepsafe.check("verlet", 0.5, [1.0]).to_dict()),
    ("check", lambda: stepsafe.check_scenes([SCENE]).to_dict()),
    ("error", lambda: stepsafe.errors("verlet", [0.5]).to_dict()),
    ("compare", lambda: stepsafe.compare(["verlet"], [1.0]).to_dict()),
    ("hmc", lambda: stepsafe.hmc(["verlet"], sigma=[1.0], trajectory_steps=4).to_dict()),
    ("design", lambda: stepsafe.design(sigma=[1.0], step=0.5).to_dict()),
    ("respa", lambda: stepsafe.impulse("verlet", "verlet", substeps=4, fast_beta=10.0,
                                       slow_beta=1.0).to_dict()),
])
def test_to_dict_carries_schema_version_and_fits_the_command_schema(command, call):
    data = json.loads(json.dumps(stepsafe.core.records.json_ready(call()), allow_nan=False))
    assert list(data)[0] == "schema_version" and data["schema_version"] == SCHEMA_VERSION
    _validator(command).validate(data)


def test_json_schemas_of_files_carry_no_schema_version(run):
    """``schema method`` and ``schema scene`` print JSON Schemas, not records."""
    for which in ("method", "scene"):
        code, out, _ = run("schema", which)
        assert code == 0 and "schema_version" not in json.loads(out)

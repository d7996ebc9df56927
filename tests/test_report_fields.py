"""Every key of every command's ``--json`` is a typed attribute of the report the command
built, holding that key's value; the command prints that report's ``to_dict()`` unchanged;
each output fits its command's JSON Schema; and each closed record of those schemas names
exactly the keys its report can carry.

The inputs cover each shape of the output: decoupled modes, tolerances, a Langevin
splitting, a 1-dof Hamiltonian, a coupled system, a scene at temperature, an impulse
method, a Gaussian and a potential HMC target, a measured run, a refinement and an
ensemble. Nested records that are reports (rows, modes, runs) are followed; records that
are plain mappings (a system's items, the analysis at temperature, a verification) are
compared whole against the attribute that holds them.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import math
from pathlib import Path
from typing import Any

import pytest

from stepsafe.api import hmc_reports, md_reports, measure_reports, reports
from stepsafe.api.reports import json_attribute
from stepsafe.core.hmc_target.advice import TargetReport
from stepsafe.core.records import json_ready

ROOT = Path(__file__).resolve().parent.parent
EX = ROOT / "examples"

#: Each command with --json on inputs that give each shape of its record.
RUNS = [
    ["region", "verlet", "--model", "all"],
    ["region", "rk4", "--verify"],
    ["region", "verlet", "--criterion", "stability"],
    ["region", "respa-verlet", "--ratio", "0.1"],
    ["advise", "--method", "verlet", "--beta", "1", "--saddle-beta", "2"],
    ["advise", "--method", "verlet", "--beta", "1", "--tol-phase", "1e-4", "--tol-energy",
     "1e-4"],
    ["advise", "--method", "verlet", "--beta", "1", "--resonance-order", "4", "--verify"],
    ["advise", "--method", "gauss", "-s", "2", "--beta", "1", "--tol-phase", "1e-4"],
    ["advise", "--method", "verlet", "--beta", "1", "--criterion", "stability"],
    ["advise", "--method", "baoab", "--beta", "1"],
    ["advise", str(EX / "double-well.yaml")],
    ["advise", str(EX / "paper-section3-system.yaml")],
    ["advise", str(EX / "respa-water.yaml")],
    ["advise", str(EX / "morse-300K.yaml")],
    ["check", str(EX / "scene.yaml"), "--verify"],
    ["check", "--method", "verlet", "--step", "3", "--beta", "1"],
    ["check", "--method", "gauss", "-s", "2", "--beta", "1", "--step", "1.9"],
    ["check", "--method", "verlet", "--beta", "1", "--step", "1.5", "--criterion",
     "stability"],
    ["check", "--method", "baoab", "--step", "0.5", "--beta", "1"],
    ["check", str(EX / "double-well.yaml")],
    ["check", str(EX / "paper-section3-system.yaml")],
    ["check", str(EX / "morse-300K.yaml")],
    ["check", str(EX / "scene.yaml"), str(EX / "respa-water.yaml"), str(ROOT / "README.md")],
    ["error", "verlet", "--z", "0.5", "--z", "3"],
    ["error", "bcr764", "--z", "0.3"],
    ["error", "verlet", "--model", "saddle", "--z", "0.5"],
    ["compare", "--beta", "1", "--inverted-beta", "1", "--tol-phase", "1e-6", "--methods",
     "verlet,bcr764,gauss:2"],
    ["compare", "--beta", "1", "--tol-phase", "1e-4", "--methods", "verlet,yoshida4",
     "--measure", str(EX / "pendulum.yaml"), "--time", "5"],
    ["hmc", "--sigma", "1", "--sigma", "0.1", "--steps", "5", "--methods",
     "verlet,rk4,symplectic-euler"],
    ["hmc", "--sigma", "1", "--length", "5", "--step", "0.5", "--jitter", "0.1"],
    ["hmc", str(EX / "banana.yaml"), "--steps", "10", "--methods", "verlet", "--step", "0.9"],
    ["design", "--sigma", "1", "--sigma", "0.3", "--step", "0.5"],
    ["design", "--sigma", "1", "--step", "0.5", "--stages", "3"],
    ["respa", "respa-verlet", "--fast-beta", "10", "--slow-beta", "1", "--step", "0.3"],
    ["measure", str(EX / "pendulum.yaml"), "--h", "0.1", "--h", "0.5", "--time", "5"],
    ["measure", str(EX / "pendulum.yaml"), "--tol-energy", "1e-3", "--time", "5"],
    ["measure", str(EX / "pendulum.yaml"), "--h", "0.5", "--time", "5", "--ensemble", "20",
     "--kT", "0.2"],
    ["measure", str(EX / "pendulum.yaml"), "--h", "0.5", "--time", "5", "--ensemble", "20",
     "--energy", "-0.5", "--seed", "4"],
]

#: Every type whose ``to_dict()`` a command prints.
REPORTS = (reports.RegionReport, reports.AdviceReport, reports.CheckReport,
           reports.SceneChecks, reports.ErrorTable, reports.CompareReport,
           hmc_reports.HmcReport, TargetReport, hmc_reports.DesignReport,
           md_reports.ImpulseReport, md_reports.ImpulseModesReport,
           measure_reports.MeasureReport, measure_reports.Refinement,
           measure_reports.EnsembleReport)


def _declared(owner: type, name: str) -> bool:
    """``name`` is a dataclass field, a documented property or a class constant of
    ``owner``."""
    if dataclasses.is_dataclass(owner) and name in {f.name for f in dataclasses.fields(owner)}:
        return True
    static = inspect.getattr_static(owner, name, None)
    if isinstance(static, property):
        return (bool(static.__doc__) and static.fget is not None
                and "return" in inspect.get_annotations(static.fget))
    hints = {k: v for cls in owner.__mro__ for k, v in inspect.get_annotations(cls).items()}
    return "ClassVar" in str(hints.get(name, ""))


def _held(report: Any, key: str, where: str) -> Any:
    """The value of the attribute that holds ``key`` (a dotted path through nested typed
    records; None past a record that is None)."""
    value = report
    for part in json_attribute(type(report), key).split("."):
        assert _declared(type(value), part), \
            f"{where}.{key}: {type(value).__name__} has no typed attribute {part!r}"
        value = getattr(value, part)
        if value is None:
            return None
    return value


def _is_record(value: Any) -> bool:
    return dataclasses.is_dataclass(value) and not isinstance(value, type)


def _as_json(value: Any) -> Any:
    if hasattr(value, "to_dict"):
        value = value.to_dict()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    if hasattr(value, "items"):
        value = {k: _as_json(v) for k, v in value.items()}
    elif isinstance(value, (list, tuple)):
        value = [_as_json(v) for v in value]
    return json.loads(json.dumps(json_ready(value)))


def assert_covered(report: Any, data: dict[str, Any], where: str) -> int:
    """Each key of ``data`` is a typed attribute of ``report`` holding its value; nested
    reports are followed. Returns how many keys were checked."""
    checked = 0
    for key, value in data.items():
        if key == "schema_version":
            continue
        held = _held(report, key, where)
        checked += 1
        if _is_record(held) and isinstance(value, dict):
            checked += assert_covered(held, value, f"{where}.{key}")
        elif (isinstance(held, tuple) and held and all(_is_record(h) for h in held)
              and isinstance(value, list)):
            assert len(held) == len(value), f"{where}.{key}"
            for i, (h, v) in enumerate(zip(held, value)):
                checked += assert_covered(h, v, f"{where}.{key}[{i}]")
        elif key == "seconds_per_time":  # a wall-clock time: differs between calls
            assert (held is None) == (value is None), f"{where}.{key}"
        else:
            assert _as_json(held) == value, f"{where}.{key}: {held!r} != {value!r}"
    return checked


def _without_wall_time(data: Any) -> Any:
    if isinstance(data, dict):
        return {k: None if k == "seconds_per_time" else _without_wall_time(v)
                for k, v in data.items()}
    if isinstance(data, list):
        return [_without_wall_time(v) for v in data]
    return data


@pytest.fixture
def printed_reports(monkeypatch):
    """Every report whose ``to_dict()`` is called, with what it returned."""
    made: list[tuple[Any, dict[str, Any]]] = []
    for cls in REPORTS:
        original = cls.to_dict

        def to_dict(self, original=original):
            out = original(self)
            made.append((self, out))
            return out

        monkeypatch.setattr(cls, "to_dict", to_dict)
    return made


@pytest.mark.parametrize("args", [
    pytest.param(r, marks=pytest.mark.slow) if r[0] == "advise" and r[-1].endswith("-300K.yaml")
    else r for r in RUNS], ids=[" ".join(Path(a).name for a in r[:4])
                                           for r in RUNS])
def test_every_json_key_is_a_typed_field_of_the_report_printed(run, printed_reports, args):
    """The command prints one report's ``to_dict()`` as it is (nothing added or changed
    after it); every key in it, at every level that is a report, is a declared field,
    property or constant of that report whose value is the key's value; and the output
    fits the schema ``stepsafe schema output COMMAND`` prints (whose advise and check
    records are closed)."""
    from stepsafe.api.schemas import output_schema

    code, out, err = run(*args, "--json")
    assert code in (0, 1, 2), err
    data = json.loads(out)
    jsonschema = pytest.importorskip("jsonschema")
    jsonschema.Draft202012Validator(output_schema(args[0])).validate(data)
    printed = [report for report, made in printed_reports
               if json.loads(json.dumps(json_ready(made))) == data]
    assert printed, f"{args[0]} --json is not the to_dict() of any report it built"
    report = printed[-1]
    assert type(report) in REPORTS
    # the same report's to_dict() once more gives the same record (the wall time aside)
    again = json.loads(json.dumps(json_ready(report.to_dict())))
    assert _without_wall_time(again) == _without_wall_time(data)
    assert assert_covered(report, data, args[0]) >= len(data) - 1



def test_a_record_key_without_a_typed_field_is_refused():
    """A report built from a record refuses a key it has no field for (a key cannot reach
    the JSON around the typed fields)."""
    data = {"method": "verlet", "h_max": 2.0, "h_max_limited_by": "boundary",
            "safe_h": [[0.0, 2.0]], "horizon": None}
    report = reports.AdviceReport(**reports.record_fields(reports.AdviceReport, data))
    assert reports.unversioned(report.to_dict()) == data
    with pytest.raises(TypeError, match="no field for the JSON key 'surprise'"):
        reports.record_fields(reports.AdviceReport, {**data, "surprise": 1})


def test_record_fields_give_json_values_back_unchanged():
    """A record with non-finite numbers, nested objects and arrays comes back from the
    report's fields as the JSON it stood for (inf and NaN as null), and the fields that
    hold its nested objects are read-only."""
    data = {"method": "m", "h_max": math.inf, "h_max_limited_by": "horizon",
            "safe_h": [[0.0, None], [1.5, 2.5]], "horizon": math.nan,
            "system": {"items": [{"q": [1.0, 2.0], "type": "bound"}], "notes": []},
            "accuracy": []}
    report = reports.AdviceReport(**reports.record_fields(reports.AdviceReport, data))
    assert report.h_max is None and report.safe_h == ((0.0, None), (1.5, 2.5))
    assert reports.unversioned(report.to_dict()) == json_ready(data)
    assert report.system is not None
    with pytest.raises(TypeError):
        report.system["items"] = []  # type: ignore[index]
    with pytest.raises(TypeError):
        report.record["h_max"] = 1.0  # type: ignore[index]



def _properties(schema: dict[str, Any]) -> set[str]:
    return set(schema["properties"]) - {"schema_version"}


#: Each closed record of :mod:`stepsafe.api.schemas`, the report type it describes, and
#: that type's fields that are not in its JSON.
CLOSED = [
    ("LINEAR_ADVICE", reports.AdviceReport, {"advice", "keys"}),
    ("CHECK_ENTRY", reports.CheckReport, {"result", "keys"}),
    ("IMPULSE_MODES", md_reports.ImpulseModesReport, {"labels"}),
    ("RESPA", md_reports.ImpulseReport, {"method", "label", "ratio"}),
    ("IMPULSE_REGION", md_reports.ImpulseReport, {"method", "label"}),
    ("COMPARE", reports.CompareReport, set()),
    ("HMC", hmc_reports.HmcReport, {"beta_range"}),
    ("HMC_TARGET", TargetReport, {"trajectory", "spread", "laplace"}),
    ("DESIGN", hmc_reports.DesignReport, set()),
    ("ERROR", reports.ErrorTable, {"z", "phase", "energy", "overflow", "kernel_energy"}),
    ("MEASURE_RUNS", measure_reports.MeasureReport, set()),
    ("REFINEMENT", measure_reports.Refinement, set()),
    ("ENSEMBLE", measure_reports.EnsembleReport, {"states"}),
]


@pytest.mark.parametrize("name, owner, not_in_json", CLOSED, ids=[c[0] for c in CLOSED])
def test_closed_schema_records_name_exactly_the_keys_of_their_report(name, owner,
                                                                     not_in_json):
    """The hand-written JSON Schema of a command's record and its report type agree: each
    key the schema states is a declared field, property or constant of the type (under
    ``JSON_NAMES``), and each field of the type (but those not in its JSON) is a key the
    schema states. A field added without its schema, or a schema key with no attribute,
    fails here."""
    from stepsafe.api import schemas

    schema = getattr(schemas, name)
    if "anyOf" in schema:
        schema = schema["anyOf"][0]
    if "properties" not in schema:  # a dict of properties (MEASURE_RUNS)
        schema = {"properties": schema}
    else:
        assert schema.get("additionalProperties") is False, f"{name} is not closed"
    keys = _properties(schema)
    for key in keys:
        attribute = json_attribute(owner, key).split(".")[0]
        assert _declared(owner, attribute), f"{name}.{key}: no attribute {attribute!r}"
    renamed = {attribute: key for key, attribute in getattr(owner, "JSON_NAMES", {}).items()}
    fields = {f.name for f in dataclasses.fields(owner)} - not_in_json
    assert {renamed.get(f, f) for f in fields} <= keys, name

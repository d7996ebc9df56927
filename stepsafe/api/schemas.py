"""The JSON Schema (draft 2020-12) of each command's ``--json`` output (``stepsafe schema
output COMMAND``), which is also the shape of the matching ``to_dict()``.

Every record carries ``schema_version`` (:data:`~stepsafe.core.records.SCHEMA_VERSION`),
its first key. A top-level record whose keys the code writes out one by one is closed
(``additionalProperties: false``): a key added without its schema fails the tests that
validate each command's real output. Records assembled from a mapping (a method's
coefficients, a region's models, a system's items) state the keys every record has and
leave the rest open. A number that can be absent (no safe step, no boundary within zmax,
a non-finite value) is ``null``, never NaN or infinity.
"""

from __future__ import annotations

from typing import Any

from stepsafe.core.records import SCHEMA_VERSION
from stepsafe.exceptions import StepsafeError

DRAFT = "https://json-schema.org/draft/2020-12/schema"

NUM: dict[str, Any] = {"type": "number"}
NUM_OR_NULL: dict[str, Any] = {"type": ["number", "null"]}
INT: dict[str, Any] = {"type": "integer"}
INT_OR_NULL: dict[str, Any] = {"type": ["integer", "null"]}
STR: dict[str, Any] = {"type": "string"}
STR_OR_NULL: dict[str, Any] = {"type": ["string", "null"]}
BOOL: dict[str, Any] = {"type": "boolean"}
BOOL_OR_NULL: dict[str, Any] = {"type": ["boolean", "null"]}
OBJECT: dict[str, Any] = {"type": "object"}
OBJECT_OR_NULL: dict[str, Any] = {"type": ["object", "null"]}
ANY: dict[str, Any] = {}
VERSION: dict[str, Any] = {"const": SCHEMA_VERSION}
#: Open intervals of steps (or of z), ``[lo, hi]``; hi null: unbounded within the horizon.
INTERVALS: dict[str, Any] = {"type": "array", "items": {
    "type": "array", "items": NUM_OR_NULL, "minItems": 2, "maxItems": 2}}


def array(items: dict[str, Any]) -> dict[str, Any]:
    return {"type": "array", "items": items}


def record(required: dict[str, Any], optional: dict[str, Any] | None = None, *,
           closed: bool = True) -> dict[str, Any]:
    """An object with the ``required`` keys (and maybe the ``optional`` ones); ``closed``:
    no other key."""
    properties = {**required, **(optional or {})}
    out: dict[str, Any] = {"type": "object", "required": list(required),
                           "properties": properties}
    if closed:
        out["additionalProperties"] = False
    return out


def top(required: dict[str, Any], optional: dict[str, Any] | None = None, *,
        closed: bool = True) -> dict[str, Any]:
    """A command's record: ``schema_version`` first, then ``required``."""
    return record({"schema_version": VERSION, **required}, optional, closed=closed)


NONLINEAR = array(record({"resonance": STR}, closed=False))

METHOD_ROW = top({"name": STR, "kind": STR, "order": {"type": ["integer", "string"]},
                  "stages": {"type": ["integer", "string"]},
                  "evaluations": {"type": ["integer", "string", "null"]},
                  "force_gradients": INT, "symplectic": BOOL, "title": STR,
                  "aliases": array(STR)}, closed=False)

SHOW = top({"method": STR, "title": STR, "kind": STR, "order": INT_OR_NULL,
            "stages": INT_OR_NULL, "evaluations": INT_OR_NULL, "symplectic": BOOL,
            "source": STR, "coefficients": OBJECT},
           {"note": STR, "harmonic_sampling": STR_OR_NULL}, closed=False)

#: What the verdict on a Langevin splitting means (its mean map's stability) and, at a
#: step, how it samples the fastest vibration.
STOCHASTIC = record({"letters": STR, "friction": NUM, "kT": NUM, "stability": STR,
                     "sampling": OBJECT_OR_NULL})

MODEL_REGION = record({"first_boundary": NUM_OR_NULL, "intervals": INTERVALS,
                       "islands": array(ANY), "resonances": array(ANY), "poles": array(ANY),
                       "zmax": NUM, "symplectic": BOOL, "criterion": STR},
                      {"nonlinear_resonances": NONLINEAR,
                       "structure_first_boundary": NUM_OR_NULL}, closed=False)

LINEAR_REGION = top({"method": STR, "title": STR, "kind": STR, "stages": INT_OR_NULL,
                     "order": INT_OR_NULL, "symplectic": BOOL,
                     "models": {"type": "object", "additionalProperties": {"anyOf": [
                         MODEL_REGION, record({"not_analysed": STR})]}},
                     "criterion": STR}, {"verify": OBJECT})

IMPULSE = {"method": STR, "substeps": INT, "fast": NUM, "slow": NUM, "beta": NUM,
           "criterion": STR, "h_max": NUM_OR_NULL, "safe_h": INTERVALS,
           "bands": array(record({"lo": NUM, "hi": NUM_OR_NULL, "kind": STR}, closed=False)),
           "horizon": NUM_OR_NULL, "step": NUM_OR_NULL, "safe": BOOL_OR_NULL,
           "reason": STR_OR_NULL, "time_unit": STR_OR_NULL, "nonlinear_resonances": NONLINEAR}

RESPA = top(IMPULSE)

IMPULSE_REGION = top({**IMPULSE, "ratio": NUM, "units": STR})

IMPULSE_MODES = top({"method": STR, "kind": {"const": "impulse"}, "substeps": INT,
                     "criterion": STR, "time_unit": STR_OR_NULL, "scene": STR_OR_NULL,
                     "h_max": NUM_OR_NULL, "safe_h": INTERVALS, "horizon": NUM_OR_NULL,
                     "limiting_mode": ANY, "step": NUM_OR_NULL, "safe": BOOL_OR_NULL,
                     "failures": array(OBJECT), "analysis": ANY,
                     "modes": array(record({"label": STR_OR_NULL}, closed=False))})

FAILURE = record({"model": STR, "z": NUM_OR_NULL, "reason": STR}, closed=False)

#: The analysis at temperature (:mod:`stepsafe.api.thermal`): the request, the criterion of
#: the method's interval z* its limits rest on, and per minimum of the system its record
#: (frequencies, scans, drift).
THERMAL_REQUEST = {"kT": NUM, "criterion": {"enum": ["structure", "stability"]},
                   "temperature": NUM_OR_NULL, "energy_unit": STR_OR_NULL,
                   "run": record({"length": NUM_OR_NULL, "steps": NUM_OR_NULL}),
                   "max_drift": NUM_OR_NULL, "seed": INT, "harmonic": BOOL,
                   "minima": array(record({"at": STR}, closed=False))}

THERMAL_ADVICE = record({**THERMAL_REQUEST, "h_max": NUM_OR_NULL, "h_max_0K": NUM_OR_NULL,
                         "limited_by": STR, "confirmed": BOOL},
                        {"follow_steps": INT}, closed=False)

THERMAL_CHECK = record({**THERMAL_REQUEST, "safe": BOOL, "reasons": array(STR)},
                       {"follow_steps": INT}, closed=False)

#: A processed method's processor forces: once at the start and at each output.
PROCESSOR = record({"start": INT, "per_output": INT})

#: ``advise --json`` for a method that is not impulse: the fields of
#: :class:`~stepsafe.api.reports.AdviceReport`, the optional ones where they apply.
LINEAR_ADVICE = top({"method": STR, "margin": NUM, "h_max": NUM_OR_NULL,
                     "h_max_limited_by": STR_OR_NULL, "safe_h": INTERVALS,
                     "criterion": STR, "time_unit": STR_OR_NULL},
                    {"horizon": NUM_OR_NULL, "limiting": OBJECT_OR_NULL, "models": OBJECT,
                     "nonlinear_resonances": NONLINEAR, "fixed_point_limit": NUM_OR_NULL,
                     "other_criterion": OBJECT, "undecided_h": INTERVALS,
                     "stochastic": STOCHASTIC, "system": OBJECT, "thermal": THERMAL_ADVICE,
                     "zero_kelvin": record({"h_max": NUM_OR_NULL,
                                            "h_max_limited_by": STR_OR_NULL,
                                            "safe_h": INTERVALS}),
                     "accuracy": array(OBJECT), "h": NUM_OR_NULL, "bound_by": STR,
                     "evaluations": NUM_OR_NULL, "solver_iterations": NUM_OR_NULL,
                     "cost_per_unit_time": NUM_OR_NULL, "processor_evaluations": PROCESSOR,
                     "verify": OBJECT})

#: One entry of ``check --json``: the fields of :class:`~stepsafe.api.reports.CheckReport`
#: (the optional ones where they apply), a file that could not be checked, or an impulse
#: method's check.
CHECK_ENTRY = {"anyOf": [
    record({"method": STR, "h": NUM, "margin": NUM, "safe": BOOL,
            "in_primary_interval": BOOL, "modes": INT, "failing": INT,
            "failures": array(FAILURE), "h_max": NUM_OR_NULL, "safe_h": INTERVALS,
            "criterion": STR, "scene": STR_OR_NULL, "time_unit": STR_OR_NULL},
           {"h_max_limited_by": STR_OR_NULL, "other_criterion": OBJECT,
            "stochastic": STOCHASTIC, "solver_failure": STR, "system": OBJECT,
            "search_failure": STR, "thermal": THERMAL_CHECK, "thermal_failure": STR,
            # an MD engine's system checked with runs: (stepsafe.systems.md.system)
            "engine_failure": STR,
            "engine_runs": record({"integrator": STR, "temperature": NUM,
                                   "verdict": STR, "seeds": array(INT),
                                   "summary": STR}, closed=False),
            "verify": OBJECT}),
    record({"scene": STR_OR_NULL, "safe": {"const": None}, "error": STR,
            "where": STR_OR_NULL}),
    record({"method": STR, "kind": {"const": "impulse"}, "safe": BOOL_OR_NULL},
           closed=False)]}

CHECK = top({"safe": BOOL, "checks": {**array(CHECK_ENTRY), "minItems": 1}})

ERROR = top({"method": STR, "model": STR, "phase_error": STR,
             "rows": array(record({"z": NUM, "phase_error": NUM_OR_NULL,
                                   "energy_error": NUM_OR_NULL, "overflow": BOOL},
                                  {"kernel_energy_error": NUM_OR_NULL}))})

#: ``compare --measure``: each method's measured cost beside the predicted one.
MEASURED_RANKING = record({
    "scene": STR, "time": NUM, "tolerance": NUM, "first": STR,
    "methods": array(record({"method": STR, "predicted_cost": NUM,
                             "measured_cost": NUM_OR_NULL, "predicted_ratio": NUM,
                             "measured_ratio": NUM_OR_NULL})),
    "measured_order": array(STR)})

COMPARE = top({"modes": OBJECT, "tolerances": OBJECT, "margin": NUM,
               "time_unit": STR_OR_NULL, "solver": STR, "jacobian_cost": NUM,
               "criterion": STR, "cost_unit": STR,
               "methods": array(record({"method": STR, "implicit": BOOL,
                                        "h_max": NUM_OR_NULL, "h": NUM_OR_NULL,
                                        "evaluations": NUM, "cost": NUM_OR_NULL,
                                        "rank": INT_OR_NULL}, closed=False))},
              {"measured": MEASURED_RANKING})

HMC_ROW = record({"method": STR, "evaluations": NUM, "symmetric": BOOL,
                  "stability_h": NUM_OR_NULL, "structure_h": NUM_OR_NULL,
                  "resonance_h": array(NUM), "h_target": NUM_OR_NULL, "steps": INT_OR_NULL,
                  "acceptance": NUM_OR_NULL, "expected_error": NUM_OR_NULL,
                  "gradients_per_proposal": NUM_OR_NULL,
                  "gradients_per_accepted": NUM_OR_NULL, "gradients_per_time": NUM_OR_NULL,
                  "rank": INT_OR_NULL, "at_step": OBJECT_OR_NULL, "stalls": array(OBJECT),
                  "notes": array(STR), "curve": array(ANY)}, closed=False)

HMC = top({"target_accept": NUM, "steps": INT_OR_NULL, "length": NUM_OR_NULL,
           "target_for_every_length": BOOL,
           "jitter": NUM, "allow_unstable_jitter": BOOL, "criterion": STR, "modes": INT,
           "beta_min": NUM, "beta_max": NUM, "time_unit": STR_OR_NULL, "approximate": BOOL,
           "cost_unit": STR, "ranked_by": STR, "rounding_gaps": STR,
           "methods": array(HMC_ROW)})

#: A target that is not Gaussian (a potential): figures estimated on draws.
HMC_TARGET_ROW = record({"method": STR, "evaluations": INT_OR_NULL, "symmetric": BOOL,
                         "z_star": NUM_OR_NULL, "stability_h": NUM_OR_NULL,
                         "h_target": NUM_OR_NULL, "capped_by": STR_OR_NULL,
                         "steps": INT_OR_NULL,
                         "acceptance": NUM_OR_NULL, "acceptance_se": NUM_OR_NULL,
                         "divergent": NUM_OR_NULL, "expected_error": NUM_OR_NULL,
                         "gradients_per_accepted": NUM_OR_NULL,
                         "gradients_per_time": NUM_OR_NULL, "rank": INT_OR_NULL,
                         "laplace_acceptance": NUM_OR_NULL, "laplace_rank": INT_OR_NULL,
                         "divergence_onset": OBJECT_OR_NULL, "at_step": OBJECT_OR_NULL,
                         "notes": array(STR)}, closed=False)

HMC_TARGET = top({"target_accept": NUM, "steps": INT_OR_NULL, "length": NUM_OR_NULL,
                  "jitter": NUM, "allow_unstable_jitter": BOOL, "dimension": INT, "seed": INT,
                  "cost_unit": STR, "ranked_by": STR, "ranking_differs": array(OBJECT),
                  "verified": BOOL, "unverified": STR_OR_NULL,
                  "mode_search": OBJECT_OR_NULL,
                  "draws": record({"source": STR, "chains": INT, "per_chain": INT},
                                  closed=False),
                  "frequencies": record({"how": STR, "draws": INT, "omega_max": NUM,
                                         "omega_max_quantiles": OBJECT}, closed=False),
                  "laplace": OBJECT_OR_NULL, "methods": array(HMC_TARGET_ROW),
                  "notes": array(STR)})

DESIGN = top({"name": STR, "stages": INT, "params": {"type": "object",
                                                     "additionalProperties": NUM},
              "step": NUM, "modes": INT, "binned": BOOL, "time_unit": STR_OR_NULL,
              "objective": STR, "steps": INT_OR_NULL, "length": NUM_OR_NULL, "jitter": NUM,
              "trajectory": STR_OR_NULL, "aia_params": OBJECT_OR_NULL,
              "method_file": STR, "rounding_gaps": STR,
              "comparison": array(record({"method": STR, "evaluations": NUM,
                                          "h": NUM_OR_NULL, "resonance_h": array(NUM)},
                                         closed=False))})

MEASURE_ROW = record({"h": NUM, "steps": INT, "time": NUM, "status": STR,
                      "energy_error": NUM_OR_NULL, "energy_drift": NUM_OR_NULL,
                      "trajectory_error": NUM_OR_NULL, "evaluations_per_time": NUM_OR_NULL,
                      "iterations_per_step": NUM_OR_NULL,
                      "predicted_energy_error": NUM_OR_NULL,
                      "predicted_trajectory_error": NUM_OR_NULL,
                      "energy_ratio": NUM_OR_NULL, "trajectory_ratio": NUM_OR_NULL,
                      "jacobians_per_time": NUM_OR_NULL, "gradients_per_time": NUM_OR_NULL,
                      "reference_error": NUM_OR_NULL, "below_reference": BOOL,
                      "energy_r2": NUM_OR_NULL, "energy_behaviour": STR_OR_NULL,
                      "invariants": array(record({"name": STR, "spread": NUM,
                                                  "drift": NUM_OR_NULL, "r2": NUM_OR_NULL,
                                                  "behaviour": STR_OR_NULL})),
                      "seconds_per_time": NUM_OR_NULL})

MEASURE_RUNS = {"method": STR, "system": STR, "initial": array(NUM), "energy": NUM_OR_NULL,
                "beta": NUM_OR_NULL, "reference": STR, "time_unit": STR_OR_NULL,
                "rows": array(MEASURE_ROW)}

REFINEMENT = top({"quantity": STR, "tol": NUM, "h": NUM_OR_NULL, "error": NUM_OR_NULL,
                  "below_reference": BOOL, "predicted_h": NUM_OR_NULL,
                  "h_safe": NUM_OR_NULL, "limited_by": STR,
                  "runs": record(MEASURE_RUNS)})

ENSEMBLE = top({"method": STR, "system": STR, "ensemble": INT, "seed": INT, "draw": STR,
                "energy": NUM_OR_NULL, "kT": NUM_OR_NULL, "centre": array(NUM),
                "centre_energy": NUM, "time_unit": STR_OR_NULL,
                "rows": array(record({"h": NUM, "steps": INT, "time": NUM,
                                      "median": NUM_OR_NULL, "q90": NUM_OR_NULL,
                                      "q99": NUM_OR_NULL, "max": NUM_OR_NULL,
                                      "unstable": INT}))})

#: The output of each command that takes ``--json``.
OUTPUTS: dict[str, dict[str, Any]] = {
    "methods": array(METHOD_ROW),
    "show": SHOW,
    "region": {"oneOf": [LINEAR_REGION, IMPULSE_REGION]},
    "advise": {"oneOf": [LINEAR_ADVICE, IMPULSE_MODES]},
    "check": CHECK,
    "error": ERROR,
    "compare": COMPARE,
    "hmc": {"oneOf": [HMC, HMC_TARGET]},
    "design": DESIGN,
    "respa": RESPA,
    "measure": {"oneOf": [top(MEASURE_RUNS), REFINEMENT, ENSEMBLE]},
}


def output_schema(command: str) -> dict[str, Any]:
    """The JSON Schema of ``stepsafe COMMAND --json`` (and of the matching ``to_dict()``).

    Parameters
    ----------
    command : str
        A command that takes ``--json``: one of :data:`OUTPUTS`.

    Returns
    -------
    dict
        A JSON Schema (draft 2020-12) document.
    """
    if command not in OUTPUTS:
        raise StepsafeError(f"no JSON output schema for {command!r}; the commands with "
                            f"--json are {', '.join(OUTPUTS)}")
    return {"$schema": DRAFT, "title": f"stepsafe {command} --json",
            "description": f"schema_version {SCHEMA_VERSION}", **OUTPUTS[command]}

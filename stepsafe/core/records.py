"""Core results as JSON-ready records: the exact shape of ``--json`` and of ``to_dict()``.

Floats keep full precision; a non-finite value (no limit, the horizon at infinity) is
``None``. Nothing here prints.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from stepsafe.core.models import ELLIPTIC
from stepsafe.core.regions import Interval, Point, Region
from stepsafe.lazy import lazy_module
from stepsafe.methods.residuals import residuals

if TYPE_CHECKING:
    from stepsafe.methods import langevin
else:  # Langevin splittings only
    langevin = lazy_module("stepsafe.methods.langevin")

#: The version of the shape of every ``--json`` record and ``to_dict()``: each record
#: carries it as ``schema_version`` (first key); ``stepsafe schema output COMMAND`` prints
#: the JSON Schema of that version. A key removed or changed in meaning raises it.
SCHEMA_VERSION = 1


def versioned(record: Mapping[str, Any]) -> dict[str, Any]:
    """``record`` with ``schema_version`` as its first key (once)."""
    return {"schema_version": SCHEMA_VERSION,
            **{k: v for k, v in record.items() if k != "schema_version"}}


def unversioned(record: Mapping[str, Any]) -> dict[str, Any]:
    """``record`` without ``schema_version`` (a record nested in another)."""
    return {k: v for k, v in record.items() if k != "schema_version"}


def json_ready(data: Any) -> Any:
    """``data`` with every non-finite float replaced by None (JSON has no inf or NaN;
    null is the records' 'no limit' / 'not defined')."""
    if isinstance(data, float):
        return data if math.isfinite(data) else None
    if isinstance(data, dict):
        return {k: json_ready(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [json_ready(v) for v in data]
    if hasattr(data, "item") and not isinstance(data, (str, bytes)):  # numpy scalars
        return json_ready(data.item())
    return data


def _num(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def _interval(iv: Interval) -> list[float | None]:
    return [_num(iv.lo), _num(iv.hi)]


def _point(p: Point) -> dict[str, Any]:
    return {"z": float(p.z), "kind": p.kind, "detail": p.detail,
            "uncertainty": _num(p.uncertainty)}


def region_data(region: Region) -> dict[str, Any]:
    """JSON-ready description of one model's region."""
    fb = region.first_boundary_point
    data: dict[str, Any] = {
        "first_boundary": _num(region.first_boundary),
        "first_boundary_kind": fb.kind if fb else None,
        "first_boundary_detail": fb.detail if fb else None,
        "first_boundary_uncertainty": _num(fb.uncertainty) if fb else None,
        "intervals": [_interval(iv) for iv in region.intervals],
        "islands": [{"lo": float(iv.lo), "hi": _num(iv.hi),
                     "orientation": ("any" if region.criterion == "stability" else
                                     "same" if same else "reversed")}
                    for iv, same in region.islands],
        "resonances": [_point(p) for p in region.resonances],
        "poles": [float(p.z) for p in region.poles],
        "zmax": float(region.zmax),
        "resolution": float(region.resolution),
        "symplectic": region.symplectic,
        "criterion": region.criterion,
    }
    if ELLIPTIC[region.model] and region.symplectic:
        data["stability_limit"] = _num(region.stability_limit)
    if region.classical is not None:
        data["classical_intervals"] = [_interval(iv) for iv in region.classical]
    if region.notes:
        data["notes"] = list(region.notes)
    return data


def method_data(method, entry) -> dict[str, Any]:
    """Identity and coefficient checks of a method."""
    res = residuals(method)
    step = method.splitting() if method.force_gradient else None
    extra = {"force_gradients": method.gradient_evaluations,
             "gradient_form": "displaced-force" if step.displaced else "hessian"} if step else {}
    return {
        "method": entry.name,
        "title": entry.title,
        "kind": method.kind,
        "order": method.order,
        "stages": method.stages,
        "evaluations": entry.evaluations,
        **extra,
        "symplectic": res.symplectic,
        "symplectic_for_separable": res.symplectic_for_separable,
        "symmetric": method.symmetric(),
        "explicit": method.explicit,
        "residuals": {
            "symplecticity": res.symplectic_separable,
            "symplecticity_allowed": res.symplectic_tolerance,
            "weights_equal": res.weights_equal,
            "weights_equal_allowed": res.weights_tolerance,
            "consistency": res.consistency,
            **({"row_sums": res.row_sums} if res.row_sums is not None else {}),
        } if method.hamiltonian else {"consistency": res.consistency},
        "source": entry.source,
        **processor_data(method),
        **stochastic_data(method),
    }


def stochastic_data(method) -> dict[str, Any]:
    """For a method that is not Hamiltonian (a Langevin splitting): what its analyses mean
    (``note``) and, where known, its stationary sampling of the harmonic oscillator in
    closed form (``harmonic_sampling``, :data:`stepsafe.methods.langevin.CLOSED_FORM_TEXT`)."""
    if method.hamiltonian:
        return {}
    letters = method.coefficients().get("letters")
    return {"note": method.analysis_note,
            "harmonic_sampling": langevin.CLOSED_FORM_TEXT.get(letters)}


def processor_data(method) -> dict[str, Any]:
    """A processed method's one-off cost: ``{"processor_evaluations": {"start": n,
    "per_output": n}}`` (P once before the first step, P^-1 for each output); {} for any
    other method."""
    n = method.processor_evaluations
    if n is None:
        return {}
    return {"processor_evaluations": {"start": n, "per_output": n}}


def _limit(lim) -> dict[str, Any] | None:
    if lim is None:
        return None
    p = lim.first_boundary_point
    out = {"model": lim.model, "beta": lim.beta_max, "count": lim.count,
           "first_boundary": _num(lim.first_boundary),
           "first_boundary_kind": p.kind if p else None,
           "h_limit": _num(lim.h_limit)}
    if p is not None and p.kind == "nonlinear":
        out["resonance"] = p.detail.split()[0]  # "n:m", the resonance that ends it
    return out


def nonlinear_data(found, beta: float | None = None, margin: float = 1.0
                   ) -> list[dict[str, Any]]:
    """The nonlinear resonances (:mod:`stepsafe.core.resonances`) as records; with the
    frequency ``beta``, each with ``h``: the step of the resonance less its uncertainty,
    times the margin."""
    out = []
    for r in found:
        item = {"resonance": r.name, "n": r.n, "m": r.m, "z": r.z,
                "uncertainty": _num(r.uncertainty)}
        if beta:  # (Python floats: a step beyond every float is inf, recorded as None)
            item["h"] = _num(margin * max(r.z - r.uncertainty, 0.0) / float(beta))
        out.append(item)
    return out


def limited_by_resonance(limited_by: str, limiting: Mapping[str, Any] | None) -> str:
    """``resonance n:m`` for a ``boundary`` that is the nonlinear resonance n:m of the
    limiting mode (see :func:`advice_data`), else ``limited_by`` as it is."""
    if limited_by == "boundary" and limiting and limiting.get("resonance"):
        return f"resonance {limiting['resonance']}"
    return limited_by


def advice_data(adv) -> dict[str, Any]:
    """JSON-ready advice: h_max, the safe h intervals, the limiting frequency, per model.

    ``h_max_limited_by`` is ``boundary`` when a structure boundary (root, pole, resonance
    M = +-I) ends the safe interval from 0, ``resonance n:m`` when the nonlinear
    resonance n theta = 2 pi m asked for (``resonance_order``) ends it first, ``horizon``
    when nothing was found below the analysed range (then ``h_max`` is the horizon, not a
    safety limit), ``none`` when no step is safe."""
    safe = adv.safe_h
    limited_by = ("none" if not safe or safe[0][0] != 0.0 else
                  "horizon" if adv.h_max_is_horizon or safe[0][1] is None else "boundary")
    limiting = _limit(adv.limiting) if limited_by == "boundary" else None
    return {
        "method": adv.method,
        "margin": adv.margin,
        "h_max": _num(adv.h_max) if adv.h_max is not None else None,
        "h_max_limited_by": limited_by_resonance(limited_by, limiting),
        "safe_h": [[float(lo), _num(hi)] for lo, hi in adv.safe_h],
        "limiting": limiting,
        "models": {lim.model: _limit(lim) for lim in adv.models},
        "horizon": _num(adv.horizon),
        "criterion": adv.criterion,
    }


def label_limits(data: dict[str, Any], betas: Mapping[str, Any],
                 labels: Mapping[str, Sequence[str | None]]) -> None:
    """Add to advice ``data`` (in place) the ``label`` of each model's largest frequency
    (the one that sets its limit, the first such mode) and of the limiting one, when the
    scene or modes file names it."""
    import numpy as np

    def name(model: str) -> str | None:
        values, names = betas.get(model), labels.get(model, ())
        if values is None or not len(values):
            return None
        index = int(np.argmax(np.asarray(values)))
        return names[index] if index < len(names) else None

    for model, entry in data["models"].items():
        if name(model):
            entry["label"] = name(model)
    limiting = data.get("limiting")
    if limiting and limiting.get("model") in data["models"] and name(limiting["model"]):
        limiting["label"] = name(limiting["model"])


def check_data(result, labels: Mapping[str, Sequence[str | None]] | None = None
               ) -> dict[str, Any]:
    """JSON-ready check; ``labels[model][i]`` names mode i of that model (scene ``label:``)."""

    def failure(f) -> dict[str, Any]:
        names = (labels or {}).get(f.model, ())
        label = names[f.index] if 0 <= f.index < len(names) else None
        return {"model": f.model, "beta": f.beta, "z": f.z, "reason": f.reason,
                "largest_safe_h": _num(f.h_limit), **({"label": label} if label else {})}

    return {
        "method": result.method,
        "h": result.h,
        "margin": result.margin,
        "safe": result.safe,
        "in_primary_interval": result.in_primary,
        "modes": result.n_modes,
        "failing": result.n_failing,
        "failures": [failure(f) for f in result.failures],
        "h_max": _num(result.advice.h_max) if result.advice.h_max is not None else None,
        "h_max_limited_by": advice_data(result.advice)["h_max_limited_by"],
        "safe_h": [[float(lo), _num(hi)] for lo, hi in result.advice.safe_h],
        "criterion": result.advice.criterion,
    }


def tradeoff_data(res) -> dict[str, Any]:
    """advice_data plus the tolerance limits, the usable step and its cost."""
    data = advice_data(res.advice)
    data["accuracy"] = [{"model": lim.model, "kind": lim.kind, "tolerance": lim.tol,
                         "beta": lim.beta, "z": _num(lim.z), "h": _num(lim.h),
                         "limited_by": lim.limited_by} for lim in res.limits]
    data["h"] = _num(res.h)
    data["bound_by"] = res.bound_by
    data["evaluations"] = res.evaluations
    data["solver_iterations"] = res.iterations
    data["cost_per_unit_time"] = _num(res.cost)
    if res.processor_evaluations is not None:
        data["processor_evaluations"] = {"start": res.processor_evaluations,
                                         "per_output": res.processor_evaluations}
    return data


def compare_row(res, explicit: bool) -> dict[str, Any]:
    """One method's row of ``compare --json`` from its :class:`~stepsafe.core.tradeoff.Tradeoff`:
    the oscillator's first boundary, the safe and accurate steps, the step to use and its cost
    (``rank`` is set by the caller once every row is known)."""
    first = next((lim for lim in res.advice.models if lim.model == "oscillator"),
                 res.advice.models[0])
    h_tol = [lim.h for lim in res.limits if lim.limited_by != "beyond-float"]
    return {
        "method": res.method,
        "implicit": not explicit,
        "first_boundary": _num(first.first_boundary),
        "h_max": _num(res.advice.h_max),
        "h_tol": (None if not h_tol else
                  (0.0 if any(h is None for h in h_tol) else _num(min(h_tol)))),
        "tolerance_status": sorted({lim.limited_by for lim in res.limits}),
        "h": _num(res.h),
        "bound_by": res.bound_by,
        "evaluations": res.evaluations,
        "solver_iterations": res.iterations,
        "solver": res.solver,
        "jacobians": res.jacobians,
        "cost": _num(res.cost),
        "rank": None,
        **({} if res.processor_evaluations is None else {"processor_evaluations": {
            "start": res.processor_evaluations, "per_output": res.processor_evaluations}}),
    }


def coefficients(method) -> dict[str, Any]:
    """The coefficient arrays of a method (``show --json``; each kind gives its own,
    :meth:`~stepsafe.methods.protocol.MethodKind.coefficients`)."""
    return method.coefficients()

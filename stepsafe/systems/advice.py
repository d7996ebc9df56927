"""Advice and checks for whole systems: decoupled modes through :mod:`stepsafe.core.advice`,
coupled pieces through the one-step matrix of :mod:`stepsafe.systems.linear`; the answer is the
intersection (only the primary interval of a coupled piece is used)."""

from __future__ import annotations

import copy
from typing import Any

from stepsafe.core.advice import advise, check_step, validate_margin
from stepsafe.core.records import advice_data, check_data, limited_by_resonance
from stepsafe.core.threads import blas_threads_for
from stepsafe.exceptions import StepsafeError, positive_finite
from stepsafe.methods.tableaux import Method
from stepsafe.systems.coupled import CoupledSystem
from stepsafe.systems.loader import SystemReport


def _limit_items(report: SystemReport, regions, margin: float) -> list[dict[str, Any]]:
    """Each item with the h limit it sets: a mode or 1-dof equilibrium through its model,
    an n-dof equilibrium through all its frequencies (``oscillator``) and rates (the
    barrier or saddle model its Hessian was analysed with)."""
    out = []
    for item in report.items:
        item = dict(item)
        model, beta = item.get("model"), item.get("beta")
        if model in regions and beta:
            z_star = regions[model].first_boundary
            item["h_limit"] = None if z_star is None else margin * z_star / beta
        elif "frequencies" in item and model and model != "coupled":
            limits = []
            for name in model.split(","):
                values = item["frequencies"] if name == "oscillator" else item["rates"]
                z_star = regions[name].first_boundary if name in regions else None
                limits += [margin * z_star / v for v in values if z_star is not None and v]
            item["h_limit"] = min(limits) if limits else None
        out.append(item)
    return out


def _limiting_item(items: list[dict[str, Any]]) -> int | None:
    """The index of the item with the smallest h limit (None if none sets one)."""
    limits = [(item["h_limit"], i) for i, item in enumerate(items)
              if item.get("h_limit") is not None]
    return min(limits)[1] if limits else None


def _coupled_criterion(report: SystemReport, criterion: str) -> None:
    if report.coupled and criterion != "structure":
        raise StepsafeError(f"--criterion {criterion} is not available for a system whose "
                            "modes couple (the coupled analysis keeps type and orientation): "
                            "use --criterion structure")


def _coupled_resonances(report: SystemReport, resonance_order: int | None) -> None:
    if report.coupled and resonance_order is not None:
        raise StepsafeError("--resonance-order is not available for a system whose modes "
                            "couple (the coupled analysis has no per-mode rotation angle to "
                            "test for n theta = 2 pi m): give the frequencies as modes")


def system_advice(method: Method, report: SystemReport, margin: float = 1.0,
                  zmax: float = 10.0, name: str | None = None,
                  criterion: str = "structure", resonance_order: int | None = None
                  ) -> dict[str, Any]:
    """JSON-ready advice for a system (see advice_data for the common fields); with
    ``resonance_order`` N its vibrations also keep below their first nonlinear resonance
    of order at most N (decoupled modes only)."""
    margin = validate_margin(margin)
    _coupled_criterion(report, criterion)
    _coupled_resonances(report, resonance_order)
    if report.modes is not None:
        adv = advise(method, report.modes, margin, zmax, name, resonance_order=resonance_order,
                     criterion=criterion)
        data = advice_data(adv)
        regions = adv.regions
    else:
        data = {"method": name or method.name, "margin": margin, "h_max": None,
                "safe_h": [[0.0, None]], "limiting": None, "models": {}, "horizon": None,
                "criterion": criterion}
        regions = {}
    for result, _ in report.coupled:
        cap = margin * result.h_max
        data["safe_h"] = _cap(data["safe_h"], cap)
        horizon = data["horizon"]
        data["horizon"] = (margin * result.horizon if horizon is None
                           else min(horizon, margin * result.horizon))
    if report.primary_only:
        data["safe_h"] = data["safe_h"][:1] if data["safe_h"] and data["safe_h"][0][0] == 0.0 \
            else []
    safe = data["safe_h"]
    data["h_max"] = safe[0][1] if safe and safe[0][0] == 0.0 else 0.0
    if report.coupled and (data["limiting"] is None or (
            data["h_max"] is not None and data["limiting"].get("h_limit") is not None
            and data["h_max"] < data["limiting"]["h_limit"])):
        data["limiting"] = {"model": "coupled", "beta": None, "h_limit": data["h_max"]}
    data["h_max_limited_by"] = limited_by_resonance(_limited_by(data), data["limiting"])
    # steps float64 could not decide in a coupled analysis (neither certified nor lost)
    data["undecided_h"] = [[margin * r.h_max, margin * r.undecided_to]
                           for r, _ in report.coupled if r.undecided_to is not None]
    items = _limit_items(report, regions, margin)
    data["system"] = _system_record(report, items)
    return data


def _limited_by(data: dict[str, Any]) -> str:
    """What ends the safe interval from 0 (see :func:`stepsafe.core.records.advice_data`)."""
    safe, horizon = data["safe_h"], data["horizon"]
    if not safe or safe[0][0] != 0.0:
        return "none"
    top = safe[0][1]
    if top is None or (horizon is not None and top >= horizon * (1.0 - 1e-12)):
        return "horizon"
    return "boundary"


def _cap(safe: list, cap: float) -> list:
    out = []
    for lo, hi in safe:
        if lo >= cap:
            continue
        out.append([lo, cap if hi is None else min(hi, cap)])
    return out


def system_check(method: Method, report: SystemReport, h: float, margin: float = 1.0,
                 zmax: float = 10.0, name: str | None = None,
                 criterion: str = "structure", resonance_order: int | None = None,
                 require_complete_search: bool = False) -> dict[str, Any]:
    """JSON-ready check of step h for a system (see check_data for the common fields);
    ``resonance_order``: see :func:`system_advice`. With ``require_complete_search`` a
    Hamiltonian whose equilibrium search cannot vouch for completeness fails the check
    (``safe`` False, ``search_failure`` says why), whatever its modes."""
    margin = validate_margin(margin)
    h = positive_finite(h, "h")  # (the coupled analysis calls h <= 0 kept: no step at all)
    _coupled_criterion(report, criterion)
    _coupled_resonances(report, resonance_order)
    if report.modes is not None:
        result = check_step(method, report.modes, h, margin, zmax, name, resonance_order,
                            criterion)
        data = check_data(result)
        regions = result.advice.regions
    else:
        data = {"method": name or method.name, "h": float(h), "margin": margin, "safe": True,
                "in_primary_interval": True, "modes": 0, "failing": 0, "failures": [],
                "h_max": None, "safe_h": [[0.0, None]], "criterion": criterion}
        regions = {}
    for result, S in report.coupled:
        with blas_threads_for(S.shape[0]):
            system = CoupledSystem(method, S)
            ok = all(system.certified(step) for step in (h, h / margin))
        dof = S.shape[0] // 2  # analysed together: they keep their structure or not as one
        data["modes"] += dof
        cap = margin * result.h_max
        data["safe_h"] = _cap(data["safe_h"], cap)
        if not ok:
            data["failing"] += dof
            data["safe"] = False
            undecided = system.definite and any(
                not system.certified(step) and not system.certainly_lost(step)
                for step in (h, h / margin))
            data["failures"].append({
                "model": "coupled", "beta": None, "z": float(h),
                "reason": (f"float64 cannot decide whether the one-step matrix of the coupled "
                           f"{dof}-dof system keeps the eigen-structure of J S at this h (S "
                           "ill-conditioned for float64; see the note): not certified" if undecided
                           else f"the one-step matrix of the coupled {dof}-dof system does "
                           "not keep the eigen-structure of J S at this h"),
                "largest_safe_h": cap})
    if report.primary_only:
        data["safe_h"] = data["safe_h"][:1] if data["safe_h"] and data["safe_h"][0][0] == 0.0 \
            else []
        top = data["safe_h"][0][1] if data["safe_h"] else 0.0
        if data["safe"] and top is not None and h >= top:
            data["safe"] = False
            data["failing"] += 1
            data["failures"].append({
                "model": "system", "beta": None, "z": None,
                "reason": "beyond the safe interval from 0, and islands beyond it are not "
                          "analysed for this system (extreme eigenvalues only)",
                "largest_safe_h": top})
    safe = data["safe_h"]
    data["h_max"] = safe[0][1] if safe and safe[0][0] == 0.0 else 0.0
    # (h = h_max is safe only where h_max is a certified step, the coupled analysis's end)
    data["in_primary_interval"] = bool(data["safe"] and (data["h_max"] is None
                                                         or h <= data["h_max"]))
    if report.engine_check is not None and data["safe"]:
        runs = report.engine_check(name or method.name, h)
        runs["summary"] = engine_reason(runs)
        data["engine_runs"] = runs
        if runs["verdict"] != "stable":  # every mode may keep its structure, the run not
            data["safe"] = False
            data["in_primary_interval"] = False
            data["engine_failure"] = runs["summary"]
    items = _limit_items(report, regions, margin)
    data["system"] = _system_record(report, items)
    search = report.search
    if require_complete_search and search is not None and not search["complete"]:
        data["safe"] = False
        data["in_primary_interval"] = False
        data["search_failure"] = ("the equilibrium search cannot vouch that it found every "
                                  "equilibrium: " + "; ".join(search["gaps"]))
    return data


def engine_reason(runs: dict[str, Any]) -> str:
    """One line on the engine's runs (:func:`stepsafe.systems.md.system.engine_check`)."""
    head = (f"{runs['integrator']} in OpenMM at {runs['temperature']:g} K, "
            f"{len(runs['seeds'])} seeds of {runs['duration']:g} ps: {runs['verdict']}")
    blown = [r for r in runs["runs"] if r["blew_up"]]
    if blown:
        return head + " (" + "; ".join(
            f"seed {r['seed']} by step {r['step']}: {r['reason']}" if r["step"] is not None
            else f"seed {r['seed']}: {r['reason']}" for r in blown) + ")"
    if runs["drift"] is not None:
        error = "" if runs["drift_error"] is None else f" +- {runs['drift_error']:.1g}"
        return head + (f" (energy drift {runs['drift']:.2g}{error} kT/ps per degree of "
                       f"freedom, tolerance {runs['drift_tolerance']:g})")
    return head


def _system_record(report: SystemReport, items: list[dict[str, Any]]) -> dict[str, Any]:
    """``system`` of the JSON: the analysis, its items and notes, and for a Hamiltonian the
    equilibrium search (what it searched, whether it vouches for completeness)."""
    record: dict[str, Any] = {"analysis": report.analysis, "items": items,
                              "notes": report.notes, "limiting_item": _limiting_item(items)}
    if report.search is not None:
        record["search"] = copy.deepcopy(report.search)
    return record


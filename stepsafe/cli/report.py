"""Results as rich tables (for people) and JSON (for scripts).

The ``print_*`` functions render the records of :mod:`stepsafe.core.records` (the
``--json`` output) with rich, imported lazily, so the two outputs never disagree. JSON is
printed with :mod:`json`, never through rich, which would wrap long lines when stdout is
a pipe.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from stepsafe.core.records import json_ready, versioned
from stepsafe.text import printable


def print_json(data: Any, record: bool = True) -> None:
    """One JSON document; a non-finite number is null (see
    :func:`stepsafe.core.records.json_ready`). A ``record`` (a command's result, not a
    JSON Schema) carries ``schema_version`` first, as does each record of a list."""
    if record and isinstance(data, Mapping):
        data = versioned(data)
    elif record and isinstance(data, list):
        data = [versioned(x) if isinstance(x, Mapping) else x for x in data]
    import json  # (the text output of a command needs none of it)

    sys.stdout.write(json.dumps(json_ready(data), indent=2, allow_nan=False) + "\n")


def print_tsv(columns: Sequence[str], rows: Iterable[Mapping[str, Any]]) -> None:
    """A table as tab-separated values for scripts: a header line naming ``columns`` (the
    ``--json`` keys), then one line per row. Numbers at full precision (the shortest text
    that reads back as the same float), true/false, an empty field for null; tabs and line
    breaks inside text become spaces, control characters are made visible."""
    def cell(value: Any) -> str:
        if value is None:
            return ""
        if isinstance(value, bool):
            return "true" if value else "false"
        if isinstance(value, float):
            return repr(value)
        if isinstance(value, (list, tuple)):
            return ", ".join(cell(v) for v in value)
        text = str(value).replace("\t", " ").replace("\r", " ").replace("\n", " ")
        return printable(text)

    lines = ["\t".join(columns)]
    lines += ["\t".join(cell(row.get(c)) for c in columns) for row in rows]
    sys.stdout.write("\n".join(lines) + "\n")


def fmt(x: float | None, digits: int = 12) -> str:
    if x is None:
        return "zmax"
    return f"{x:.{digits}g}"


def fmt_exact(x: float) -> str:
    """The shortest decimal that reads back as ``x`` (a value the user gave, echoed as it
    is: 1.9999999999999998 is not shown as 2)."""
    text = repr(float(x))
    return text[:-2] if text.endswith(".0") else text


def fmt_below(x: float, digits: int = 12) -> str:
    """``x`` to ``digits`` significant digits, rounded towards zero and strictly below a
    positive ``x``: a step limit shown to the user is one the user may take (an ``h_max``
    printed rounded up would be outside the safe set)."""
    return _directed(x, digits, below=True)


def fmt_above(x: float, digits: int = 12) -> str:
    """``x`` rounded up, strictly above a positive ``x`` (lower ends of safe intervals)."""
    return _directed(x, digits, below=False)


def _directed(x: float, digits: int, below: bool) -> str:
    from decimal import ROUND_CEILING, ROUND_FLOOR, Decimal

    if not math.isfinite(x) or x == 0:
        return fmt(x, digits)
    rounding, outwards = (ROUND_FLOOR, -math.inf) if below else (ROUND_CEILING, math.inf)
    # strictly beyond x, also once read back as a float (1e-12 reads as 1e-12 itself): if
    # not, the float next to x is rounded instead (at most twice: a decimal rounded away
    # from x from that float reads back as it or beyond, even where the floats are coarser
    # than the digits, as for subnormal x)
    target = x
    while True:
        exact = Decimal(target)
        rounded = exact.quantize(Decimal(1).scaleb(exact.adjusted() - (digits - 1)),
                                 rounding=rounding)
        text = f"{rounded:.{digits}g}" if rounded else "0"  # exact: at most `digits` digits
        if (float(text) < x) if below else (float(text) > x):
            break
        target = math.nextafter(target, outwards)
    mantissa, e, exponent = text.partition("e")
    if "." in mantissa:  # no trailing zeros (they would suggest more digits than shown)
        mantissa = mantissa.rstrip("0").rstrip(".")
    return mantissa + e + exponent


def _fmt_interval(iv: list) -> str:
    lo, hi = iv
    return f"({fmt(lo)}, {'zmax' if hi is None else fmt(hi)})"


def _fmt_steps(iv: list) -> str:
    """A safe interval of h, shown inside what is safe (ends rounded inwards)."""
    lo, hi = iv
    return f"({fmt_above(lo) if lo else '0'}, {'no limit' if hi is None else fmt_below(hi)})"


def _lit(*parts: Any):
    """File text for rich, shown as typed: a rich ``Text`` (never parsed as markup, so
    "[red]x[/red]" or "[/]" is text, not a style, and ":smile:" is not an emoji), with
    control characters made visible. ``parts`` are strings or ``(string, style)`` pairs."""
    from rich.text import Text

    return Text.assemble(*((printable(p[0]), p[1]) if isinstance(p, tuple) else printable(p)
                           for p in parts))


#: Width of text piped to a file or a program when COLUMNS does not say otherwise.
MAX_PIPE_WIDTH = 400


def _console():
    import os

    from rich.console import Console

    console = Console(soft_wrap=False)  # rich honours NO_COLOR and COLUMNS itself
    if not console.is_terminal and not os.environ.get("COLUMNS"):
        # piped: tables keep their natural width (no column cut to an ellipsis)
        console = Console(soft_wrap=False, width=MAX_PIPE_WIDTH)
    console.on_broken_pipe = _pipe_closed  # rich would exit 1 ("unsafe"); the CLI decides
    return console


def _pipe_closed() -> None:
    raise BrokenPipeError(32, "Broken pipe")


def print_region(head: dict[str, Any], models: dict[str, dict[str, Any]]) -> None:
    console = _console()
    order = "unknown" if head["order"] is None else head["order"]
    console.print(_lit((head["method"], "bold"), f" — {head['title']}  "
                       f"({head['kind']}, {head['stages']} stages, order {order}, "
                       f"{'symplectic' if head['symplectic'] else 'NOT symplectic'})"))
    stability = head.get("criterion") == "stability"
    if stability:
        console.print("criterion: stability (the flow's type, either orientation; for the "
                      "oscillator |tr M| <= 2)")
    for model, d in models.items():
        if "not_analysed" in d:
            console.print()
            console.print(_lit((model, "bold"), f"  not analysed: {d['not_analysed']}"))
            continue
        if d["first_boundary"] is None:
            first = f"none below zmax = {fmt(d['zmax'])}"
        else:
            first = fmt(d["first_boundary"])
            if d["first_boundary_kind"]:
                first += f"  ({d['first_boundary_kind']}: {d['first_boundary_detail']})"
        console.print(f"\n[bold]{model}[/bold]  first boundary z* = {first}")
        if stability and "structure_first_boundary" in d \
                and d["structure_first_boundary"] != d["first_boundary"]:
            z_s = d.get("structure_first_boundary")
            console.print("  under the structure criterion (type and orientation): z* = "
                          + ("none below zmax" if z_s is None else fmt(z_s)))
        if "classical_intervals" in d:
            console.print("  preserved: never (not symplectic: a centre becomes a spiral)")
            console.print("  classical |mu| <= 1: " + (", ".join(
                _fmt_interval(iv) for iv in d["classical_intervals"]) or "none"))
        else:
            console.print("  preserved: " + (", ".join(
                _fmt_interval(iv) for iv in d["intervals"]) or "nowhere"))
        if "stability_limit" in d and d["stability_limit"] != d["first_boundary"]:
            limit = "beyond zmax" if d["stability_limit"] is None else fmt(d["stability_limit"])
            console.print(f"  classical stability limit (|tr M| <= 2, either orientation): {limit}"
                      + (" (resonances inside it excepted)" if d["resonances"] else ""))
        for i in d["islands"]:
            hi = "zmax" if i["hi"] is None else fmt(i["hi"])
            turn = "" if i["orientation"] == "any" else f" orientation {i['orientation']}"
            console.print(f"  island ({fmt(i['lo'])}, {hi}){turn}")
        for r in d["resonances"]:
            console.print(f"  resonance at {fmt(r['z'])} ± {r['uncertainty']:.1g} ({r['detail']})")
        if d["poles"]:
            console.print("  poles (no unique step): " + ", ".join(fmt(p) for p in d["poles"]))
        for note in d.get("notes", ()):
            console.print(_lit(f"  note: {note}"))
        if d.get("nonlinear_resonances"):
            console.print("  nonlinear resonances n:m (n theta = 2 pi m) below z*: " + ", ".join(
                f"{r['resonance']} at {fmt(r['z'])}" for r in d["nonlinear_resonances"]))
    console.print("\nz = beta*h. " + (
        "Resonances (M = +-I within rounding) are excluded: float64 cannot tell a touch of "
        "|tr M| = 2 from a gap narrower than their uncertainty." if stability else
        "Islands marked 'reversed' have the flow's type but the opposite orientation: not "
        "safe (--criterion stability accepts them)."))


def print_method(data: dict[str, Any], coefficients: dict[str, Any]) -> None:
    from rich.table import Table

    console = _console()
    console.print(_lit((data["method"], "bold"), f" — {data['title']}"))
    table = Table(show_header=False)
    table.add_column("field")
    table.add_column("value")
    for key in ("kind", "order", "stages", "evaluations", "force_gradients", "gradient_form",
                "explicit", "symmetric", "symplectic", "symplectic_for_separable", "source"):
        if key in ("force_gradients", "gradient_form") and key not in data:
            continue
        value = "unknown" if data[key] is None and key in ("order", "evaluations") \
            else data[key]
        table.add_row(key, _lit(value))
    if "processor_evaluations" in data:
        cost = data["processor_evaluations"]
        table.add_row("processor evaluations", f"{cost['start']} once before the first step, "
                                               f"{cost['per_output']} per output (P^-1)")
    for key, value in data["residuals"].items():
        table.add_row(f"residual: {key}", f"{value:.3g}")
    console.print(table)
    for key, value in coefficients.items():
        console.print(_lit((key, "bold"), f" = {value}"))
    if data.get("note"):
        console.print(_lit(f"note: {data['note']}"))
    if data.get("harmonic_sampling"):
        console.print(_lit(f"harmonic oscillator, z = omega h < 2, every friction: "
                           f"{data['harmonic_sampling']}"))


def print_methods(rows: list[dict[str, Any]]) -> None:
    from rich.table import Table

    table = Table()
    for col in ("name", "kind", "order", "stages", "evaluations", "symplectic"):
        table.add_column(col, overflow="fold")
    table.add_column("title", ratio=1)
    table.add_column("also called", overflow="fold")
    for r in rows:
        table.add_row(*(_lit(r[c]) if r[c] is not None else "-" for c in
                        ("name", "kind", "order", "stages", "evaluations", "symplectic",
                         "title")), _lit(", ".join(r.get("aliases", ()))))
    _console().print(table)


def print_advice(data: dict[str, Any]) -> None:
    from rich.table import Table

    console = _console()
    margin, unit = data["margin"], data.get("time_unit")
    u = f" {unit}" if unit else ""
    console.print(_lit((data["method"], "bold"),
                       f"  (margin {margin:g}: frequencies may be up to {1 / margin:.4g}x larger)"
                       if margin < 1 else ""))
    table = Table()
    for col in ("model", "modes", f"largest beta{f' (rad/{unit})' if unit else ''}",
                "first boundary z*", f"h limit = F z*/beta{f' ({unit})' if unit else ''}"):
        table.add_column(col, overflow="fold")
    for model, lim in data["models"].items():
        z = "none below zmax" if lim["first_boundary"] is None else fmt(lim["first_boundary"])
        if lim["first_boundary_kind"] in ("pole", "resonance"):
            z += f" ({lim['first_boundary_kind']})"
        elif lim["first_boundary_kind"] == "nonlinear":
            z += f" ({lim['resonance']} resonance)"
        table.add_row(model, str(lim["count"]), fmt(lim["beta"]), z,
                      "no limit" if lim["h_limit"] is None else fmt_below(lim["h_limit"]))
    if data["models"]:
        console.print(table)
    safe = data["safe_h"]
    if "accuracy" in data:
        _print_accuracy(console, data, u)
    undecided = data.get("undecided_h") or []
    if data["h_max_limited_by"] == "none" and undecided:
        console.print("[red]No step certified from 0:[/red] float64 cannot decide the coupled "
                      f"analysis up to h = {fmt(min(b for _, b in undecided))}{u} (see the note).")
    elif data["h_max_limited_by"] == "none" and any(
            item.get("type") == "coupled" for item in (data.get("system") or {}).get("items", [])):
        # (the coupled analysis certifies steps; it does not prove the others unsafe: pairs
        # of opposite Krein sign within 1e-6 of each other are left undecided)
        console.print("[red]No safe step from 0:[/red] no step the coupled analysis examined "
                      "could be certified to keep this structure (see the analysis below).")
    elif data["h_max_limited_by"] == "none":
        console.print("[red]No safe step from 0:[/red] the method never preserves this structure.")
    elif safe[0][1] is None:
        console.print("[green]Safe for every h[/green] (no frequency limits the step).")
    elif data["h_max_limited_by"] == "horizon":
        console.print(f"[green]No limit found[/green] up to h = {fmt_below(safe[0][1])}{u}, the "
                      "horizon of the analysis (zmax / largest beta; raise --zmax to look "
                      "further).")
    else:
        lim = data["limiting"]
        who = (f"{lim['label']} ({lim['model']})" if lim and lim.get("label")
               else lim and lim["model"])
        by = ("" if not lim else f", limited by {who} beta = {fmt(lim['beta'])}"
              if lim["beta"] is not None else f", limited by the {lim['model']} analysis")
        if lim and lim.get("resonance"):
            by += f" (its {lim['resonance']} nonlinear resonance)"
        console.print(_lit((f"Safe: 0 < h < {fmt_below(safe[0][1])}{u}", "green"), by))
        for low, high in undecided:
            console.print(f"[yellow]Undecided:[/yellow] float64 cannot decide h in "
                          f"({fmt(low)}, {fmt(high)}){u} (see the note).")
    islands = [iv for iv in safe if iv[0] != 0.0]
    if islands:
        console.print("Also safe (islands outside the primary interval; any error in beta can "
                      "move h out of them): " + ", ".join(_fmt_steps(iv) + u for iv in islands))
    if data["horizon"] is not None and data["h_max_limited_by"] != "horizon":
        console.print(f"Steps above {fmt(data['horizon'])}{u} (zmax / largest beta) were not "
                      "analysed.")
    if data.get("fixed_point_limit") is not None:
        console.print(f"Fixed-point iteration of the stages converges only for h < "
                      f"{fmt_below(data['fixed_point_limit'])}{u} (a solver limit, not a "
                      "structure limit: beyond it, solve the stages by Newton's method).")
    resonances = [r for r in data.get("nonlinear_resonances") or () if r.get("h") is not None]
    if resonances:
        console.print("Nonlinear resonances of the fastest vibration (n theta = 2 pi m; "
                      "--resonance-order N keeps h below those of order <= N): " + ", ".join(
                          f"{r['resonance']} at h = {fmt_below(r['h'])}{u}"
                          for r in resonances))
    _print_other_criterion(console.print, data, u)
    _print_stochastic(console.print, data)
    if not unit and data["models"]:
        console.print("h is in the time unit of 1/beta (--time-unit names it).")


def _print_other_criterion(echo, data: dict[str, Any], u: str) -> None:
    """One line with the safe steps under the criterion not asked for, when they differ."""
    other = data.get("other_criterion")
    if not other:
        return
    steps = ", ".join(_fmt_steps(iv) + u for iv in other["safe_h"]) or "none"
    verdict = "" if "safe" not in other else (
        f"; h = {fmt(data['h'])}{u} is {'safe' if other['safe'] else 'unsafe'} under it")
    echo(f"Under --criterion {other['criterion']} ({CRITERION_MEANING[other['criterion']]}) "
         f"the safe steps are {steps}{verdict}.")


def _print_stochastic(echo, data: dict[str, Any]) -> None:
    """What a Langevin splitting's verdict means (its ``stochastic`` record), and at a step
    how it samples the fastest vibration."""
    rec = data.get("stochastic")
    if not rec:
        return
    echo(f"Langevin splitting {rec['letters']} (friction gamma = {fmt(rec['friction'])}, kT = "
         f"{fmt(rec['kT'])}, from the method file): the stability is that of the mean map, "
         "the same for every friction gamma > 0.")
    s = rec.get("sampling")
    if s and s["stable"]:
        echo(f"Sampling of the fastest vibration (beta = {fmt(s['beta'])}, z = {fmt(s['z'])}), "
             f"stationary over exact (1 is exact): configurational temperature "
             f"{fmt(s['configurational_temperature_ratio'])}, kinetic "
             f"{fmt(s['kinetic_temperature_ratio'])}; the mean decays by "
             f"{fmt(s['decay_per_step'])} per step.")


CRITERION_MEANING = {"structure": "type and orientation",
                     "stability": "type only, |tr M| <= 2"}


def _styled(word: str, colour: str) -> str:
    """``word`` in colour, unless NO_COLOR is set (https://no-color.org); click drops the
    colour itself when stdout is not a terminal."""
    import os

    import click

    return word if os.environ.get("NO_COLOR") else click.style(word, fg=colour)


def print_check(data: dict[str, Any]) -> None:
    """Plain click output: check runs in CI on every commit, so it does not import rich."""
    import click

    u = f" {data['time_unit']}" if data.get("time_unit") else ""
    h, name = fmt_exact(data["h"]) + u, printable(data["method"])
    scene = f"{printable(data['scene'])}: " if data.get("scene") else ""
    if data["safe"]:
        where = "" if data["in_primary_interval"] else \
            " (in an island outside the primary interval)"
        click.echo(scene + _styled("SAFE", "green") + f": {name} with h = {h} "
                   f"preserves all {data['modes']} mode(s){where}"
                   f"{_criterion_words(data)}.")
        _print_other_criterion(click.echo, data, u)
        _print_stochastic(click.echo, data)
        return
    besides = [data[key] for key in ("solver_failure", "search_failure", "engine_failure",
                                     "thermal_failure")
               if data.get(key)]
    if besides and not data["failing"]:
        click.echo(scene + _styled("UNSAFE", "red") + f": {name} with h = {h}: every mode "
                   f"keeps its structure, but {' and '.join(besides)}.")
        return
    click.echo(scene + _styled("UNSAFE", "red") + f": {name} with h = {h}: "
               f"{data['failing']} of {data['modes']} mode(s) lose their structure"
               f"{_criterion_words(data)}.")
    for reason in besides:
        click.echo(f"  and {reason}")
    for f in data["failures"]:
        if f.get("label"):
            f = {**f, "model": f"{printable(f['label'])} ({f['model']})"}
        limit = ("none below the horizon" if f["largest_safe_h"] is None
                 else fmt_below(f["largest_safe_h"]) + u if f["largest_safe_h"] > 0 else "none")
        what = (f"{f['model']}: " if f["beta"] is None else
                f"{f['model']} beta = {fmt(f['beta'])}: z = beta*h = {fmt(f['z'])} ")
        click.echo(f"  {what}{f['reason']}; largest safe h for it: {limit}")
    if data["failing"] > len(data["failures"]):
        click.echo(f"  ... and {data['failing'] - len(data['failures'])} more")
    if data["h_max"]:
        limited_by = data.get("h_max_limited_by") or ""
        why = (" (no limit found up to the horizon of the analysis)" if limited_by == "horizon"
               else f" (limited by the {limited_by.split()[1]} nonlinear resonance)"
               if limited_by.startswith("resonance ") else "")
        click.echo(f"Safe steps for all modes: 0 < h < {fmt_below(data['h_max'])}{u}{why}")
    elif data["h_max"] is not None:
        click.echo("No step is safe for all modes.")
    _print_other_criterion(click.echo, data, u)
    _print_stochastic(click.echo, data)


#: What ``--resonance-order`` does not cover, printed under its verdicts.
RESONANCE_CAVEAT = ("Note: --resonance-order excludes the resonance points; the unstable band "
                    "around each widens with the amplitude of the motion, and resonances "
                    "between modes (n1 theta1 + n2 theta2 = 2 pi m) are not analysed: keep a "
                    "margin below them.")


def _criterion_words(data: dict[str, Any]) -> str:
    return (" (criterion: stability, the type only)"
            if data.get("criterion") == "stability" else "")


def _print_accuracy(console, data: dict[str, Any], u: str = "") -> None:
    for lim in data["accuracy"]:
        what = {"phase": "phase error" if lim["model"] == "oscillator" else "growth-rate error",
                "energy": "energy error"}[lim["kind"]]
        if lim["limited_by"] == "unreachable":
            console.print(f"{lim['model']} beta = {fmt(lim['beta'])}: no step keeps the {what} "
                          f"below {lim['tolerance']:g}.")
        elif lim["limited_by"] == "beyond-float":
            console.print(f"{lim['model']} beta = {fmt(lim['beta'])}: the {what} stays below "
                          f"{lim['tolerance']:g} for every float step.")
        elif lim["limited_by"] == "boundary":
            console.print(f"{lim['model']} beta = {fmt(lim['beta'])}: the {what} stays below "
                          f"{lim['tolerance']:g} up to the first boundary "
                          f"(h < {fmt_below(lim['h'])}{u}).")
        else:
            console.print(f"{lim['model']} beta = {fmt(lim['beta'])}: {what} <= "
                          f"{lim['tolerance']:g} for h <= {fmt_below(lim['h'])}{u} "
                          f"(z = {fmt(lim['z'])}).")
    if data["h"] is not None:
        cost = data["cost_per_unit_time"]
        console.print(f"[bold]Use h = {fmt_below(data['h'])}{u}[/bold] (bound by "
                      f"{data['bound_by']})"
                      + (f": {fmt(cost, 6)} force evaluations per{u or ' unit time'}"
                         f" ({data['evaluations']} per step)" if cost is not None else "."))


def print_errors(data: dict[str, Any]) -> None:
    from rich.table import Table

    table = Table(title=_lit(f"{data['method']} on the {data['model']} model"))
    table.add_column("z = beta*h", overflow="fold")
    table.add_column(data["phase_error"], overflow="fold")
    kernel = any("kernel_energy_error" in r for r in data["rows"])
    if data["model"] == "oscillator":
        table.add_column("energy error bound", overflow="fold")
        if kernel:
            table.add_column("kernel alone: energy", overflow="fold")
    for r in data["rows"]:
        cells = [fmt(r["z"]), _fmt_err(r["phase_error"], r.get("overflow"))]
        if data["model"] == "oscillator":
            cells.append(_fmt_err(r["energy_error"], r.get("overflow")))
            if kernel:
                cells.append(_fmt_err(r["kernel_energy_error"], r.get("overflow")))
        table.add_row(*cells)
    _console().print(table)
    if kernel:
        _console().print("processed method P^-1 K P: the phase error is the kernel's; the "
                         "energy error is that of the outputs P^-1 K^n P x")


def _fmt_err(x: float | None, overflow: bool = False) -> str:
    if overflow:
        return "overflow (M too large)"
    return "not preserved" if x is None else f"{x:.6e}"


def print_compare(data: dict[str, Any]) -> None:
    from rich.table import Table

    tol = ", ".join(f"{k} <= {v:g}" for k, v in data["tolerances"].items()) or "none"
    unit = data.get("time_unit")
    per = f"per {unit}, h in {unit}" if unit else "per unit time"
    table = Table(title=f"cost {per} (force evaluations), tolerance: {tol}")
    for col in ("rank", "method", "z* (osc.)", "h_max (safe)", "h (tolerance)", "use h",
                "bound by", "evals/step", "cost"):
        table.add_column(col, overflow="fold")
    for r in data["methods"]:
        table.add_row(
            "-" if r["rank"] is None else str(r["rank"]),
            _lit(r["method"] + (" *" if r["implicit"] else "")),
            "-" if r["first_boundary"] is None else fmt(r["first_boundary"], 6),
            "-" if r["h_max"] is None else fmt_below(r["h_max"], 6),
            "-" if r["h_tol"] is None else ("unreachable" if r["h_tol"] == 0 else
                                            fmt_below(r["h_tol"], 6)),
            "-" if r["h"] is None else fmt_below(r["h"], 6), r["bound_by"],
            "-" if r["evaluations"] is None else str(r["evaluations"]) + (
                " +P" if "processor_evaluations" in r else "") + (
                f" +{r['jacobians']}J" if r.get("jacobians") else ""),
            "-" if r["cost"] is None else fmt(r["cost"], 6))
    console = _console()
    console.print(table)
    processed = [r for r in data["methods"] if "processor_evaluations" in r]
    for r in processed:
        cost = r["processor_evaluations"]
        console.print(_lit(f"+P {r['method']} (processed): {cost['start']} force evaluations "
                           f"once before the first step and {cost['per_output']} per output "
                           "(P^-1), not in the cost per unit time"))
    solver = data.get("solver", "best")
    if not any(r["implicit"] for r in data["methods"]):
        return
    if solver == "nominal":
        console.print("* implicit: one evaluation per stage (nominal); no solver is counted.")
    else:
        jac = data.get("jacobian_cost", 1.0)
        console.print({
            "best": "* implicit: the cheaper stage solver at the step it allows: fixed-point "
                    "iteration (Gauss-Seidel order, to 1e-14, h below 0.9 of its "
                    "convergence limit) or simplified Newton (its force evaluations plus "
                    f"{jac:g} per Jacobian, --jacobian-cost).",
            "fixed-point": "* implicit: force evaluations of fixed-point iteration of the "
                           "stages (Gauss-Seidel order) to 1e-14 at that h (iterations in "
                           "--json); --solver nominal counts one per stage.",
            "newton": "* implicit: force evaluations of simplified Newton's method on the "
                      "stages (2 iterations on a linear model at any h, and the update) "
                      f"plus {jac:g} per Jacobian (--jacobian-cost), one evaluated and "
                      "factorised per distinct substep."}[solver])
        for r in data["methods"]:
            if r.get("solver"):
                passes = "" if r["solver_iterations"] is None else \
                    f", {r['solver_iterations']} passes"
                jacobians = f", {r['jacobians']} Jacobian per step" if r.get("jacobians") \
                    else ""
                console.print(_lit(f"  {r['method']}: {r['solver']}{passes}{jacobians}"))


#: a system with more modes or equilibria than this lists only the most limiting
SUMMARY_ITEMS = 10


def print_system(system: dict[str, Any], every: bool = False, unit: str | None = None
                 ) -> None:
    """The modes or equilibria a system: scene was reduced to: every one, or (beyond
    :data:`SUMMARY_ITEMS`, unless ``every``) the ones with the smallest h limit."""
    import click

    click.echo(f"System analysis: {system['analysis']}")
    items = system["items"]
    if len(items) > SUMMARY_ITEMS and not every:
        def key(item):
            limit = item.get("h_limit")
            return (limit is None, limit if limit is not None else 0.0)

        click.echo(f"  the {SUMMARY_ITEMS} most limiting of {len(items)} (--every-mode lists "
                   "all; --json has all):")
        items = sorted(items, key=key)[:SUMMARY_ITEMS]
    for item in items:
        where = (f"(q, p) = ({fmt(item['q'], 8)}, {fmt(item['p'], 8)}) "
                 if "q" in item else "")
        if "names" in item:  # an equilibrium of an n-dof Hamiltonian
            point = ", ".join(f"{printable(n)} = {x:.6g}" for n, x in zip(item["names"],
                                                                           item["x"]))
            where = f"({point}) energy {item['energy']:.6g} "
            kind = item["type"] + (f" (index {item['index']})" if item["type"] == "mixed"
                                   else "")
            freqs = ", ".join(f"{w:.6g}" for w in item["frequencies"])
            rates = ", ".join(f"{r:.6g}" for r in item["rates"])
            item = {**item, "type": kind, "model": (f"frequencies {freqs}" if freqs else "")
                    + ("; " if freqs and rates else "") + (f"rates {rates}" if rates else "")}
        beta = "" if item.get("beta") is None else f"beta = {fmt(item['beta'], 8)} "
        limit = item.get("h_limit")
        limit_text = "" if "h_limit" not in item else (
            "no limit" if limit is None or not math.isfinite(limit)
            else f"h < {fmt_below(limit, 10)}"
            + (f" {unit}" if unit else ""))
        moving = ""
        if item.get("atoms"):  # a mode of an MD system: which atoms carry it
            atoms = ", ".join(f"{printable(name)} {share:.0%}" for name, share in item["atoms"])
            moving = f" ({item['wavenumber']:.0f} cm-1; moving {atoms})"
        click.echo(f"  {where}{item['type']} {item.get('model') or ''} {beta}{limit_text}"
                   f"{moving}")
    for note in system["notes"]:
        click.echo(f"  note: {printable(note)}")
    if "search" in system:
        print_search(system["search"])


def print_search(search: dict[str, Any]) -> None:
    """What the equilibrium search did and whether it vouches for completeness."""
    import click

    ends = [f"{search['walks_to_equilibrium']} to an equilibrium",
            f"{search['walks_to_boundary']} to the box boundary"]
    if search["walks_to_singularity"]:
        ends.append(f"{search['walks_to_singularity']} into a singularity of H")
    ends.append(f"{search['walks_stopped']} stopped")
    found = search["found_by_walks"]
    found_bound = search["found_by_bound"]
    click.echo(f"Search: {search['starts']} Newton starts, then {search['walks']} walks along "
               f"the equilibria's eigendirections ({', '.join(ends)}; {found} new "
               f"equilibri{'um' if found == 1 else 'a'} found by them), then an interval "
               f"branch and bound over {search['boxes']} boxes ({found_bound} new "
               f"equilibri{'um' if found_bound == 1 else 'a'} found by it): "
               + ("complete" if search["complete"] else "INCOMPLETE, an equilibrium may be "
                  "missing: " + "; ".join(search["gaps"]) + " (check "
                  "--require-complete-search fails on this)"))
    if search["complete"]:
        click.echo("  (complete: interval arithmetic on grad H, rounded outward, excluded "
                   "every part of the box but the boxes where a Krawczyk test proved one "
                   "equilibrium, each of them found)")

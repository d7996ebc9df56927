"""The method-library table of docs/methods.md, generated from the built-in method files.

``python -m stepsafe.cli.methods_table`` prints it as Markdown: per single-force method its
kind, order, force evaluations per step, the harmonic-oscillator threshold z* = omega h
(end of the first interval where the structure is preserved, computed by
:func:`~stepsafe.core.regions.find_region`), z* per evaluation (the step per force
evaluation, the cost measure for comparing methods; a force-gradient term counts as
:data:`~stepsafe.methods.tableaux.GRADIENT_COST` forces), the classical stability limit
|tr M| <= 2 where it differs from z*, and the first author(s) and year of the source.
A processed method ``P^-1 K P`` counts its kernel's evaluations per step (z* per
evaluation uses them, z* is the kernel's); its processor's, spent once at the start and
once per output, are listed beside them.
The docs site renders it into that page when it is built (``docs/hooks/generate.py``).
"""

from __future__ import annotations

import re

from stepsafe.core.regions import find_region
from stepsafe.methods.library import FAMILIES, builtin_names, resolve
from stepsafe.methods.tableaux import GRADIENT_COST

#: the region is searched up to this z (a method preserving the structure beyond it is
#: listed as such)
ZMAX = 10.0

#: initials and a surname; a capitalised word ending in '.' is a journal abbreviation
_AUTHOR = re.compile(r"(?:[A-Z][a-z]?\.[ -]?)+ ?((?:de |van |von )?[A-Z][\w'-]+)(?![\w.'-])")
_YEAR = re.compile(r"\((1[89]\d\d|20\d\d)\)|\b(1[89]\d\d|20\d\d)\b")


def short_source(source: str) -> str:
    """First author(s) and year of the first reference in a ``source:`` text:
    'Blanes, Casas, Sanz-Serna, SIAM J. ... (2014) ...' -> 'Blanes, Casas & Sanz-Serna
    2014'; more than three authors -> 'Tuckerman et al. 1992'."""
    match = _AUTHOR.search(source)
    if match is None:
        return source.split(",")[0][:40]
    names, position = [match.group(1)], match.end()
    while True:
        nxt = re.match(r",? (?:and )?", source[position:])
        follow = _AUTHOR.match(source, position + (nxt.end() if nxt else 0))
        if not nxt or follow is None:
            break
        names.append(follow.group(1))
        position = follow.end()
    year = _YEAR.search(source, position)
    when = f" {year.group(1) or year.group(2)}" if year else ""
    if len(names) > 3:
        return f"{names[0]} et al.{when}"
    shown = names[0] if len(names) == 1 else ", ".join(names[:-1]) + " & " + names[-1]
    return shown + when


def rows() -> list[dict]:
    """One row per built-in single-force method file (not the families)."""
    out = []
    for name in builtin_names(single_force=True):
        if name in FAMILIES:
            continue
        method, entry = resolve(name)
        region = find_region(method, "oscillator", ZMAX)
        first = region.first_interval
        z_star = None if first is None else region.first_boundary  # None: up to ZMAX
        if first is None:
            classical = region.classical[0].hi if region.classical else None
        else:
            classical = region.stability_limit
        out.append({"name": name, "kind": entry.kind, "order": entry.order,
                    "evaluations": entry.evaluations, "preserved": first is not None,
                    "processor": method.processor_evaluations,
                    "gradients": method.gradient_evaluations,
                    "z_star": z_star, "stability": classical,
                    "source": short_source(entry.source)})
    return sorted(out, key=lambda r: (r["order"], r["name"]))


def _number(x: float | None, digits: int) -> str:
    return "" if x is None else f"{x:.{digits}f}"


def markdown() -> str:
    """The table as Markdown lines, ending with a newline."""
    lines = ["| method | kind | order | evaluations | z* | z* per evaluation | "
             "stability limit, where different | source |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows():
        evaluations = r["evaluations"]
        if r["kind"] == "rk" and r["preserved"]:
            evaluations = f"{evaluations} per stage iteration (implicit)"
        cost = r["evaluations"]
        if r["gradients"] and cost is not None:  # force gradients at GRADIENT_COST forces
            evaluations = f"{evaluations} + {r['gradients']} force gradient" + \
                ("s" if r["gradients"] > 1 else "")
            cost = cost + GRADIENT_COST * r["gradients"]
        if r.get("processor"):
            evaluations = (f"{evaluations} per step + {r['processor']} at the start and "
                           f"{r['processor']} per output (processor)")
        if not r["preserved"]:
            z_star, per = "never (not symplectic)", ""
        elif r["z_star"] is None:
            z_star, per = f"none up to {ZMAX:g}", ""
        else:
            z_star = _number(r["z_star"], 6)
            per = _number(r["z_star"] / cost, 4) if cost else ""
        limit = r["stability"]
        shown = "" if limit is None or (r["z_star"] is not None
                                        and abs(limit - r["z_star"]) <= 1e-9 * limit) \
            else _number(limit, 6) + ("" if r["preserved"] else r" (\|R(iz)\| ≤ 1)")
        lines.append(f"| `{r['name']}` | {r['kind']} | {r['order']} | {evaluations} | "
                     f"{z_star} | {per} | {shown} | {r['source']} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(markdown(), end="")

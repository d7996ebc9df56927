"""The README shows what the code prints: its quick start and the outputs quoted for units,
resonances, HMC, many-dof systems, measurements and impulse methods are regenerated here
and compared, on any machine.

What is compared is what the code promises, not the digits one machine's floating-point path
happens to produce (:func:`assert_shown`): the text, every verdict and count, and every
figure to its printed digits. A figure printed to :data:`LONG_FIGURE` or more significant
digits (limits, boundaries, frequencies: computed to about 1e-12 relative or better and
printed to 12) may round either way on a machine whose BLAS or SIMD kernels round
differently when its value lies within that difference of a decimal boundary, so it may
differ by one unit in its last digit, the tolerance its digits state. Shorter figures
(acceptances, error bounds, ratios) are printed far above any such difference and must
match. Diagnostics of the floating-point path are compared only to what they promise, each
with its reason (:data:`NEWTON_FAILURES`).
"""

from __future__ import annotations

import difflib
import json
import re
from collections.abc import Callable, Sequence
from decimal import Decimal
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from stepsafe.cli import main

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()

#: A printed figure: not part of a word (bcss2, x86_64) or of a version (2.4.6).
FIGURE = re.compile(r"(?<![\w.])[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?(?!\w|\.\d)")
#: Figures of at least this many significant digits may differ by one unit in the last.
LONG_FIGURE = 7
#: Runs of spaces and of table rules: their lengths follow the widths of the figures.
LAYOUT = re.compile(r"([ ─━])\1+")

#: A loose field: (pattern whose group 1 is the field, acceptance of (shown, printed), reason).
Loose = tuple[str, Callable[[str, str], bool], str]

#: How many of the Newton starts do not converge: which starts near the edge of a basin
#: (a fractal set for Newton's method) converge depends on the rounding of each step's
#: linear solve, so the count differs between BLAS kernels; the equilibria found, their
#: types and limits are the contract, and they are compared exactly.
NEWTON_FAILURES: Loose = (r"starts, (\d+) did not converge",
                          lambda shown, printed: 0 <= int(printed) <= 128,
                          "Newton's convergence near a basin's edge follows the rounding")

#: How many boxes the interval branch and bound evaluated: where a box's enclosure is
#: decided by a few ulps of an elementary function (numpy's SIMD kernels differ between
#: CPUs), a box may be halved once more; the verdict ``complete`` is the contract.
BOXES: Loose = (r"over (\d+) boxes", lambda shown, printed: 1 <= int(printed) <= 60000,
                "an enclosure decided by an ulp may halve a box once more")


def _significant_digits(figure: str) -> int:
    mantissa = re.split("[eE]", figure)[0].lstrip("+-").replace(".", "")
    return len(mantissa.lstrip("0")) or 1


def _last_digit_unit(figure: str) -> Decimal:
    return Decimal(1).scaleb(Decimal(figure).as_tuple().exponent)


def same_figure(shown: str, printed: str) -> bool:
    """``printed`` is the figure ``shown``: the same text, or for a figure of at least
    :data:`LONG_FIGURE` significant digits within one unit of its last digit."""
    if shown == printed:
        return True
    if _significant_digits(shown) < LONG_FIGURE:
        return False
    return abs(Decimal(printed) - Decimal(shown)) <= _last_digit_unit(shown)


def _masked(text: str, loose: Sequence[Loose]) -> tuple[str, list[list[str]]]:
    fields = []
    for pattern, _, _ in loose:
        fields.append(re.findall(pattern, text))
        text = re.sub(pattern, lambda m: m.group(0).replace(m.group(1), "<loose>", 1), text)
    return text, fields


def mismatches(shown: str, printed: str, loose: Sequence[Loose] = ()) -> list[str]:
    """Where the README block ``shown`` is not what the command ``printed`` (see the
    module docstring): empty when it is."""
    shown, shown_fields = _masked(shown, loose)
    printed, printed_fields = _masked(printed, loose)
    problems = []
    for (pattern, accept, reason), a, b in zip(loose, shown_fields, printed_fields):
        if len(a) != len(b) or not all(accept(x, y) for x, y in zip(a, b)):
            problems.append(f"{pattern!r}: shown {a}, printed {b} ({reason})")
    texts = [LAYOUT.sub(r"\1", part) for part in FIGURE.split(shown)]
    printed_texts = [LAYOUT.sub(r"\1", part) for part in FIGURE.split(printed)]
    if texts != printed_texts:
        problems.append("the text differs")
        return problems
    for i, (a, b) in enumerate(zip(FIGURE.findall(shown), FIGURE.findall(printed))):
        if not same_figure(a, b):
            problems.append(f"figure {a} shown, {b} printed, after {texts[i][-60:]!r}")
    return problems


def assert_shown(shown: str, printed: str, loose: Sequence[Loose] = ()) -> None:
    problems = mismatches(shown, printed, loose)
    if problems:
        diff = "\n".join(difflib.unified_diff(shown.splitlines(), printed.splitlines(),
                                              "README", "printed", lineterm=""))
        pytest.fail("\n".join(problems) + "\n" + diff)


def _output(*args: str) -> str:
    result = CliRunner().invoke(main, list(args), env={"COLUMNS": "200", "NO_COLOR": "1"})
    assert result.exit_code in (0, 1), result.output
    return result.stdout


def _block_after(marker: str, text: str = README) -> str:
    start = text.index("```text\n", text.index(marker)) + len("```text\n")
    return text[start:text.index("```", start)]


# ------------------------------------------------------------------ the comparison itself

@pytest.mark.parametrize("shown, printed", [
    ("h < 0.491688108573", "h < 0.491688108572"),  # a 12-digit limit rounded the other way
    ("h < 1.99999999999", "h < 2"),
    ("1.6e-09 and 2.5e+12", "1.6e-09 and 2.5e+12"),
    ("│ 2.8696418697  │ 1 │", "│ 2.86964186969 │ 1 │"),  # a wider cell: the layout follows
    ("━━ verlet ━━", "━━━━ verlet ━"),
])
def test_what_the_comparison_accepts(shown, printed):
    assert mismatches(shown, printed) == []


@pytest.mark.parametrize("shown, printed", [
    ("h < 0.491688108573", "h < 0.491688108575"),  # two units of the last digit
    ("acceptance 0.8581", "acceptance 0.8582"),  # a short figure: exact
    ("L = 14 steps", "L = 15 steps"),  # counts are exact
    ("SAFE: h = 2", "UNSAFE: h = 2"),  # the verdict
    ("b = 0.20982502", "b = 0.20982512"),
    ("bcss2 ranks 1", "bcss3 ranks 1"),  # a digit inside a name is text
    ("h < 1 fs", "h < 1 ps"),
    ("4 equilibria (128 Newton starts, 3 did not converge)",
     "5 equilibria (128 Newton starts, 3 did not converge)"),
])
def test_what_the_comparison_refuses(shown, printed):
    assert mismatches(shown, printed, [NEWTON_FAILURES]) != []


def test_a_loose_field_is_held_to_its_reason():
    shown = "4 equilibria of H found in the box (128 Newton starts, 3 did not converge"
    assert mismatches(shown, shown.replace("3 did", "2 did"), [NEWTON_FAILURES]) == []
    assert mismatches(shown, shown.replace("3 did", "2 did")) != []
    assert mismatches(shown, shown.replace("3 did", "129 did"), [NEWTON_FAILURES]) != []


# ----------------------------------------------------------------------- the README's blocks

def test_quick_start_output():
    assert_shown(_block_after("## Quick start"),
                 _output("advise", "--method", "yoshida4", "--beta", "3.2", "--inverted-beta",
                         "1.1"))


def _line_shown(line: str, printed: str) -> None:
    """``line`` of the README is one of the lines ``printed``."""
    lines = printed.splitlines()
    assert any(not mismatches(line, other) for other in lines), (line, printed)


def test_quoted_outputs():
    water = _output("advise", str(ROOT / "examples/water.yaml"), "--resonance-order", "4")
    for line in _block_after("stepsafe advise examples/water.yaml --resonance-order 4") \
            .splitlines():
        _line_shown(line, water)
    units = _output("advise", "--method", "verlet", "--wavenumber", "3700", "--time-unit", "fs")
    quoted = re.search(r"gives beta = (\S+) rad/fs and `(Safe: 0 < h < [^`]+)`", README)
    assert quoted is not None
    safe = next(line for line in units.splitlines() if line.startswith("Safe:"))
    assert_shown(quoted.group(2), safe.split(", limited by")[0])
    row = next(line for line in units.splitlines() if line.startswith("│ oscillator"))
    assert same_figure(quoted.group(1), row.split("│")[3].strip())


def test_scene_schema_is_the_code_s():
    start = README.index("```json\n", README.index("<summary>scene file JSON Schema</summary>"))
    block = README[start + len("```json\n"):README.index("```", start + 8)]
    assert block == _output("schema", "scene")


@pytest.mark.slow  # about 30 s: the jittered acceptance of 1000 modes for four methods, for L
def test_hmc_output():
    target = str(ROOT / "examples/gaussian-1000.csv")
    hmc = _output("hmc", "--modes", target, "--length", "5", "--jitter", "0.1", "--methods",
                  "verlet,bcss2,bcss3,mclachlan2-min")
    assert_shown(_block_after("stepsafe hmc --modes examples/gaussian-1000.csv --length 5"), hmc)
    rows = {line.split("│")[2].strip(): line for line in hmc.splitlines()
            if line.startswith("│")}
    cost = {name: float(line.split("│")[-2]) for name, line in rows.items()}
    # the ratio the prose quotes, to its one decimal
    quoted = re.search(r"verlet needs (\d+\.\d) times the gradients of bcss3", README)
    assert quoted is not None
    assert abs(float(quoted.group(1)) - cost["verlet"] / cost["bcss3"]) <= 0.05 + 1e-3


def _design_objective(params: np.ndarray, step: float, jitter: float) -> np.ndarray:
    """The objective the design minimises for the README's target (its binned frequencies,
    :mod:`stepsafe.core.design`), for each row of ``params``."""
    from stepsafe.core.design import _binned, error_bounds

    sigma = np.loadtxt(ROOT / "examples/gaussian-1000.csv", skiprows=1, ndmin=1)
    values, counts = np.unique(1.0 / sigma, return_counts=True)
    betas, weights, _ = _binned(values, counts.astype(float))
    return error_bounds(2, params, betas * step, weights, jitter)


def test_design_output(tmp_path):
    """The design shows b to 8 digits: the objective rho summed over the modes grows like
    2.5e4 (b - b*)^2 relative about its minimiser b*, so its float64 rounding (a few 1e-16)
    leaves b* uncertain by about 1e-10 (the optimiser's simplex stops at 1e-10), and the
    8-digit figure reaches the objective of every digit to 1e-12. That objective is the
    contract, compared here: the member designed on this machine reaches the least value
    near the figure shown, to the objective's rounding."""
    target = str(ROOT / "examples/gaussian-1000.csv")
    out = tmp_path / "mine.yaml"
    design = _output("design", "--modes", target, "--step", "0.2", "--jitter", "0.1", "-o",
                     str(out))
    assert_shown(_block_after("stepsafe design --modes examples/gaussian-1000.csv"),
                 design.replace(str(out), "mine.yaml"))
    shown = float(re.search(r"with b = (\S+), designed", README).group(1))
    designed = float(re.search(r'b: "(\S+)"', out.read_text()).group(1))
    assert abs(designed - shown) <= 1e-8
    near = shown + np.linspace(-1e-7, 1e-7, 201)  # steps of 1e-9 about the minimiser
    least = _design_objective(near[:, None], 0.2, 0.1).min()
    reached, at_shown = _design_objective(np.array([[designed], [shown]]), 0.2, 0.1)
    assert reached <= least * (1 + 1e-12)
    assert at_shown <= reached * (1 + 1e-12)


def test_criterion_output():
    out = _output("check", "--method", "bcss3", "--beta", "1", "--step", "3.5", "--criterion",
                  "stability")
    assert_shown(_block_after("stepsafe check --method bcss3 --beta 1 --step 3.5 --criterion"),
                 out)


def test_many_dof_output():
    block = _block_after("stepsafe advise examples/henon-heiles.yaml")
    out = _output("advise", str(ROOT / "examples/henon-heiles.yaml"))
    assert block.endswith("\n  ")  # the block is indented under a list item
    assert_shown(block[:-2], "".join("  " + line if line.strip() else line
                                     for line in out.splitlines(True)), [NEWTON_FAILURES, BOXES])


def _near_rounding(shown: str, printed: str) -> bool:
    """Both ranges at rounding level (below 1e-11) and within a factor 10 of each other."""
    a = [float(x) for x in shown.split(" to ")]
    b = [float(x) for x in printed.split(" to ")]
    return all(0 < x < 1e-11 and 0 < y < 1e-11 and 0.1 <= y / x <= 10 for x in a for y in b)


#: The reference's floor on the pendulum is the difference of two DOP853 runs at the
#: rounding level of float64: its digits follow the platform's libm.
REFERENCE_FLOOR: Loose = (r"as the trajectory errors\): ([0-9.e+-]+(?: to [0-9.e+-]+)?);",
                          _near_rounding, "the floor is at the rounding level")


def test_measure_outputs():
    pendulum = str(ROOT / "examples/pendulum.yaml")
    assert_shown(_block_after("stepsafe measure examples/pendulum.yaml --h 0.1"), _output(
        "measure", pendulum, "--h", "0.1", "--h", "0.5", "--h", "1.9", "--h", "2.1",
        "--time", "200"), [REFERENCE_FLOOR])
    assert_shown(_block_after("stepsafe measure examples/pendulum.yaml --method gauss"), _output(
        "measure", pendulum, "--method", "gauss", "-s", "2", "--h", "0.5", "--h", "2",
        "--h", "3.6", "--time", "200"), [REFERENCE_FLOOR])


def test_impulse_method_outputs():
    assert_shown(_block_after("stepsafe region respa-verlet --ratio 0.1"), _output(
        "region", "respa-verlet", "--ratio", "0.1"))
    scene = str(ROOT / "examples/respa-water.yaml")
    assert_shown(_block_after("stepsafe check examples/respa-water.yaml"),
                 _output("check", scene))
    assert_shown(_block_after("stepsafe advise examples/respa-water.yaml --substeps 8"), _output(
        "advise", scene, "--substeps", "8", "--resonance-order", "3"))


def test_respa_output():
    out = _output("respa", "--fast-wavenumber", "3700", "--slow-wavenumber", "300",
                  "--time-unit", "fs", "--substeps", "4", "--step", "2")
    assert_shown(_block_after("stepsafe respa --fast-wavenumber 3700 --slow-wavenumber 300"),
                 out)
    eight = _output("respa", "--fast-wavenumber", "3700", "--slow-wavenumber", "300",
                    "--time-unit", "fs", "--substeps", "8", "--step", "4", "--resonance-order",
                    "3")
    assert "UNSAFE" in eight and "3:1 at H = 2.98" in eight


def test_compare_table():
    """The README's compare table is the command's ranking: steps to the digits the command
    prints, evaluations and iterations exactly, the cost rounded to the digits shown; and
    the implicit methods' ranks with --solver nominal as the prose says."""
    args = ("compare", "--beta", "1", "--tol-phase", "1e-6")
    start = README.index(f"`stepsafe {' '.join(args)}` (beta")
    table = README[start:].split("\n\n")[1].splitlines()[2:]
    shown = [[cell.strip() for cell in line.split("|")[1:-1]] for line in table]
    data = json.loads(_output(*args, "--json"))["methods"]
    printed = {cells[2].rstrip(" *"): cells for line in _output(*args).splitlines()
               if line.startswith("│") for cells in [[c.strip() for c in line.split("│")]]}
    assert len(shown) == len(data)
    for (rank, name, z, h_max, h, evaluations, cost), row in zip(shown, data):
        name = name.replace(" (implicit)", "").replace(" -s ", "-s")
        assert (int(rank), name) == (row["rank"], row["method"])
        assert all(same_figure(a, b) for a, b in zip((z, h_max, h), printed[name][3:6]))
        count = f"{row['evaluations']}" + (
            f" + {row['jacobians']} Jacobian" if row["jacobians"] else "") + (
            f" ({row['solver']}, {row['solver_iterations']} iterations)"
            if row["implicit"] else "")
        assert evaluations == count
        assert abs(Decimal(cost) - Decimal(row["cost"])) <= _last_digit_unit(cost) / 2
    ranks = {}
    for solver in ("fixed-point", "nominal"):
        rows = json.loads(_output(*args, "--solver", solver, "--json"))["methods"]
        ranks[solver] = [row["rank"] for row in rows if row["implicit"]]
        if solver == "fixed-point":
            assert {row["evaluations"] for row in rows if row["implicit"]} == {14}
    assert ranks == {"fixed-point": [6, 7], "nominal": [2, 4]}
    assert "would rank 6th\nand 7th, with `--solver nominal` (2 evaluations per step) 2nd " \
           "and 4th" in README


def test_method_library_table_is_generated_from_the_files():
    from stepsafe.cli.methods_table import markdown

    start = README.index("<!-- generated: python -m stepsafe.cli.methods_table -->\n")
    start = README.index("\n", start) + 1
    block = README[start:README.index("<!-- end of generated table -->", start)]
    assert_shown(block, markdown())


#: The rows of the "Safe at temperature" table and the commands that make them.
THERMAL_ROWS = {"`examples/morse.yaml`": ("advise", str(ROOT / "examples/morse.yaml")),
                "`--kT 0.015`": ("advise", str(ROOT / "examples/morse.yaml"), "--kT", "0.015"),
                "`examples/morse-300K.yaml`": ("advise", str(ROOT / "examples/morse-300K.yaml"))}


def _limit(cell: str) -> float:
    return float(re.search(r"h < ([\d.]+)", cell).group(1))


@pytest.mark.slow  # three analyses at temperature, a few seconds each
def test_safe_at_temperature_table():
    """Each row against the analysis it quotes: the 0 K limit rounded down to its digits;
    the limit at temperature and the first band's edge below what was measured and within
    a grid step of the scan (2%) of it, the criterion named (a band near its resonance),
    every band's peak failure fraction to its digits, the drift's bound (|rate| + 2
    standard errors) below the power of ten shown and the fluctuation to its digit."""
    section = README[README.index("### Safe at temperature"):]
    rows = [line for line in section.splitlines()[:40] if line.startswith("| ")][1:]
    assert len(rows) == len(THERMAL_ROWS)
    for row, (key, args) in zip(rows, THERMAL_ROWS.items()):
        assert key in row
        cells = [c.strip() for c in row.strip("|").split("|")]
        data = json.loads(_output(*args, "--json"))
        t = data["thermal"]
        m = t["minima"][0]
        zero = data["zero_kelvin"]["h_max"]
        shown = _limit(cells[2])
        assert shown <= zero and Decimal(str(shown)) + _last_digit_unit(str(shown)) > \
            Decimal(zero)
        warm = _limit(cells[3])
        assert 0.98 * t["h_max"] <= warm <= t["h_max"] * 1.02
        assert t["limited_by"].startswith("resonance band")
        bands = [b for sc in m["scans"] for b in sc["bands"]]
        words = cells[4].split("; ")
        assert len(words) == len(bands)
        for word, band in zip(words, bands):
            assert band["name"] in word
            peak = re.search(r"\(([\d.]+)%\)", word).group(1)
            assert f"{100 * band['peak']:.{len(peak.split('.')[-1]) if '.' in peak else 0}f}"\
                == peak
            edge = re.search(r"from ([\d.]+)", word)
            if edge:
                assert 0.98 * band["lower"]["clear"] <= float(edge.group(1)) <= \
                    band["lower"]["clear"]
        drift = m["drift"]
        bound = abs(drift["rate"]) + 2 * drift["error"]
        power = float(re.search(r"below (1e-\d+)", cells[5]).group(1))
        assert bound < power
        fluct = float(re.search(r"\(([\d.]+)\)$", cells[5]).group(1))
        assert f"{drift['fluctuation']:.1g}" == f"{fluct:g}"

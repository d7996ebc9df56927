"""The README and the pages of the docs site (``docs/``) show what the code prints: every
command in a ``bash`` block is run, and the ``text`` block that follows it is compared with
what the command printed, on any machine; every ``python`` block runs as written.

A ``bash`` block holds commands, one a line; ``# exit N`` after a command is the exit code
it must give (else 0). Each ``stepsafe`` command is run through click's runner in a folder of
its own where ``examples/`` and ``methods/`` are the repository's, in order, so that a file
one command writes is there for the next. Any other command (installing, running the test
suite or a benchmark) must be one of :data:`NOT_RUN`, with its reason. A ``text`` block
right after a ``bash`` block is the output of the block's last command, and is compared
unless that command is not run (a benchmark's timings). HTML comments on the lines right
above a block annotate it: ``<!-- slow: why -->`` for a block that takes more than a few
seconds (its test is then marked slow), ``<!-- requires: openmm -->`` for one that needs an
optional extra's module (its test is skipped without it; a ``python`` block that imports one
of :data:`OPTIONAL` is skipped without it too). A ``python`` block runs as written; a
``text`` block right after it is what it prints, compared as a command's output. The parts
of a page written ``<!-- generated: ... -->`` are rendered from the code when the site is
built (``docs/hooks/generate.py``), and their rendering is tested here.

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
import importlib.util
import json
import os
import re
import shlex
import subprocess
import sys
import textwrap
import unicodedata
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from decimal import Decimal
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from stepsafe.cli import main

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()
#: Every page whose commands and outputs are tested: the README and the docs site's pages.
PAGES = ["README.md", *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").rglob("*.md"))]

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


def _near_rounding(shown: str, printed: str) -> bool:
    """Both ranges at rounding level (below 1e-11) and within a factor 10 of each other."""
    a = [float(x) for x in shown.split(" to ")]
    b = [float(x) for x in printed.split(" to ")]
    return all(0 < x < 1e-11 and 0 < y < 1e-11 and 0.1 <= y / x <= 10 for x in a for y in b)


#: The reference's floor on the pendulum is the difference of two DOP853 runs at the
#: rounding level of float64: its digits follow the platform's libm.
REFERENCE_FLOOR: Loose = (r"as the trajectory errors\): ([0-9.e+-]+(?: to [0-9.e+-]+)?);",
                          _near_rounding, "the floor is at the rounding level")


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
    """Where the block ``shown`` is not what the command ``printed`` (see the
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
                                              "shown", "printed", lineterm=""))
        pytest.fail("\n".join(problems) + "\n" + diff)


def _output(*args: str) -> str:
    result = CliRunner().invoke(main, list(args), env={"COLUMNS": "200", "NO_COLOR": "1"})
    assert result.exit_code in (0, 1), result.output
    return result.stdout


def _page(name: str) -> str:
    return (ROOT / name).read_text()


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



# ------------------------------------------------------------------ the pages' blocks

#: The loose fields every shown output is compared with (see :data:`Loose`).
LOOSE_FIELDS = [NEWTON_FAILURES, BOXES, REFERENCE_FLOOR]

#: Commands a page shows that are not run here, by their first words, and why.
NOT_RUN = {
    "pip install": "installs the project: .ci/run runs it in a fresh environment",
    "pytest": "the test suite itself: .ci/run runs the README's line",
    "python benchmarks/": "benchmarks measure speed on the machine that runs them",
    "python examples/tradeoff.py": "tests/test_accuracy.py and tests/test_examples.py run it",
    "python docs/figures/morse_thermal.py": "a minute of ensembles drawn as a figure: "
                                            "tests/test_thermal_figure.py checks its data",
    "mkdocs build": "builds this site: .ci/run runs it",
}
#: A fenced block: its indentation, language and text (dedented).
FENCE = re.compile(r"^( *)```(\w*)\n(.*?)^\1```$", re.M | re.S)
#: Modules of the optional extras: a page's block that needs one is skipped without it.
OPTIONAL = ("openmm", "blackjax", "jax", "matplotlib")


def _annotations(text: str, start: int) -> tuple[bool, tuple[str, ...]]:
    """Whether the block at ``start`` is marked slow, and the modules it requires, from the
    HTML comments on the lines right above it."""
    slow, requires = False, []
    for line in reversed(text[:start].rstrip().split("\n")):
        note = re.fullmatch(r"\s*<!-- (slow|requires)\b:?\s*(.*?)\s*-->\s*", line)
        if note is None:
            break
        if note.group(1) == "slow":
            slow = True
        else:
            requires += [m.strip() for m in note.group(2).split(",")]
    return slow, tuple(requires)


@dataclass(frozen=True)
class Shown:
    """A ``bash`` block of a page: its commands and the output shown after it."""

    page: str
    line: int
    commands: tuple[tuple[str, ...], ...]  #: each command's words (a ``&&`` chain split)
    exit_codes: tuple[int, ...]
    output: str | None
    slow: bool
    requires: tuple[str, ...]  #: modules of optional extras the block needs

    @property
    def id(self) -> str:
        return f"{self.page}:{self.line}"


def _split(line: str) -> tuple[list[list[str]], int]:
    """The commands of one line of a ``bash`` block and the exit code its comment states."""
    code = re.search(r"#\s*exit (\d+)\s*$", line)
    words = shlex.split(line, comments=True)
    commands: list[list[str]] = [[]]
    for word in words:
        if word == "&&":
            commands.append([])
        else:
            commands[-1].append(word)
    return [c for c in commands if c], int(code.group(1)) if code else 0


def shown_blocks(page: str) -> list[Shown]:
    text = _page(page)
    fences = list(FENCE.finditer(text))
    blocks = []
    for i, fence in enumerate(fences):
        indent, language, body = fence.groups()
        if language != "bash":
            continue
        commands, codes = [], []
        for line in textwrap.dedent(body).splitlines():
            parts, code = _split(line)
            commands += [tuple(p) for p in parts]
            codes += [code] * len(parts)
        output = None
        after = fences[i + 1] if i + 1 < len(fences) else None
        if after is not None and after.group(2) == "text" \
                and not text[fence.end():after.start()].strip():
            output = textwrap.dedent(after.group(3))
        blocks.append(Shown(page, text.count("\n", 0, fence.start()) + 1, tuple(commands),
                            tuple(codes), output, *_annotations(text, fence.start())))
    return blocks


def _not_run(command: tuple[str, ...]) -> str | None:
    line = " ".join(command)
    return next((why for start, why in NOT_RUN.items() if line.startswith(start)), None)


BLOCKS = [block for page in PAGES for block in shown_blocks(page)]


def test_the_pages_show_commands():
    """The parser finds the blocks: the README's quick start and test line, and the guides'."""
    ids = {block.page for block in BLOCKS}
    assert {"README.md", "docs/guides/hmc.md", "docs/guides/md.md"} <= ids
    quick = next(b for b in BLOCKS if b.page == "README.md")
    assert quick.commands[0] == ("pip", "install", ".")
    assert quick.commands[1][:2] == ("stepsafe", "advise") and quick.output
    assert _split("stepsafe check x.yaml   # exit 1") == ([["stepsafe", "check", "x.yaml"]], 1)
    text = "x\n<!-- requires: openmm, jax -->\n<!-- slow: 20 s -->\n```bash\n"
    assert _annotations(text, text.index("```")) == (True, ("openmm", "jax"))
    assert _annotations("<!-- slow -->\ntext\n```", 19) == (False, ())
    assert any(b.slow for b in BLOCKS) and not all(b.slow for b in BLOCKS)


@pytest.mark.parametrize("block", [
    pytest.param(block, id=block.id, marks=[pytest.mark.slow] if block.slow else [])
    for block in BLOCKS])
def test_shown_commands_print_what_the_page_shows(block, tmp_path, monkeypatch):
    for module in block.requires:
        pytest.importorskip(module)
    for folder in ("examples", "methods"):
        (tmp_path / folder).symlink_to(ROOT / folder)
    monkeypatch.chdir(tmp_path)
    printed = None
    for command, code in zip(block.commands, block.exit_codes):
        if command[0] != "stepsafe":
            assert _not_run(command), f"{block.id}: {shlex.join(command)} is not run: " \
                "add it to NOT_RUN with the reason, or show a stepsafe command"
            printed = None
            continue
        if command[1] == "plot":
            pytest.importorskip("matplotlib")
        result = CliRunner().invoke(main, list(command[1:]),
                                    env={"COLUMNS": "200", "NO_COLOR": "1"})
        assert result.exit_code == code, (block.id, command, result.output)
        printed = result.stdout
    if block.output is not None and printed is not None:
        assert_shown(block.output, printed, LOOSE_FIELDS)
    elif block.output is not None:
        assert _not_run(block.commands[-1]), block.id


def _python_blocks():
    for page in PAGES:
        text = _page(page)
        fences = list(FENCE.finditer(text))
        for i, m in enumerate(fences):
            if m.group(2) == "python":
                code = textwrap.dedent(m.group(3))
                slow, requires = _annotations(text, m.start())
                imported = re.findall(r"^\s*(?:import|from)\s+(\w+)", code, re.M)
                requires += tuple(name for name in OPTIONAL if name in imported)
                after = fences[i + 1] if i + 1 < len(fences) else None
                output = textwrap.dedent(after.group(3)) if after is not None \
                    and after.group(2) == "text" and not text[m.end():after.start()].strip() \
                    else None
                yield pytest.param(page, code, requires, output,
                                   id=f"{page}:{text.count(chr(10), 0, m.start()) + 1}",
                                   marks=[pytest.mark.slow] if slow else [])


PYTHON_BLOCKS = list(_python_blocks())


@pytest.mark.parametrize("page, code, requires, output", PYTHON_BLOCKS)
def test_python_blocks_run(page, code, requires, output, monkeypatch, capsys):
    """Every ``python`` block of a page runs as written, from the repository's root, and
    prints the ``text`` block that follows it, if one does."""
    for module in requires:
        pytest.importorskip(module)
    monkeypatch.chdir(ROOT)
    capsys.readouterr()
    exec(compile(code, page, "exec"), {})
    if output is not None:
        assert_shown(output, capsys.readouterr().out, LOOSE_FIELDS)


def _generate():
    spec = importlib.util.spec_from_file_location("docs_generate",
                                                  ROOT / "docs" / "hooks" / "generate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_generated_parts_are_the_code_s():
    """The hook renders each generated part from the code: the scene schema is what
    ``stepsafe schema scene`` prints, the CLI reference has every command's help, the API
    reference every public name, and every marker a page holds renders."""
    generate = _generate()
    markers = {m.group(1) for page in PAGES for m in generate.MARKER.finditer(_page(page))}
    assert {"cli reference", "api reference", "stepsafe schema scene",
            "python -m stepsafe.cli.methods_table"} <= markers
    for what in markers - {"python -m stepsafe.cli.methods_table"}:  # the table: below
        assert generate.render(what)
    assert generate.render("stepsafe schema scene") == \
        "```json\n" + _output("schema", "scene") + "```\n"
    reference = generate.render("cli reference")
    for name in ("advise", "check", "compare", "design", "error", "hmc", "measure",
                 "methods", "plot", "region", "respa", "schema", "show", "validate"):
        assert f"## stepsafe {name}\n" in reference and f"Usage: stepsafe {name} " in reference
    assert max(len(line) for line in reference.splitlines()) <= generate.WIDTH
    import stepsafe

    api = generate.render("api reference")
    for name in stepsafe.__all__:
        assert name.startswith("__") or f"        - {name}\n" in api, name


def test_method_library_table_is_generated_from_the_files():
    from stepsafe.cli.methods_table import markdown

    assert _generate().render("python -m stepsafe.cli.methods_table") == markdown()
    assert "<!-- generated: python -m stepsafe.cli.methods_table -->" in _page("docs/methods.md")


#: A page of the site cited from the code, the tests or the README, with its section.
CITED = re.compile(r"(?<![\w/.])(docs/[\w/-]+\.md)(?:#([\w-]+))?")


def _slug(heading: str) -> str:
    """The anchor MkDocs gives a heading (python-markdown's toc slugify)."""
    text = re.sub(r"\[([^]]*)\]\([^)]*\)", r"\1", heading).replace("`", "")
    text = unicodedata.normalize("NFKD", text).encode("ascii", "ignore").decode("ascii")
    text = re.sub(r"[^\w\s-]", "", text).strip().lower()
    return re.sub(r"[-\s]+", "-", text)


def _anchors(page: str) -> set[str]:
    text = FENCE.sub("", _page(page))
    return {_slug(m.group(1)) for m in re.finditer(r"^#+ (.+)$", text, re.M)}


def test_cited_pages_and_sections_exist():
    """Every docs page the code, the tests, the benchmarks or the README cite exists, with
    the section named after '#'; so does every file the README links to."""
    sources = [p for folder in ("stepsafe", "tests", "benchmarks")
               for p in (ROOT / folder).rglob("*.py")] + [ROOT / "README.md"]
    cited = {(m.group(1), m.group(2), str(source.relative_to(ROOT)))
             for source in sources for m in CITED.finditer(source.read_text())}
    assert ("docs/theory.md", "regions", "stepsafe/core/regions.py") in cited
    for page, anchor, source in cited:
        assert (ROOT / page).is_file(), (source, page)
        assert anchor is None or anchor in _anchors(page), (source, page, anchor)
    for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", README):
        assert target.startswith("http") or (ROOT / target).exists(), target


def test_slugs_are_the_ones_mkdocs_gives():
    assert _slug("The one-step matrix") == "the-one-step-matrix"
    assert _slug("`--verify` over the families and the library") == \
        "-verify-over-the-families-and-the-library"
    assert _slug("Hamiltonian Monte Carlo: `hmc` and `design`") == \
        "hamiltonian-monte-carlo-hmc-and-design"


# ----------------------------------------------------------- figures quoted in the prose

def test_quoted_outputs():
    md = _page("docs/guides/md.md")
    units = _output("advise", "--method", "verlet", "--wavenumber", "3700", "--time-unit", "fs")
    quoted = re.search(r"gives beta = (\S+) rad/fs and `(Safe: 0 < h < [^`]+)`", md)
    assert quoted is not None
    safe = next(line for line in units.splitlines() if line.startswith("Safe:"))
    assert_shown(quoted.group(2), safe.split(", limited by")[0])
    row = next(line for line in units.splitlines() if line.startswith("│ oscillator"))
    assert same_figure(quoted.group(1), row.split("│")[3].strip())


@pytest.mark.slow  # about 30 s: the jittered acceptance of 1000 modes for four methods
def test_hmc_ratio_quoted():
    hmc = _output("hmc", "--modes", str(ROOT / "examples/gaussian-1000.csv"), "--length", "5",
                  "--jitter", "0.1", "--methods", "verlet,bcss2,bcss3,mclachlan2-min")
    rows = {line.split("│")[2].strip(): line for line in hmc.splitlines()
            if line.startswith("│")}
    cost = {name: float(line.split("│")[-2]) for name, line in rows.items()}
    # the ratio the prose quotes, to its one decimal
    quoted = re.search(r"verlet needs (\d+\.\d) times the gradients of bcss3",
                       _page("docs/guides/hmc.md"))
    assert quoted is not None
    assert abs(float(quoted.group(1)) - cost["verlet"] / cost["bcss3"]) <= 0.05 + 1e-3


def _design_objective(params: np.ndarray, step: float, jitter: float) -> np.ndarray:
    """The objective the design minimises for the page's target (its binned frequencies,
    :mod:`stepsafe.core.design`), for each row of ``params``."""
    from stepsafe.core.design import _binned, error_bounds

    sigma = np.loadtxt(ROOT / "examples/gaussian-1000.csv", skiprows=1, ndmin=1)
    values, counts = np.unique(1.0 / sigma, return_counts=True)
    betas, weights, _ = _binned(values, counts.astype(float))
    return error_bounds(2, params, betas * step, weights, jitter)


def test_design_reaches_the_objective_of_the_b_shown(tmp_path):
    """The design shows b to 8 digits: the objective rho summed over the modes grows like
    2.5e4 (b - b*)^2 relative about its minimiser b*, so its float64 rounding (a few 1e-16)
    leaves b* uncertain by about 1e-10 (the optimiser's simplex stops at 1e-10), and the
    8-digit figure reaches the objective of every digit to 1e-12. That objective is the
    contract, compared here: the member designed on this machine reaches the least value
    near the figure shown, to the objective's rounding."""
    out = tmp_path / "mine.yaml"
    _output("design", "--modes", str(ROOT / "examples/gaussian-1000.csv"), "--step", "0.2",
            "--jitter", "0.1", "-o", str(out))
    shown = float(re.search(r"with b = (\S+), designed", _page("docs/guides/hmc.md")).group(1))
    designed = float(re.search(r'b: "(\S+)"', out.read_text()).group(1))
    assert abs(designed - shown) <= 1e-8
    near = shown + np.linspace(-1e-7, 1e-7, 201)  # steps of 1e-9 about the minimiser
    least = _design_objective(near[:, None], 0.2, 0.1).min()
    reached, at_shown = _design_objective(np.array([[designed], [shown]]), 0.2, 0.1)
    assert reached <= least * (1 + 1e-12)
    assert at_shown <= reached * (1 + 1e-12)


def test_respa_resonance_quoted():
    """The outer step of 4 fs with 8 substeps passes the linear test but not the 3:1
    resonance, at the 2.99 fs the page quotes."""
    eight = _output("respa", "--fast-wavenumber", "3700", "--slow-wavenumber", "300",
                    "--time-unit", "fs", "--substeps", "8", "--step", "4", "--resonance-order",
                    "3")
    assert "UNSAFE" in eight and "3:1 at H = 2.98" in eight
    assert "its 3:1 is at 2.99 fs" in _page("docs/guides/respa.md")


def test_compare_table():
    """The compare table is the command's ranking: steps to the digits the command
    prints, evaluations and iterations exactly, the cost rounded to the digits shown; and
    the implicit methods' ranks with --solver nominal as the prose says."""
    page = _page("docs/guides/numerical-analysis.md")
    args = ("compare", "--beta", "1", "--tol-phase", "1e-6")
    start = page.index(f"`stepsafe {' '.join(args)}` (beta")
    table = page[start:].split("\n\n")[1].splitlines()[2:]
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
           "and 4th" in page


@pytest.mark.slow  # about 10 s: renders every page and the API reference
def test_the_site_builds_with_warnings_as_errors(tmp_path):
    """``mkdocs build --strict`` (as .ci/run builds it) passes: every link and anchor
    resolves, every docstring of the API reference parses, every generated part renders."""
    for module in ("mkdocs", "material", "mkdocstrings_handlers.python"):
        pytest.importorskip(module, reason="the docs extra: pip install '.[docs]'")
    result = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir",
                             str(tmp_path / "site")], cwd=ROOT, capture_output=True, text=True,
                            env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert result.returncode == 0, result.stderr
    assert (tmp_path / "site" / "reference" / "cli" / "index.html").is_file()


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
    section = _page("docs/guides/thermal.md")
    lines = section.splitlines()
    top = next(i for i, line in enumerate(lines) if line.startswith("| "))
    end = next((i for i in range(top, len(lines)) if not lines[i].startswith("|")), len(lines))
    rows = [line for line in lines[top:end] if line.startswith("| ")][1:]  # (the first table)
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


def test_readme_temperature_rows_are_the_guide_s():
    """The README's "Safe at temperature" rows are rows of the guide's table, under its
    header (test_safe_at_temperature_table checks those against the analysis): the Morse
    bond at kT/D = 0.006 and the O-H bond at 300 K; the section links the guide and the
    figure, and the README stays within 250 lines."""
    section = README[README.index("\n## Safe at temperature\n"):]
    section = section[:section.index("\n## ", 1)]
    rows = [line for line in section.splitlines() if line.startswith("| ")]
    guide = [line for line in _page("docs/guides/thermal.md").splitlines()
             if line.startswith("| ")]
    assert rows[0] == guide[0] and set(rows[1:]) <= set(guide[1:])
    assert [("morse.yaml" in r, "300 K" in r) for r in rows[1:]] == [(True, False),
                                                                    (False, True)]
    assert "(docs/guides/thermal.md)" in section
    assert "(docs/figures/morse-thermal.png)" in section
    assert README.count("\n") <= 250

"""The README shows what the code prints: its quick start and the outputs quoted for units
and resonances are regenerated here and compared."""

from __future__ import annotations

from pathlib import Path

from click.testing import CliRunner

from stepsafe.cli import main

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()


def _output(*args: str) -> str:
    result = CliRunner().invoke(main, list(args), env={"COLUMNS": "200", "NO_COLOR": "1"})
    return result.stdout


def test_quick_start_output():
    start = README.index("```text\n", README.index("## Quick start")) + len("```text\n")
    block = README[start:README.index("```", start)]
    assert block == _output("advise", "--method", "yoshida4", "--beta", "3.2",
                            "--inverted-beta", "1.1")


def test_quoted_outputs():
    water = _output("advise", str(ROOT / "examples/water.yaml"), "--resonance-order", "4")
    line = next(x for x in water.splitlines() if x.startswith("Safe:"))
    assert line in README
    units = _output("advise", "--method", "verlet", "--wavenumber", "3700", "--time-unit", "fs")
    assert "Safe: 0 < h < 2.86964186966 fs" in units and "0.696951079904" in units
    assert "`Safe: 0 < h < 2.86964186966 fs`" in README and "0.696951079904" in README


def test_scene_schema_is_the_code_s():
    start = README.index("```json\n", README.index("<summary>scene file JSON Schema</summary>"))
    block = README[start + len("```json\n"):README.index("```", start + 8)]
    assert block == _output("schema", "scene")

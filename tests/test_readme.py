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


def _block_after(marker: str) -> str:
    start = README.index("```text\n", README.index(marker)) + len("```text\n")
    return README[start:README.index("```", start)]


def test_hmc_output():
    target = str(ROOT / "examples/gaussian-1000.csv")
    hmc = _output("hmc", "--modes", target, "--length", "5", "--jitter", "0.1", "--methods",
                  "verlet,bcss2,bcss3,mclachlan2-min")
    assert _block_after("stepsafe hmc --modes examples/gaussian-1000.csv --length 5") == hmc
    rows = {line.split("│")[2].strip(): line for line in hmc.splitlines()
            if line.startswith("│")}
    cost = {name: float(line.split("│")[-2]) for name, line in rows.items()}
    assert f"verlet needs {cost['verlet'] / cost['bcss3']:.1f} times" in README


def test_design_output(tmp_path):
    # (a test of its own: the two run side by side on two workers)
    target = str(ROOT / "examples/gaussian-1000.csv")
    out = tmp_path / "mine.yaml"
    design = _output("design", "--modes", target, "--step", "0.2", "--jitter", "0.1", "-o",
                     str(out))
    assert _block_after("stepsafe design --modes examples/gaussian-1000.csv") == \
        design.replace(str(out), "mine.yaml")


def test_criterion_output():
    out = _output("check", "--method", "bcss3", "--beta", "1", "--step", "3.5", "--criterion",
                  "stability")
    assert _block_after("stepsafe check --method bcss3 --beta 1 --step 3.5 --criterion") == out


def test_many_dof_output():
    block = _block_after("stepsafe advise examples/henon-heiles.yaml")
    out = _output("advise", str(ROOT / "examples/henon-heiles.yaml"))
    assert block[:-2] == "".join("  " + line if line.strip() else line
                            for line in out.splitlines(True))


def test_measure_outputs():
    pendulum = str(ROOT / "examples/pendulum.yaml")
    assert _block_after("stepsafe measure examples/pendulum.yaml --h 0.1") == _output(
        "measure", pendulum, "--h", "0.1", "--h", "0.5", "--h", "1.9", "--h", "2.1",
        "--time", "200")
    assert _block_after("stepsafe measure examples/pendulum.yaml --method gauss") == _output(
        "measure", pendulum, "--method", "gauss", "-s", "2", "--h", "0.5", "--h", "2",
        "--h", "3.6", "--time", "200")


def test_impulse_method_outputs():
    assert _block_after("stepsafe region respa-verlet --ratio 0.1") == _output(
        "region", "respa-verlet", "--ratio", "0.1")
    scene = str(ROOT / "examples/respa-water.yaml")
    assert _block_after("stepsafe check examples/respa-water.yaml") == _output(
        "check", scene)
    assert _block_after("stepsafe advise examples/respa-water.yaml --substeps 8") == _output(
        "advise", scene, "--substeps", "8", "--resonance-order", "3")


def test_respa_output():
    out = _output("respa", "--fast-wavenumber", "3700", "--slow-wavenumber", "300",
                  "--time-unit", "fs", "--substeps", "4", "--step", "2")
    assert _block_after("stepsafe respa --fast-wavenumber 3700 --slow-wavenumber 300") == out
    eight = _output("respa", "--fast-wavenumber", "3700", "--slow-wavenumber", "300",
                    "--time-unit", "fs", "--substeps", "8", "--step", "4", "--resonance-order",
                    "3")
    assert "UNSAFE" in eight and "3:1 at H = 2.98" in eight


def test_method_library_table_is_generated_from_the_files():
    from stepsafe.methods.table import markdown

    start = README.index("<!-- generated: python -m stepsafe.methods.table -->\n")
    start = README.index("\n", start) + 1
    block = README[start:README.index("<!-- end of generated table -->", start)]
    assert block == markdown()

"""Shared fixtures: the CLI runner and method lookup."""

from __future__ import annotations

import json
import os

# one BLAS/OpenMP thread per test process: with pytest -n 2 on two cores, threaded BLAS
# on small matrices only oversubscribes (set before anything imports numpy)
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import pytest  # noqa: E402
from click.testing import CliRunner  # noqa: E402
from hypothesis import settings  # noqa: E402

# CI (.ci/run sets CI) draws the same examples on every run, so a red run is reproducible
# and a green one is not luck; without CI every run draws new ones
settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")

from stepsafe.cli import main  # noqa: E402


@pytest.fixture
def run():
    """Run the CLI in-process; returns (exit code, stdout, stderr)."""
    runner = CliRunner()

    def _run(*args: str):
        result = runner.invoke(main, list(args), catch_exceptions=False)
        return result.exit_code, result.stdout, result.stderr

    return _run


@pytest.fixture
def run_json(run):
    def _run(*args: str):
        code, out, err = run(*args, "--json")
        assert code == 0, err
        return json.loads(out)

    return _run


"""Shared fixtures: the CLI runner and method lookup."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from stepsafe.cli import main


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


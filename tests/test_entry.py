"""The command line's process (:mod:`stepsafe.__main__`, ``python -m stepsafe`` and the
``stepsafe`` script): start-up without the cyclic collector, the objects made by then frozen,
the command itself run with the collector on; in-process use of the click group leaves the
host's collector settings alone. Each case runs in a fresh interpreter."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: Runs ``python -m stepsafe ARGV`` in this interpreter, then prints the collector's state as
#: the command left it (an atexit handler runs after the group's sys.exit).
AS_A_PROCESS = """
import atexit, gc, json, runpy, sys
sys.argv = ['stepsafe', *{argv!r}]

def state():
    tracked = {{id(o) for o in gc.get_objects()}}
    commands = sys.modules.get('stepsafe.cli.commands')
    print(json.dumps({{"enabled": gc.isenabled(), "frozen": gc.get_freeze_count(),
                       "command_frozen": commands is not None
                       and id(commands.check_cmd) not in tracked
                       and id(commands.__dict__) not in tracked}}))

atexit.register(state)
runpy.run_module('stepsafe', run_name='__main__', alter_sys=True)
"""


def _last_json(argv: list[str], code: str) -> tuple[int, dict]:
    proc = subprocess.run([sys.executable, "-c", code.format(argv=argv)], capture_output=True,
                          text=True, cwd=ROOT, check=False)
    return proc.returncode, json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("argv", [["check", "--method", "verlet", "--step", "0.5", "--beta", "1"],
                                  ["--debug", "check", "examples/scene.yaml"]])
def test_a_command_runs_with_the_collector_on_and_its_start_up_frozen(argv):
    code, state = _last_json(argv, AS_A_PROCESS)
    assert code == 0
    assert state["enabled"]
    assert state["frozen"] > 10_000  # numpy, click, the package: all made before the command
    assert state["command_frozen"]  # the command's module was loaded before the freeze


def test_an_unknown_command_or_none_is_reported_as_before():
    code, state = _last_json(["nosuch", "--beta", "1"], AS_A_PROCESS)
    assert code == 2 and state["enabled"] and not state["command_frozen"]
    code, state = _last_json(["--version"], AS_A_PROCESS)
    assert code == 0 and state["enabled"]


IN_PROCESS = """
import gc, json
from click.testing import CliRunner
from stepsafe.cli import main
{before}
result = CliRunner().invoke(main, {argv!r})
print(json.dumps({{"code": result.exit_code, "enabled": gc.isenabled(),
                   "frozen": gc.get_freeze_count()}}))
"""


@pytest.mark.parametrize("before", ["", "gc.disable()"])
def test_the_group_in_process_keeps_the_hosts_collector_settings(before):
    argv = ["check", "--method", "verlet", "--step", "0.5", "--beta", "1"]
    _, state = _last_json(argv, IN_PROCESS.replace("{before}", before))
    assert state == {"code": 0, "enabled": before == "", "frozen": 0}

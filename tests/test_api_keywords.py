"""The public API's arguments: one name per meaning, each saying its unit; a name a function
does not take, an extra positional argument, a number given as text and a changed array are
refused or have no effect, never a silently different answer."""

from __future__ import annotations

import inspect
import math
import re
from pathlib import Path

import mpmath
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import stepsafe
from stepsafe.methods.library import FAMILIES, builtin_names

ROOT = Path(__file__).resolve().parent.parent
PENDULUM = {"hamiltonian": "p**2/2 - cos(q)", "box": {"q": [-3, 3], "p": [-1, 1]}}

#: Every public function, with arguments for a small valid call.
CALLS = {
    "method": (("verlet",), {}),
    "method_from_file": ((str(ROOT / "methods/verlet.yaml"),), {}),
    "region": (("verlet", "oscillator"), {}),
    "advise": (("verlet", [1.0]), {}),
    "check": (("verlet", 0.5, [1.0]), {}),
    "check_scenes": (([str(ROOT / "examples/scene.yaml")],), {}),
    "errors": (("verlet", [0.5]), {}),
    "compare": ((["verlet"], [1.0]), {}),
    "transfer_matrices": (("verlet", [0.5]), {}),
    "problem": (("verlet", [1.0]), {}),
    "load_scene": ((str(ROOT / "examples/scene.yaml"),), {}),
    "hmc": ((["verlet"],), {"sigma": [1.0], "trajectory_steps": 4}),
    "design": ((), {"sigma": [1.0], "step": 0.5}),
    "impulse": (("verlet", "verlet"), {"substeps": 4, "fast_beta": 10.0, "slow_beta": 1.0}),
    "impulse_advice": (("respa-verlet", [(10.0, 1.0)]), {}),
    "measure": (("verlet", [0.5]), {"system": PENDULUM, "time": 2.0}),
    "refine": (("verlet", "energy", 1e-2), {"system": PENDULUM, "time": 2.0}),
}


def _taken(name: str) -> list[str]:
    """The names in the error for an unknown keyword."""
    args, kwargs = CALLS[name]
    with pytest.raises(stepsafe.StepsafeError) as caught:
        getattr(stepsafe, name)(*args, **kwargs, no_such_name=1)
    message = caught.value.message
    assert "unknown argument 'no_such_name'" in message
    return re.search(r"\(it takes ([^)]*)\)$", message).group(1).split(", ")


def test_every_public_function_is_covered():
    public = {n for n in stepsafe.__all__ if callable(getattr(stepsafe, n))
              and not isinstance(getattr(stepsafe, n), type)}
    assert public == set(CALLS)


@pytest.mark.parametrize("name", sorted(CALLS))
def test_an_unknown_keyword_lists_every_name_taken(name):
    """The error lists every parameter of the function and, where ``**inputs`` go on to
    :func:`stepsafe.problem`, every keyword of it; and each name listed is taken (giving
    it, here with a value of no use, is never an unknown argument)."""
    taken = _taken(name)
    assert len(taken) == len(set(taken))
    func = getattr(stepsafe, name)
    params = inspect.signature(func).parameters
    own = [n for n, p in params.items() if p.kind is not p.VAR_KEYWORD]
    assert set(own) <= set(taken)
    if any(p.kind is p.VAR_KEYWORD for p in params.values()):
        problem = set(inspect.signature(stepsafe.problem).parameters)
        assert problem - {"method", "h"} <= set(taken) | {"scene"}
    args, kwargs = CALLS[name]
    positional = [n for n, p in params.items()
                  if p.kind is p.POSITIONAL_OR_KEYWORD][:len(args)]
    for key in taken:
        if key in positional or key in kwargs:
            continue
        try:
            func(*args, **kwargs, **{key: object()})
        except stepsafe.StepsafeError as exc:
            assert "unknown argument" not in exc.message, (name, key)


@pytest.mark.parametrize("word, offered", [
    ("frequencies", ("beta=", "ordinary_frequency=")),
    ("frequency", ("beta=", "ordinary_frequency=")),
    ("omega", ("beta=",)),
    ("saddle", ("saddle_beta=",)),
    ("inverted", ("inverted_beta=",)),
])
@pytest.mark.parametrize("call", ["advise", "check", "compare", "problem"])
def test_words_that_could_mean_either_frequency_are_refused(word, offered, call):
    """A word that names a frequency without saying which is no keyword: the error says
    which keyword each reading is (the angular beta, rad per time unit; the ordinary
    frequency, cycles per time unit)."""
    args, kwargs = CALLS[call]
    with pytest.raises(stepsafe.StepsafeError) as caught:
        getattr(stepsafe, call)(args[0], *args[1:], **{word: [0.5]})
    assert all(o in caught.value.message for o in offered)


def test_fast_and_slow_name_their_beta():
    with pytest.raises(stepsafe.StepsafeError, match="fast_beta="):
        stepsafe.impulse("respa-verlet", fast=10.0, slow_beta=1.0)


def _edits(a: str, b: str) -> int:
    """Levenshtein distance."""
    row = list(range(len(b) + 1))
    for i, ca in enumerate(a, 1):
        prev, row[0] = row[0], i
        for j, cb in enumerate(b, 1):
            prev, row[j] = row[j], min(row[j] + 1, row[j - 1] + 1, prev + (ca != cb))
    return row[-1]


@pytest.mark.parametrize("name", sorted(CALLS))
def test_no_two_keywords_differ_by_a_letter(name):
    """Within each function no two names are one edit apart or a plural of each other,
    except hmc's ``step`` (a time h) and ``steps`` (the count L), whose values are of
    different kinds: a count that is no whole number is refused."""
    taken = _taken(name)
    close = {(a, b) for a in taken for b in taken if a < b and (
        _edits(a, b) <= 1 or a.rstrip("s") == b.rstrip("s")
        or a.removesuffix("ies") + "y" == b or b.removesuffix("ies") + "y" == a)}
    assert close <= {("step", "steps")}, close
    if close:
        with pytest.raises(stepsafe.StepsafeError, match="steps must be an integer"):
            stepsafe.hmc(["verlet"], sigma=[1.0], trajectory_steps=0.5)


def test_every_frequency_and_time_keyword_says_its_unit():
    """problem's Parameters name the unit of each frequency and time, and so does each
    command-line option's help."""
    doc = inspect.getdoc(stepsafe.problem)
    params = doc[doc.index("Parameters"):doc.index("Returns")]
    units = {"beta": "rad per time unit", "saddle_beta, inverted_beta": "rad per time",
             "modes": "rad per time unit", "ordinary_frequency": "cycles per time unit",
             "wavenumber": "cm^-1", "period": "time unit", "sigma": "units of q",
             "h": "time unit", "time_unit": "unit of every step"}
    for key, unit in units.items():
        entry = params[params.index(f"\n{key} :"):]
        entry = entry[:entry.index("\n", entry.index("\n", 1) + 1) + 200]
        assert unit in " ".join(entry.split()), key
    from click.testing import CliRunner

    from stepsafe.cli import main

    for command, options in (("check", {"--beta": "rad per time unit",
                                        "--saddle-beta": "R p q", "--frequency": "cycles",
                                        "--wavenumber": "cm-1", "--period": "time unit",
                                        "--sigma": "beta = 1/S", "--step": "--time-unit"}),
                             ("hmc", {"--step": "time unit", "--length": "time unit"})):
        text = " ".join(CliRunner().invoke(main, [command, "--help"]).output.split())
        text = text[text.index("Options:"):]
        for option, unit in options.items():
            start = re.search(rf"{option}[ ,=]", text).start()
            assert unit in text[start:start + 300], (command, option)


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(f=st.floats(1e-3, 1e3), z=st.floats(0.05, 3.95))
def test_beta_and_ordinary_frequency_differ_by_two_pi(f, z):
    """check of Verlet (safe exactly for beta*h < 2): ``beta=[w]`` at h = z / w and
    ``ordinary_frequency=[f]`` at h = z / (2 pi f) give the verdict of z < 2, z taken at
    50 digits from the h used."""
    with mpmath.workdps(50):
        for keyword, beta in (("beta", mpmath.mpf(f)), ("ordinary_frequency",
                                                       2 * mpmath.pi * mpmath.mpf(f))):
            h = float(z / beta)
            exact = mpmath.mpf(h) * beta
            if abs(exact - 2) < mpmath.mpf(10) ** -9:
                continue
            report = stepsafe.check("verlet", h, **{keyword: [f]})
            assert report.safe is bool(exact < 2), (keyword, f, h)


@pytest.mark.parametrize("call", [
    lambda: stepsafe.hmc(["verlet"], [1.0], sigma=[1.0]),
    lambda: stepsafe.design([1.0], step=0.5, sigma=[1.0]),
    lambda: stepsafe.method("gauss", 2),
    lambda: stepsafe.region("verlet", "oscillator", 5.0),
    lambda: stepsafe.impulse("verlet", "verlet", 4, fast_beta=10.0, slow_beta=1.0),
    lambda: stepsafe.advise("verlet", [1.0], [2.0]),
    lambda: stepsafe.check("verlet", 0.1, [1.0], [2.0]),
    lambda: stepsafe.measure("verlet", [0.5], str(ROOT / "examples/pendulum.yaml")),
])
def test_arguments_after_the_first_ones_are_given_by_name(call):
    with pytest.raises(stepsafe.StepsafeError, match="positional argument"):
        call()


NUMBER_TEXTS = st.floats(1e-3, 1e3).map(repr) | st.sampled_from(["1", " 2.5 ", "1e-1", "+3"])

TEXT_CALLS = {
    "check.h": lambda v: stepsafe.check("verlet", v, [1.0]),
    "check.zmax": lambda v: stepsafe.check("verlet", 0.1, [1.0], zmax=v),
    "check.margin": lambda v: stepsafe.check("verlet", 0.1, [1.0], margin=v),
    "hmc.step": lambda v: stepsafe.hmc(["verlet"], sigma=[1.0], step=v),
    "hmc.length": lambda v: stepsafe.hmc(["verlet"], sigma=[1.0], length=v),
    "design.step": lambda v: stepsafe.design(sigma=[1.0], step=v),
    "impulse.step": lambda v: stepsafe.impulse("respa-verlet", fast_beta=1.0,
                                               slow_beta=0.1, step=v),
    "measure.h": lambda v: stepsafe.measure("verlet", [v], system=PENDULUM, time=2.0),
    "advise.period": lambda v: stepsafe.advise("verlet", period=[v]),
    "advise.sigma": lambda v: stepsafe.advise("verlet", sigma=[v]),
    "advise.wavenumber": lambda v: stepsafe.advise("verlet", wavenumber=[v],
                                                   time_unit="fs"),
    "advise.beta": lambda v: stepsafe.advise("verlet", [v]),
    "advise.tol_phase": lambda v: stepsafe.advise("verlet", [1.0], tol_phase=v),
    "check.resonance_order": lambda v: stepsafe.check("verlet", 0.1, [1.0],
                                                      resonance_order=v),
    "region.zmax": lambda v: stepsafe.region("verlet", zmax=v),
    "hmc.target_accept": lambda v: stepsafe.hmc(["verlet"], sigma=[1.0], target_accept=v),
    "hmc.jitter": lambda v: stepsafe.hmc(["verlet"], sigma=[1.0], jitter=v),
    "hmc.gradient_cost": lambda v: stepsafe.hmc(["verlet"], sigma=[1.0], gradient_cost=v),
    "impulse.fast_beta": lambda v: stepsafe.impulse("respa-verlet", fast_beta=v,
                                                    slow_beta=0.1),
    "errors.z": lambda v: stepsafe.errors("verlet", [v]),
    "measure.time": lambda v: stepsafe.measure("verlet", [0.5], system=PENDULUM, time=v),
}


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(text=NUMBER_TEXTS, where=st.sampled_from(sorted(TEXT_CALLS)))
def test_a_number_given_as_text_is_refused(text, where):
    """A number must be given as a number (alone, or in a list where a list is taken):
    a text is a value only with its unit."""
    with pytest.raises(stepsafe.StepsafeError, match="text|number|integer"):
        TEXT_CALLS[where](text)


def test_a_step_with_its_unit_is_taken_in_the_time_unit():
    """``"0.5 fs"`` is 0.5 in fs, and 500 in as; it names the time unit when none is given
    (beta then in rad/fs); a unit of another kind or none where none is known is refused."""
    a = stepsafe.check("verlet", "0.5 fs", [1.0])
    assert (a.h, a.record["time_unit"]) == (0.5, "fs")
    b = stepsafe.check("verlet", "0.5 fs", [1e-3], time_unit="as")
    assert (b.h, b.record["time_unit"]) == (500.0, "as")
    with pytest.raises(stepsafe.StepsafeError, match="not a time|frequency unit"):
        stepsafe.check("verlet", "0.5 THz", [1.0])
    p = stepsafe.problem("verlet", [1.0])
    with pytest.raises(stepsafe.StepsafeError, match="time unit"):
        stepsafe.check(h="0.5 fs", problem=p)


def _arrays(obj, seen=None):
    """Every numpy array reachable from a method object's fields."""
    import dataclasses

    seen = seen if seen is not None else set()
    if id(obj) in seen:
        return
    seen.add(id(obj))
    if isinstance(obj, np.ndarray):
        yield obj
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        for f in dataclasses.fields(obj):
            yield from _arrays(getattr(obj, f.name), seen)
    elif isinstance(obj, (list, tuple)):
        for item in obj:
            yield from _arrays(item, seen)


METHODS = [(n, None) for n in builtin_names() if n not in FAMILIES] + \
    [(f, s) for f in FAMILIES for s in (2, 3)]


@pytest.mark.parametrize("name, stages", METHODS)
def test_a_method_coefficients_cannot_be_changed(name, stages):
    """Every coefficient array of every method (bases, kernels, processors, an impulse
    method's outer and inner methods) is read-only, so a verdict cannot change after
    the method was loaded (a Langevin splitting holds a word and two numbers, none of
    them an array)."""
    m = stepsafe.method(name, stages=stages)
    arrays = list(_arrays(m.tableau))
    assert arrays or isinstance(m.tableau.letters, str)
    for arr in arrays:
        assert not arr.flags.writeable
        with pytest.raises(ValueError):
            arr[...] = 5.0


def test_a_changed_array_changes_no_later_verdict():
    """Verlet at beta = 1, h = 1.5 is safe (z < 2); after trying to change its drift and
    the problem's frequency, still; the caller's own array stays theirs to change."""
    m = stepsafe.method("verlet")
    with pytest.raises(ValueError):
        m.tableau.drift[1] = 5.0
    mine = np.array([1.0])
    p = stepsafe.problem(m, mine)
    mine[0] = 100.0  # the problem holds a copy
    with pytest.raises(ValueError):
        p.modes.betas["oscillator"][0] = 100.0
    with pytest.raises(TypeError):
        p.modes.betas["oscillator"] = np.array([100.0])  # type: ignore[index]
    assert stepsafe.check(h=1.5, problem=p).safe
    assert stepsafe.check(m, 1.5, [1.0]).safe
    assert math.isclose(stepsafe.advise(m, [1.0]).h_max, 2.0, rel_tol=1e-12)


def _keywords() -> list[tuple[str, str]]:
    """Every (function, keyword) pair a caller may give beyond the small valid call."""
    out = []
    for name, (args, kwargs) in CALLS.items():
        func = getattr(stepsafe, name)
        params = inspect.signature(func).parameters
        positional = [n for n, p in params.items()
                      if p.kind is p.POSITIONAL_OR_KEYWORD][:len(args)]
        names = [n for n, p in params.items() if p.kind is not p.VAR_KEYWORD]
        if any(p.kind is p.VAR_KEYWORD for p in params.values()):
            names += [n for n in inspect.signature(stepsafe.problem).parameters
                      if n not in names and n not in ("method", "h", "scene")]
        out += [(name, key) for key in names if key not in positional and key not in kwargs]
    return out


@pytest.mark.slow
@settings(max_examples=200, deadline=None, suppress_health_check=list(HealthCheck))
@given(pair=st.sampled_from(_keywords()), value=st.deferred(lambda: _junk()))
def test_any_value_of_any_keyword_is_an_answer_or_a_stepsafe_error(pair, value):
    """Each keyword of each public function, given a value of the wrong kind (None, text,
    bytes, complex, huge integers, arrays of the wrong shape, mappings, objects), gives an
    answer or a StepsafeError, never another exception."""
    name, key = pair
    args, kwargs = CALLS[name]
    try:
        getattr(stepsafe, name)(*args, **kwargs, **{key: value})
    except stepsafe.StepsafeError:
        pass


def _junk():
    from test_api_inputs import JUNK

    return JUNK

"""Regions shared within one analysis (:func:`stepsafe.core.regions.shared_regions`).

Inside the block a repeated :func:`~stepsafe.core.regions.find_region` call (the same method
object, model, zmax and resolution) returns the region found before; a call that differs in
any of them, or a method that is equal but another object, is analysed afresh; outside the
block every call is. ``check`` and ``advise`` answer under both criteria from one analysis
of each model, with the answers of separate analyses.
"""

from __future__ import annotations

import re

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import stepsafe
from stepsafe.core import regions as regions_module
from stepsafe.core.regions import find_region, shared_regions
from stepsafe.exceptions import MethodError
from stepsafe.methods.library import builtin_names, resolve

MODELS = ("oscillator", "saddle", "inverted")
SINGLE = [n for n in builtin_names(single_force=True) if n not in ("gauss", "lobatto3ab")]


@pytest.fixture
def analyses(monkeypatch):
    """The arguments of every region analysis run (calls of ``_find_region``)."""
    calls: list[tuple] = []
    inner = regions_module._find_region

    def counted(method, model, zmax, resolution):
        calls.append((method.name, model, zmax, resolution))
        return inner(method, model, zmax, resolution)

    monkeypatch.setattr(regions_module, "_find_region", counted)
    return calls


@settings(max_examples=12, deadline=None, database=None)
@given(name=st.sampled_from(SINGLE), model=st.sampled_from(MODELS),
       zmax=st.sampled_from([0.5, 3.0, 10.0]))
def test_a_shared_region_is_the_region_of_a_separate_analysis(name, model, zmax):
    """Inside a block the region is analysed once and equals a separate analysis; a model
    the method has no form for is refused alike inside and outside."""
    method, _ = resolve(name)
    try:
        alone = find_region(method, model, zmax)
    except MethodError as exc:
        with shared_regions(), pytest.raises(MethodError, match=re.escape(str(exc))):
            find_region(method, model, zmax)
        return
    with shared_regions():
        first = find_region(method, model, zmax)
        again = find_region(method, model, zmax)
    assert again is first
    assert first == alone


def test_only_the_same_method_object_and_arguments_share(analyses):
    method, _ = resolve("yoshida4")
    twin, _ = resolve("yoshida4")  # equal coefficients, another object
    with shared_regions():
        find_region(method, "oscillator", 10.0)
        find_region(method, "oscillator", 10.0)
        find_region(twin, "oscillator", 10.0)
        find_region(method, "saddle", 10.0)
        find_region(method, "oscillator", 5.0)
        find_region(method, "oscillator", 10.0, resolution=0.01)
        with shared_regions():  # an inner block shares the outer one's regions
            find_region(method, "saddle", 10.0)
    find_region(method, "oscillator", 10.0)  # outside any block: analysed again
    assert len(analyses) == 6
    assert analyses.count(("yoshida4", "oscillator", 10.0, None)) == 3


def test_a_failed_analysis_is_not_kept(analyses):
    method, _ = resolve("verlet")
    with shared_regions():
        for _ in range(2):
            with pytest.raises(stepsafe.StepsafeError):
                find_region(method, "oscillator", float("nan"))
    assert analyses == []  # refused before any analysis, each time


def test_check_and_advise_analyse_each_model_once_under_both_criteria(analyses):
    scene = {"oscillator": [3.2], "inverted": [1.1], "saddle": [0.4]}
    report = stepsafe.check("yoshida4", 0.05, modes=scene)
    assert report.safe
    assert sorted(m for _, m, _, _ in analyses) == sorted(scene)
    analyses.clear()
    advice = stepsafe.advise("bcss3", [4.0])
    assert sorted(m for _, m, _, _ in analyses) == ["oscillator"]
    assert advice.other_criterion is not None  # both criteria were answered

"""What the method files state is what the code computes.

Every ``thresholds:`` entry (harmonic oscillator: ``structure`` = end of the first preserved
interval z*, ``stability`` = the classical limit |tr M| <= 2) is compared with the region
found from the coefficients, to the digits the file writes; comments carry no thresholds of
their own. The numerical facts the comments state (published middle weights against the
sum of the others, vanishing order conditions, a closed form) are recomputed at 50 digits.
"""

from __future__ import annotations

import re
from decimal import Decimal
from pathlib import Path

import mpmath as mp
import pytest
from support import method

from stepsafe.core.regions import find_region
from stepsafe.exceptions import StepsafeError
from stepsafe.files.expressions import mpmath_backend
from stepsafe.files.yamlio import load_yaml
from stepsafe.methods.fileformat import validate_tree
from stepsafe.methods.library import builtin_dir, load_file

FILES = sorted(builtin_dir().glob("*.yaml"))
STATED = [(p.stem, load_file(p).thresholds) for p in FILES if load_file(p).thresholds]


def _tolerance(text: str, z: float, uncertainty: float) -> float:
    """Half a unit in the last written digit (a whole number is exact), plus the computed
    point's own uncertainty and rounding."""
    exponent = Decimal(text).as_tuple().exponent
    written = 0.5 * 10.0 ** exponent if exponent < 0 else 0.0
    return written + uncertainty + 1e-12 * z


@pytest.mark.parametrize("name, stated", STATED, ids=[n for n, _ in STATED])
def test_stated_thresholds_are_the_computed_ones(name, stated):
    region = find_region(method(name), "oscillator")
    first = region.first_interval
    assert first is not None and first.hi is not None
    if "structure" in stated:
        uncertainty = first.hi_point.uncertainty if first.hi_point else 0.0
        assert abs(first.hi - float(stated["structure"])) <= \
            _tolerance(stated["structure"], first.hi, uncertainty), (name, first.hi)
    if "stability" in stated:
        assert region.stability_limit is not None
        assert abs(region.stability_limit - float(stated["stability"])) <= \
            _tolerance(stated["stability"], region.stability_limit, 1e-12), \
            (name, region.stability_limit)


def test_every_bounded_explicit_method_states_its_thresholds():
    """Splittings and compositions all have a first boundary: each file records it."""
    missing = [p.stem for p in FILES if load_file(p).kind in ("splitting", "composition")
               and not load_file(p).thresholds]
    assert missing == []


COMMENT_THRESHOLD = re.compile(
    r"(h\*|z\*|threshold|stability limit|limit|ends at|boundary)[^#]*\d\.\d{3,}", re.I)


def test_comments_carry_no_thresholds_of_their_own():
    """A threshold belongs in ``thresholds:`` (checked above), not in a comment."""
    for path in FILES:
        for number, line in enumerate(path.read_text().splitlines(), 1):
            comment = line[line.index("#"):] if "#" in line else ""
            assert not COMMENT_THRESHOLD.search(comment), f"{path.name}:{number}: {line}"


def _weights(name: str) -> list:
    tree = load_yaml(builtin_dir() / f"{name}.yaml")
    return validate_tree(tree, name, mpmath_backend()).coefficients["weights"], tree


@pytest.mark.parametrize("name, digits", [("kahan-li6", 26), ("kahan-li8", 26),
                                          ("sofroniou-spaletta10", 31), ("mclachlan8", 25),
                                          ("kahan-li10", 19)])
def test_published_middle_weight_against_the_sum_of_the_others(name, digits):
    """The comments state to how many digits the published middle weight equals
    1 - 2 (sum of the others); the files ship the published value."""
    with mp.workdps(50):
        weights, tree = _weights(name)
        half = len(tree["weights"])
        middle = weights[half - 1]
        assert mp.mpf(tree["weights"][-1]) == middle
        gap = abs(middle - (1 - 2 * mp.fsum(weights[:half - 1])))
        assert gap < mp.mpf(10) ** -digits and gap > 0


def test_yoshida6_order_conditions_vanish():
    with mp.workdps(50):
        weights, _ = _weights("yoshida6")
        assert abs(mp.fsum(w ** 3 for w in weights)) < mp.mpf("1e-38")
        assert abs(mp.fsum(w ** 5 for w in weights)) < mp.mpf("1e-38")
        table = [mp.mpf(x) for x in ("0.784513610477560", "0.235573213359357",
                                     "-1.17767998417887")]
        table = table + [1 - 2 * mp.fsum(table)] + table[::-1]
        assert mp.mpf("1e-15") < abs(mp.fsum(w ** 3 for w in table)) < mp.mpf("1e-13")


def test_mclachlan2_min_closed_form():
    """a = 1/2 + cbrt((sqrt 326 - 18)/864) - cbrt((sqrt 326 + 18)/864), the real root of
    48 a^3 - 72 a^2 + 38 a - 5, agrees with the file's 20 digits."""
    with mp.workdps(50):
        a = mp.mpf(load_yaml(builtin_dir() / "mclachlan2-min.yaml")["constants"]["a"])
        closed = mp.mpf(1) / 2 + mp.cbrt((mp.sqrt(326) - 18) / 864) \
            - mp.cbrt((mp.sqrt(326) + 18) / 864)
        assert abs(48 * closed ** 3 - 72 * closed ** 2 + 38 * closed - 5) < mp.mpf("1e-45")
        assert abs(closed - a) < mp.mpf("1e-20")


def test_bcss4_is_minus_the_identity_at_its_structure_threshold():
    from reference_methods import mp_transfer

    with mp.workdps(50):
        M = mp_transfer("bcss4", dps=50)(mp.mpf("3.043"), "oscillator")
        assert max(abs(M[0, 0] + 1), abs(M[1, 1] + 1), abs(M[0, 1]), abs(M[1, 0])) \
            < mp.mpf("1e-19")


def test_sofroniou_spaletta10_instability_band_past_the_structure_threshold():
    """tr M < -2 just past z* on a band of width 7.6e-4, then a reversed island."""
    region = find_region(method("sofroniou-spaletta10"), "oscillator")
    band = region.reversed[0].lo_point.z - region.first_boundary
    assert 7.5e-4 < band < 7.7e-4 and region.stability_limit == region.first_boundary
    assert region.first_interval.hi_point.z == region.first_boundary


@pytest.mark.parametrize("value, message", [
    ({"structure": "3.1.4"}, "positive decimal"), ({"structure": "-1"}, "positive decimal"),
    ({"structure": "1e3"}, "positive decimal"), ({"limit": "3"}, "limit"),
    ({}, "mapping"), ("3", "mapping")])
def test_bad_thresholds_are_refused(value, message):
    tree = {"name": "x", "kind": "splitting", "order": "2", "source": "s",
            "drift": ["1/2", "1/2"], "kick": ["1"], "thresholds": value}
    with pytest.raises(StepsafeError, match=message):
        validate_tree(tree, "x.yaml")


def test_the_method_file_page_documents_the_key():
    page = Path(__file__).resolve().parent.parent / "docs" / "method-files.md"
    assert "`thresholds:`" in page.read_text()


def test_every_name_and_alias_finds_one_file():
    """Aliases (the names other libraries use) are unique and never another file's name."""
    from stepsafe.methods.library import FAMILIES, resolve

    owner: dict[str, str] = {}
    for path in FILES:
        for name in (path.stem, *load_file(path).aliases):
            assert name not in owner and name not in FAMILIES, (name, path.stem, owner.get(name))
            owner[name] = path.stem
    for name, stem in owner.items():
        assert resolve(name)[1].name == stem

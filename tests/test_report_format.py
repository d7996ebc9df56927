"""Step limits as printed: rounded to 12 digits away from the safe side's end, strictly,
also once read back as floats, at every magnitude (subnormal ones included)."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from stepsafe.cli.report import fmt_above, fmt_below

POSITIVE = st.floats(min_value=5e-324, max_value=1.7976931348623157e308)


def _digits(text: str) -> int:
    return len(text.split("e")[0].replace(".", "").lstrip("0"))


@given(st.one_of(POSITIVE, st.floats(5e-324, 2.2250738585072014e-308),
                 st.integers(-320, 300).map(lambda k: float(f"1e{k}"))))
def test_strictly_inside_and_twelve_digits(x):
    below, above = fmt_below(x), fmt_above(x)
    assert float(below) < x < float(above), (x, below, above)
    assert _digits(below) <= 12 and _digits(above) <= 12


def test_short_decimals_and_the_ends_of_the_range():
    assert fmt_above(1e-12) == "1.00000000001e-12"  # 1e-12 itself reads back as x
    assert fmt_below(5e-324) == "0"
    assert fmt_below(1e-320) == "9.99494801536e-321"  # the floats there are 5e-324 apart

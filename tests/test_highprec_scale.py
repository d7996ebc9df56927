"""The high-precision reference at any precision, on coefficients consistent only to their
rounding.

A splitting's drift and kick sums, as float64 values (or decimals read at 40 digits), agree
only to their rounding; the reference must judge that at float64's scale, as the float path
does, whatever digits it works at: escalation at 120 digits raised ``ValueError:
inconsistent splitting`` (``region pefrl --zmax 1e50``, exit 3). ``--verify`` must pass a
float answer that is wrong only on the safe side where float64 says it cannot decide.
"""

from __future__ import annotations

import json

import mpmath as mp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import stepsafe
from stepsafe.core import escalate
from stepsafe.methods.tableaux import RESIDUAL_TOL, Splitting
from stepsafe.reference import highprec as R


def test_the_reference_sum_tolerance_is_the_float_paths():
    assert R.SUM_TOL == RESIDUAL_TOL


coefficient = st.floats(-2.0, 2.0, allow_nan=False).filter(lambda v: abs(v) > 1e-3)


@settings(max_examples=40, deadline=None)
@given(drift=st.lists(coefficient, min_size=2, max_size=5), data=st.data(),
       scale=st.integers(-40, 40), dps=st.sampled_from([40, 120, 400]))
def test_float_splittings_have_a_prk_form_at_any_precision(drift, data, scale, dps):
    """Float coefficients whose sums agree to float rounding (the last kick is the drift
    sum less the other kicks, in float64), scaled by 2^scale: no ValueError at any digits,
    and the saddle's M is the float path's PRK form (Splitting.as_prk) to its rounding."""
    ends_with_drift = data.draw(st.booleans())
    m = len(drift) - 1 if ends_with_drift else len(drift)
    kick = data.draw(st.lists(coefficient, min_size=m - 1, max_size=m - 1))
    kick.append(float(np.sum(drift)) - float(np.sum(kick)))
    drift = [float(np.ldexp(v, scale)) for v in drift]
    kick = [float(np.ldexp(v, scale)) for v in kick]
    prk = Splitting(np.array(drift), np.array(kick), name="random").as_prk()
    z = 0.3 * 2.0 ** -scale
    with mp.workdps(dps):
        pieces = R._euler_pieces(drift, kick)  # old code: ValueError from 40 digits on
        assert pieces
        for model in ("saddle", "saddle-p"):
            try:
                M = R.transfer_matrix_splitting(drift, kick, z, model)
                P = R.transfer_matrix_prk(prk.A_q.tolist(), prk.b_q.tolist(),
                                          prk.A_p.tolist(), prk.b_p.tolist(), z, model)
            except ZeroDivisionError:  # z on a pole of both: nothing to compare
                continue
            for i in range(2):
                assert abs(M[i, i] - P[i, i]) <= 1e-9 * max(1, abs(P[i, i]))


def test_pefrl_float_coefficients_at_120_digits():
    split = stepsafe.method("pefrl").tableau
    with mp.workdps(120):
        M = R.transfer_matrix_splitting(split.drift.tolist(), split.kick.tolist(), 1.0,
                                        "saddle")
    assert M[0, 0] > 1 > M[1, 1] > 0


def test_unequal_sums_still_have_no_prk_form():
    with pytest.raises(ValueError, match="no PRK form"):
        R._euler_pieces([0.5, 0.5], [1.0 + 1e-9])


def test_the_library_far_out_on_the_saddles():
    """Escalation beyond z = 1e35 (the reference at 40 and 120 digits): old code raised
    ValueError (inconsistent splitting), then refine_root's 'no sign change' (tr M - 2 ~
    1e-68 rounded to 0 at 40 digits). The truth here is preserved (M -> I from the
    saddle's side): anything but an exception is acceptable, undecided included."""
    report = stepsafe.region("mclachlan2-min", model="saddle", zmax=1e35)
    region = report.regions["saddle"]
    assert region.intervals and region.intervals[0].lo == 0.0


def test_escalation_keeps_the_float_answer_when_the_reference_refuses(monkeypatch):
    def refusing(method):
        def mfun(z, model):
            raise ValueError("no form")
        return mfun

    monkeypatch.setattr(escalate, "reference_of", refusing)
    esc = escalate.Escalation(stepsafe.method("verlet").tableau, "saddle")
    assert esc.decide(1.0, 2.0, 2.0, 1e-12) is None
    assert esc.pole(1.0, 0.1) is None


NC1 = """name: nc1
kind: splitting
order: 1
source: test
drift: ["9007199254740992", "-9007199254740992 + 1.4"]
kick: ["1"]
"""


def test_verify_accepts_a_conservative_float_answer(run, tmp_path):
    """drift 2^53 and -2^53 + 1.4 cancel to far below float64's rounding: float64 leaves
    bands undecided and calls the stretches between them 'not preserved', where the
    40-digit reference (tr M = 2 - 1.4 z^2) finds a centre: safe side, not a failure
    (old code: 94 'reference None' lines, exit 3)."""
    path = tmp_path / "nc1.yaml"
    path.write_text(NC1)
    code, out, err = run("check", "--method", str(path), "--beta", "1", "--step", "1.9",
                         "--verify", "--json")
    assert code == 1, err
    verdict = json.loads(out)["checks"][0]["verify"]
    assert verdict["ok"] and verdict["conservative"] > 0 and not verdict["failed"]


def test_verify_confirms_a_pole_of_tiny_residue(tmp_path):
    """nc1 on the saddle: a pole at exactly 2^-53 (the weight 2^53), where 1/tr M is about
    1/2 except at the point: confirmed there (old code: ValueError, inconsistent
    splitting, from the exact decimals' sums 1.4 and 1; then the pole unconfirmed)."""
    from stepsafe.core.regions import Point
    from stepsafe.reference.verify import check_point, mp_method, mp_transfer

    path = tmp_path / "nc1.yaml"
    path.write_text(NC1)
    Mfun = mp_transfer(mp_method(str(path)))
    pole = Point(2.0 ** -53, "pole", 1e-31, "stage system singular")
    assert check_point(Mfun, "saddle", pole).ok


def test_verify_names_the_method_the_reference_cannot_treat(monkeypatch):
    from stepsafe.exceptions import StepsafeError
    from stepsafe.reference import verify

    def refusing(m):
        def mfun(z, model):
            raise ValueError("inconsistent splitting")
        return mfun

    region = stepsafe.region("verlet", model="saddle").regions["saddle"]
    monkeypatch.setattr(verify, "mp_transfer", refusing)
    with pytest.raises(StepsafeError, match="verlet"):
        verify.verify_regions("verlet", None, None, {"saddle": region})

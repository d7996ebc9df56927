"""Steps close to reported points: every step the gate calls safe is preserved at 50 digits.

Hostile cases: boundaries within 1e-6 relative of a pole
(M = +I on the saddle, where the multiplier crosses 1 on its way to 0 at the pole), and
orientation switches on the barrier computed with cancellation (drift coefficients 1e2 to
1e8 that cancel to 1). Random splittings generate more of both; each reported point is
probed at relative offsets 1e-2 .. 1e-13 on both sides.
"""

from __future__ import annotations

import sys

import mpmath
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from stepsafe.core.advice import Modes, advise
from stepsafe.methods.library import resolve
from stepsafe.reference import highprec
from stepsafe.reference.verify import mp_method, mp_transfer, points

OFFSETS = [s * 10.0 ** -k for k in range(2, 14) for s in (-1.0, 1.0)]


def _method_file(folder, name: str, drift: list[str], kick: list[str]) -> str:
    path = folder / f"{name}.yaml"
    drift = [*drift, "1 - (" + " + ".join(["0", *drift]) + ")"]
    kick = [*kick, "1 - (" + " + ".join(["0", *kick]) + ")"]
    path.write_text(f"name: {name}\nkind: splitting\norder: 1\nsource: generated\n"
                    f"drift: {drift!r}\nkick: {kick!r}\n")
    return str(path)


def _false_safes(path: str, model: str, zmax: float) -> list[float]:
    """Steps (beta = 1) near the reported points that the advice calls safe but that
    are not preserved at 50 digits."""
    method, _ = resolve(path)
    adv = advise(method, Modes.from_arrays({model: [1.0]}), 1.0, zmax)
    region = adv.regions[model]
    Mfun = mp_transfer(mp_method(path, None, None, 50))
    bad = []
    for p in points(region):
        for off in OFFSETS:
            z = p.z * (1.0 + off)
            if not (0 < z < zmax) or not any(lo < z and (hi is None or z < hi)
                                             for lo, hi in adv.safe_h):
                continue
            with mpmath.workdps(50):
                try:
                    M = Mfun(mpmath.mpf(z), model)
                except ZeroDivisionError:
                    bad.append(z)
                    continue
                if not highprec.is_preserved(M, model):
                    bad.append(z)
    return bad


@pytest.mark.parametrize("name, drift, kick, model, zmax", [
    # M = +I 2.5e-6 after a pole (the island must not be preserved from the pole on)
    ("many-11", ["0.0", "0.8851554622329858", "0.5199874313536643", "-0.2585039506316802",
                 "-0.20690011531840335", "-0.7019903814515651", "0.09094886925595946",
                 "-0.4784624116586951", "-0.2546473137723626", "0.8634235267401613"],
     ["-0.9688344581849229", "0.04823126965965274", "-0.45744219621506144",
      "-0.8181350380237762", "-0.33270708010996275", "0.2547746810965097",
      "-0.6789214071313698", "0.9583792214566773", "0.3485270845296977",
      "0.40165387526796725"], "saddle", 1.0),
    # the barrier's orientation switch at 1/sqrt(-a1 a2 b1) under cancellation
    ("cancel-1e4", ["1e4"], ["1"], "inverted", 1.0),
    ("cancel-1e8", ["1e8"], ["1e8"], "inverted", 1e-10),
    ("cancel-1e2", ["1e2"], ["1"], "inverted", 1.0),
    # an axis crossing 6.3e-10 after a tr M = +2 root (the barrier reversed in between)
    ("many-18", ['0.0', '0.5231762810878307', '-0.2625282849143462', '0.12222675862367205',
      '0.1916761508771878', '0.8846226451864427', '0.5145166986919285',
      '0.01630174584068489', '0.6827944248516691', '-0.2670601533317336',
      '-0.23177961640253475', '0.9199519215233334', '0.09188402524062811',
      '0.54688115283686', '-0.37110290694292725', '0.830581738834786',
      '0.22546783136656057'],
     ['0.8672744695753984', '-0.06215280631850084', '-0.3211332695243059',
      '-0.4744947581417789', '-0.7935077826693697', '-0.5987142763352327',
      '0.3844854523017014', '-0.7187189279264214', '-0.48256901670950536',
      '-0.1052426379073017', '0.08938079918834485', '-0.2389880709232035',
      '0.5701893583888806', '-0.48643769765060285', '-0.26279995528943445',
      '-0.14998772116448977', '-0.7422605835667542'], "inverted", 6.0),
])
def test_no_false_safe_beside_points_close_to_poles_or_under_cancellation(tmp_path, name, drift,
                                                                        kick, model, zmax):
    assert _false_safes(_method_file(tmp_path, name, drift, kick), model, zmax) == []


def test_m_equals_identity_just_below_a_pole(tmp_path):
    """Symmetric splitting with a 1e8 drift: M = +I 1.35e-8 (relative) below the pole is
    the first boundary, not the pole."""
    path = tmp_path / "cancel-sym.yaml"
    path.write_text("name: cancel-sym\nkind: splitting\norder: 1\nsource: generated\n"
                    "symmetric: true\n"
                    "drift: ['0.603570324503159', '100000000.0', '0.43674928304255944', "
                    "\"1 - 2*(0.603570324503159 + 100000000.0 + 0.43674928304255944)\"]\n"
                    "kick: ['0.33317498606281704', '1.0', "
                    "\"1/2 - (0 + 0.33317498606281704 + 1.0)\"]\n")
    method, _ = resolve(str(path))
    adv = advise(method, Modes.from_arrays({"saddle": [1.0]}), 1.0, 2e-8)
    with mpmath.workdps(50):
        Mfun = mp_transfer(mp_method(str(path), None, None, 50))
        root = highprec.refine_root(lambda x: Mfun(x, "saddle")[0, 0] - 1,
                                    mpmath.mpf("9.99999980e-9"), mpmath.mpf("9.99999982e-9"))
    assert adv.h_max <= float(root)
    assert _false_safes(str(path), "saddle", 2e-8) == []


coefficient = st.floats(-1.0, 1.0, allow_nan=False).map(lambda x: repr(round(x, 6)))


#: The draws of the random-splitting property.
RANDOM_SPLITTING = {"drift": st.lists(coefficient, min_size=2, max_size=6), "data": st.data(),
                    "big": st.sampled_from([None, "1e3", "1e6", "-1e5"]),
                    "model": st.sampled_from(["saddle", "inverted"])}


@settings(max_examples=12, deadline=None, suppress_health_check=list(HealthCheck))
@given(**RANDOM_SPLITTING)
def test_random_splittings_near_their_points(tmp_path_factory, drift, data, big, model):
    """Every draw is a valid method file (one more drift than kicks, each list completed to
    a consistent sum), so whatever loading it raises fails the property."""
    kick = data.draw(st.lists(coefficient, min_size=len(drift) - 1, max_size=len(drift) - 1))
    if big is not None:
        drift = [big, *drift[1:]]
    folder = tmp_path_factory.mktemp("random")
    path = _method_file(folder, "random", drift, kick)
    assert _false_safes(path, model, 4.0) == []


def test_the_random_splitting_property_fails_when_loading_fails(tmp_path_factory,
                                                                monkeypatch):
    """A loader that raises on every draw makes the property fail, not pass unexamined
    (the property's own body, drawn as it draws, without shrinking the failure)."""
    def broken(*args, **kwargs):
        raise TypeError("a loader that always fails")

    monkeypatch.setattr(sys.modules[__name__], "resolve", broken)
    body = test_random_splittings_near_their_points.hypothesis.inner_test
    once = settings(max_examples=3, phases=[Phase.generate], database=None, deadline=None,
                    suppress_health_check=list(HealthCheck))(given(**RANDOM_SPLITTING)(body))
    with pytest.raises(TypeError, match="a loader that always fails"):
        once(tmp_path_factory)


def test_offsets_cover_both_sides():
    assert min(OFFSETS) < 0 < max(OFFSETS) and np.isclose(min(abs(o) for o in OFFSETS), 1e-13)


def test_m_equals_identity_under_cancelling_composition_weights(tmp_path):
    """A composition of pefrl with weights +-1e6: the M = +I touch near z = 2.9033627 is
    placed within its stated uncertainty, although the rounding bound of tr M - 2 vanishes
    at a touch (an uncertainty of 2e-11 would miss it by 1e-9); on the saddle the touch is
    the multiplier crossing 1, placed only to the rounding of M_qq - 1 over its slope."""
    path = tmp_path / "comp-cancel.yaml"
    path.write_text("name: comp-cancel\nkind: composition\norder: 1\nsource: generated\n"
                    "base: pefrl\nsymmetric: true\nweights: ['1000000.0', "
                    "'-0.918483869638351', '-0.14219727462268272', '-999999.403516199', "
                    "\"1 - 2*(1000000.0 + -0.918483869638351 + -0.14219727462268272 + "
                    "-999999.403516199)\"]\n")
    assert _false_safes(str(path), "saddle", 3.5) == []

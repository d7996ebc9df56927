"""HMC step limits on the safe side, refusals that say what is wrong, and bounded memory.

* ``stability_h`` of a covariance computed in float64 never exceeds the 50-digit limit
  ``z* sigma_min`` (the eigenvalue's rounding widens beta as advise does), and a limit is
  rounded towards 0 (bcss3 at sigma 1: ``|tr M| <= 2`` at 50 digits at the value returned).
* A positive definite precision whose smallest eigenvalue float64 cannot resolve is refused
  as undecided (not "negative"), naming ``file::$.system.precision``.
* An ``L = floor(T/h)`` beyond :data:`stepsafe.core.hmc.MAX_TRAJECTORY_STEPS` is said to be
  capped; frequencies whose steps overflow are refused; near the float64 limit the step at
  target still reaches the target.
* Many modes: every one-step evaluation stays within :data:`CHUNK_ELEMENTS` (memory grows
  with the number of modes, not with modes x grid steps).
"""

from __future__ import annotations

import json
from types import MappingProxyType

import mpmath as mp
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from reference_methods import mp_transfer

from stepsafe import hmc
from stepsafe.core import hmc as core
from stepsafe.exceptions import StepsafeError

#: A 5x5 covariance of condition 5.7e11 at scale 1e-140: float64's smallest standard
#: deviation lies 3e-6 relative above the 50-digit one, so a stability limit not widened by
#: the eigenvalue's rounding would exceed the true one.
C28 = [[7.7996191966714555e-140, -1.1635116590740418e-139, -8.299835009371132e-140,
        -5.724956791330007e-140, 1.212491073576497e-139],
       [-1.1635116590740418e-139, 1.7366858249790233e-139, 1.2378221579697713e-139,
        8.56739092927553e-140, -1.81025788493934e-139],
       [-8.299835009371132e-140, 1.2378221579697713e-139, 8.833200752338848e-140,
        6.0836450105753e-140, -1.2897755950149326e-139],
       [-5.724956791330007e-140, 8.56739092927553e-140, 6.0836450105753e-140,
        4.275265647564987e-140, -8.940670304562188e-140],
       [1.212491073576497e-139, -1.81025788493934e-139, -1.2897755950149326e-139,
        -8.940670304562188e-140, 1.8871716515659674e-139]]


def _mp_eigenvalues(matrix) -> list:
    with mp.workdps(50):
        A = mp.matrix([[mp.mpf(float(x)) for x in row] for row in matrix])
        values = mp.eigsy(A)[0]
        return [values[i] for i in range(len(matrix))]


def _ill_conditioned(n: int, cond: float, scale: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    C = (Q * (np.geomspace(1.0, cond, n) * scale)) @ Q.T
    return 0.5 * (C + C.T)


@pytest.mark.parametrize("matrix", [C28, _ill_conditioned(4, 3e11, 1.0, 1),
                                    _ill_conditioned(6, 1e10, 1e100, 2)],
                         ids=["c28", "cond3e11", "cond1e10"])
def test_covariance_stability_limit_is_below_the_50_digit_one(matrix):
    """Verlet is stable for z < 2: the true limit is 2 sigma_min (the smallest standard
    deviation, sqrt of the covariance's smallest eigenvalue at 50 digits)."""
    row = hmc(["verlet"], system={"covariance": np.asarray(matrix).tolist()},
              trajectory_steps=5).rows[0]
    with mp.workdps(50):
        truth = 2 * mp.sqrt(min(_mp_eigenvalues(matrix)))
        assert mp.mpf(row.stability_h) <= truth
        assert mp.mpf(row.structure_h) <= truth
        # below by the eigenvalue's rounding bound (16 n eps cond / 4 relative), not more
        assert mp.mpf(row.stability_h) > truth * (1 - mp.mpf("0.02"))


@pytest.mark.parametrize("name", ["bcss3", "verlet", "yoshida4", "mclachlan2-min"])
def test_stability_limit_keeps_the_trace_within_2_at_50_digits(name):
    row = hmc([name], sigma=[1.0]).rows[0]
    M = mp_transfer(name)
    with mp.workdps(50):
        for h in (row.stability_h, row.structure_h, row.h_target):
            m = M(mp.mpf(h), "oscillator")
            assert abs(m[0, 0] + m[1, 1]) <= 2, (name, h)


def test_printed_limits_are_rounded_towards_zero(run_json, run):
    data = run_json("hmc", "--sigma", "1", "--methods", "bcss3")
    row = data["methods"][0]
    code, out, _ = run("hmc", "--sigma", "1", "--methods", "bcss3")
    assert code == 0
    cells = [c.strip() for c in next(line for line in out.splitlines()
                                     if "bcss3" in line and "│" in line).split("│")]
    shown = float(cells[4].split()[0])
    assert shown < row["stability_h"]
    assert float(cells[5]) < row["h_target"]


P6 = [[1310996406399372.2, 308136343078985.2, -355661748304641.9, 32097991760595.977],
      [308136343078985.2, 72426215058071.52, -83591231477556.1, 7547384899692.627],
      [-355661748304641.9, -83591231477556.1, 96494083744271.9, -8702355296871.494],
      [32097991760595.977, 7547384899692.627, -8702355296871.494, 790844613728.6378]]


def test_positive_definite_precision_is_not_called_negative(tmp_path, run):
    """P6 has every eigenvalue >= 1 at 50 digits, condition 1.5e15: float64 cannot decide
    the sign of the smallest, which is what the refusal says, naming file and key."""
    assert min(_mp_eigenvalues(P6)) > 1
    scene = tmp_path / "p6.yaml"
    scene.write_text(json.dumps({"system": {"precision": P6}}))
    code, _, err = run("hmc", str(scene), "--methods", "verlet")
    assert code == 2
    line, = err.strip().splitlines()
    assert f"{scene}::$.system.precision:" in line
    assert "within rounding of 0" in line and "negative" not in line
    with pytest.raises(StepsafeError, match="not decided") as caught:
        hmc(["verlet"], system={"precision": P6})
    assert caught.value.where == "system::$.system.precision"


def test_negative_precision_is_called_negative_with_its_key():
    with pytest.raises(StepsafeError, match="negative eigenvalue") as caught:
        hmc(["verlet"], system={"precision": [[1.0, 0.0], [0.0, -1.0]]})
    assert caught.value.where == "system::$.system.precision"


def test_inverted_mode_given_directly_is_not_called_a_precision():
    with pytest.raises(StepsafeError, match="not modes of a Gaussian target") as caught:
        hmc(["verlet"], sigma=[1.0], inverted_beta=[1.0])
    assert "precision" not in caught.value.message.split(":")[-1]


def test_capped_trajectory_length_is_said():
    """sigma 1e-150 with T = 5: L = T/h ~ 3.6e150 at h at target, capped at 10^12."""
    report = hmc(["verlet"], sigma=[1e-150, 1.0], length=5.0)
    row = report.rows[0]
    assert row.steps == core.MAX_TRAJECTORY_STEPS
    assert any("capped" in n and "h at target" in n for n in row.notes)
    assert any("capped" in n for n in report.to_dict()["methods"][0]["notes"])
    plain = hmc(["verlet"], sigma=[1.0], length=5.0).rows[0]
    assert not any("capped" in n for n in plain.notes)


def test_overflowing_steps_are_refused(run):
    code, out, err = run("hmc", "--sigma", "1e308", "--methods", "verlet")
    assert code == 2 and not out
    assert len(err.strip().splitlines()) == 1 and "sigma" in err
    with pytest.raises(StepsafeError, match="normal range"):
        hmc(["verlet"], sigma=[5e307])


def test_step_at_target_reaches_the_target_near_the_float64_limit():
    """At sigma 1e307 (steps near 1e307) the search grid must not overflow."""
    for row in hmc(["verlet", "bcss3"], sigma=[1e307], trajectory_steps=10).rows:
        assert row.acceptance >= 0.8
        assert row.h_target <= row.stability_h
        assert row.stability_h <= 2e307 if row.method == "verlet" else True


def test_many_modes_evaluate_in_bounded_pieces(monkeypatch):
    """No one-step evaluation is larger than the chunk (nor the jitter rule's samples),
    whatever the number of modes; the peak search bins the slow ones."""
    sizes = []
    real = core.one_step

    def counted(method, z):
        sizes.append(np.size(z))
        return real(method, z)

    monkeypatch.setattr(core, "one_step", counted)
    monkeypatch.setattr(core, "CHUNK_ELEMENTS", 4096)
    sigma = np.geomspace(1e-3, 1.0, 6000)
    row = hmc(["verlet"], sigma=sigma, trajectory_steps=10, step=1e-4).rows[0]
    assert row.h_target is not None and row.acceptance >= 0.8
    assert max(sizes) <= max(4096, core.JITTER_SAMPLES * core.JITTER_MODES)
    values, counts = core._binned(*core._distinct(1.0 / sigma))
    assert values.size <= core.PEAK_MODES + core.PEAK_BINS and counts.sum() == sigma.size


def test_api_numpy_scalars_sparse_and_frozen_rows():
    import scipy.sparse as sp

    row = hmc(["verlet"], sigma=[1.0, 0.5], target_accept=np.float32(0.9),
              jitter=np.float32(0.1), trajectory_steps=5, step=0.3).rows[0]
    assert row.h_target is not None
    errors = row.at_step["largest_errors"]
    assert isinstance(errors, tuple) and all(isinstance(e, MappingProxyType) for e in errors)
    with pytest.raises(TypeError):
        errors[0]["expected_error"] = 0.0
    sparse = hmc(["verlet"], system={"covariance": sp.csr_matrix(np.diag([1.0, 4.0, 9.0]))})
    # sigma_min = 1 exactly (diagonal): Verlet's limit z = 2 less its float64 uncertainty
    assert 2.0 * (1 - 1e-12) < sparse.rows[0].stability_h < 2.0


@pytest.mark.parametrize("matrix", [C28, _ill_conditioned(4, 3e11, 1.0, 1)],
                         ids=["c28", "cond3e11"])
@pytest.mark.parametrize("near_the_limit", [True, False])
def test_a_design_is_stable_for_the_true_frequencies_of_a_covariance(matrix, near_the_limit):
    """design widens each frequency by the rounding of the eigenvalue it came from, as hmc
    does. Here float64's smallest standard deviation is 3e-6 and 2e-5 above the 50-digit
    one: a step 1e-7 below the family's limit z = 4 for the float64 frequency is past it
    for the true one, and is refused (b = 1/4 there has |tr M| = 2.0001 at the true
    frequency); a step well inside gets a member with |tr M| <= 2 at 50 digits."""
    from stepsafe import design

    nominal = float(np.sqrt(np.linalg.eigvalsh(np.asarray(matrix)).min()))
    with mp.workdps(50):
        sigma_min = mp.sqrt(min(_mp_eigenvalues(matrix)))
    step = 4 * nominal * (1 - 1e-7) if near_the_limit else float(2.8 * sigma_min)
    system = {"covariance": np.asarray(matrix).tolist()}
    if near_the_limit:
        with pytest.raises(StepsafeError, match="no 2-stage member"):
            design(system=system, step=step)
        return
    b = design(system=system, step=step).params["b"]
    with mp.workdps(50):
        z, bb = mp.mpf(step) / sigma_min, mp.mpf(b)
        assert abs(1 - z ** 2 / 2 + bb * (1 - 2 * bb) * z ** 4 / 4) <= 1


@pytest.mark.parametrize("command", ["hmc", "design"])
def test_a_refused_target_names_the_file_it_came_from(run, tmp_path, command):
    """A scene's or a --modes file's target that HMC cannot take (a sigma whose 1/sigma
    is subnormal, an inverted mode) is one line naming the file and key, exit 2."""
    extra = ["--steps", "10"] if command == "hmc" else ["--step", "1"]
    csv = tmp_path / "modes.csv"
    csv.write_text("sigma\n1e308\n1\n")
    scene = tmp_path / "scene.yaml"
    scene.write_text("modes: [{beta: 1, model: inverted}, {sigma: 1}]\n")
    for args in (["--modes", str(csv)], [str(scene)]):
        code, _, err = run(command, *args, *extra)
        name = csv if args[0] == "--modes" else scene
        assert code == 2 and f"{name}::$.modes:" in err, err
        assert len(err.strip().splitlines()) == 1
    code, _, err = run(command, "--modes", str(csv), "--sigma", "2", *extra)
    assert code == 2 and "modes.csv" not in err  # (two sources: neither is named)


def test_a_trajectory_beyond_a_million_steps_is_approximate():
    """L theta in float64 carries an error of about eps L pi: at L = 1e12 (a length capped)
    the 4th digit of the acceptance (0.956151 against 0.956238 at 60 digits),
    so such figures say approximate; up to 1e6 steps they are exact."""
    far = hmc(["bcss3"], sigma=[1e-150, 1e150], length=1e150)
    assert any("approximate" in note for note in far.rows[0].notes) and far.approximate
    near = hmc(["bcss3"], sigma=[1.0, 0.5], trajectory_steps=10**6, step=0.3)
    assert near.rows[0].at_step["approximate"] is False and not near.approximate


def test_unstable_jittered_steps_raise_no_floating_point_warning():
    """sigma = 1e-100 at step 1 (z = 1e100): the one-step matrices overflow, which reads
    as unstable (acceptance 0), and no RuntimeWarning reaches the caller."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        report = hmc(["verlet", "bcss2", "bcss3"], sigma=[1e-100, 1.0], jitter=0.1, step=1.0)
    for row in report.rows:
        assert row.at_step["acceptance"] == 0.0 and row.at_step["expected_error"] == np.inf


@pytest.mark.slow
@settings(max_examples=10, deadline=None)
@given(exponent=st.integers(-960, 960), log_z=st.floats(-3.0, 300.0),
       shape=st.lists(st.floats(1.0, 100.0), max_size=3),
       jitter=st.sampled_from((0.0, 0.1, 0.5)),
       trajectory=st.sampled_from(("any", "steps", "length")),
       name=st.sampled_from(("verlet", "bcss2", "bcss3", "yoshida4")))
def test_hmc_at_any_scale_and_step_is_scale_free_and_warns_of_nothing(
        exponent, log_z, shape, jitter, trajectory, name):
    """sigma, the step and the length scaled by 2^e (exactly, so z = beta h and L =
    floor(T / h) are the unit target's to the bit) give the unit target's figures, for
    any z up to 1e300, with every floating-point warning an error; where every jittered
    step of the fastest mode is past its stability limit (z (1 - J) > 10 for these
    methods) the acceptance bound over every L is 0 (that mode's rho is infinite)."""
    import warnings

    scale = 2.0 ** exponent
    step = 10.0 ** log_z
    assume(step * scale < 1e300 and 100.0 * scale < 1e300 and scale > 1e-290)
    base = [1.0, *shape]
    extra = {"any": {}, "steps": {"trajectory_steps": 10}, "length": {"length": 3.0}}[trajectory]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        unit = hmc([name], sigma=base, step=step, jitter=jitter, **extra).rows[0]
        scaled_extra = {k: v * scale if k == "length" else v for k, v in extra.items()}
        scaled = hmc([name], sigma=[s * scale for s in base], step=step * scale,
                     jitter=jitter, **scaled_extra).rows[0]
    assert scaled.at_step["acceptance"] == pytest.approx(unit.at_step["acceptance"],
                                                         abs=1e-12)
    assert scaled.stability_h / scale == unit.stability_h
    assert scaled.h_target / scale == pytest.approx(unit.h_target, rel=1e-12)
    if step * (1.0 - jitter) > 10.0 and trajectory == "any":
        assert unit.at_step["acceptance"] == scaled.at_step["acceptance"] == 0.0

"""Verdicts at temperature against ensembles integrated in the test: a cubic and a quartic
oscillator (``check`` of the thermal analysis at one step, velocity Verlet and PEFRL), and
the FPU-alpha chain of ``examples/fpu-alpha.yaml`` at two temperatures through ``stepsafe
check --kT``.

Each step is also run by the method written out in numpy (:mod:`thermal_support`: Verlet,
and PEFRL from its published coefficients) from the test's own Boltzmann draws (exact 1-D
draws by quadrature; Metropolis for the chain), 2000 trajectories, for as many steps as the
analysis ran, with two failure counts that need nothing of stepsafe:

* *blown up*: a state not finite or a coordinate beyond 1000 times the start's largest;
* *grown*: blown up, or the energy above the minimum past ``4 rho0^2`` times its start,
  ``rho0`` the energy ratio of the method's invariant ellipse on the oscillator at the
  minimum's own fastest ``z0 = omega_0 h`` (Verlet's ``1 / (1 - z0^2 / 4)``; multiplied
  out here from the method's kicks and drifts).

The analysis counts a trajectory failed when it leaves ``10 sqrt(rho)`` times the start's
extent or its energy passes ``4 rho^2`` times its start, with ``rho`` taken at the largest
instantaneous frequency the run meets (above ``omega_0``: a looser energy test than
*grown*, a tighter distance than *blown up*). So its failure fraction should lie between
the two counts: within 4 binomial standard errors (plus 2 of 500) of that interval. A step
called UNSAFE in a band is one where the test's own run fails too; a step called SAFE is
one where the test's own run loses no more than the 1% threshold allows (2.3 standard
errors of 2000)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from support import method
from thermal_support import (
    PEFRL_DRIFTS,
    PEFRL_KICKS,
    boltzmann_1d,
    cubic,
    fpu_energy,
    fpu_force,
    metropolis,
    pefrl,
    quartic,
    verlet,
)

from stepsafe.systems.thermal.bands import clopper_pearson
from stepsafe.systems.thermal.limit import thermal_check

ROOT = Path(__file__).resolve().parent.parent
#: The test's own trajectories.
OWN = 2000
#: The user's run, in steps: the ensembles run all of it (it is within their cap).
RUN = 2000
#: Most the test's own run may lose at a SAFE step: the 1% threshold and 2.3 standard errors.
SAFE_LOSS = 0.01 + 2.3 * math.sqrt(0.01 * 0.99 / OWN)


def _tolerance(p: float, m: int) -> float:
    """4 binomial standard errors of the difference of fractions from m and OWN draws, at
    p (at least 1/4 of a failure in each), plus 2/m."""
    p = min(max(p, 0.25 / OWN), 1 - 0.25 / OWN)
    return 4 * math.sqrt(p * (1 - p) * (1 / m + 1 / OWN)) + 2 / m


def _ellipse_ratio(name: str, z: float) -> float:
    """``rho0``: the largest over the smallest energy ``(q^2 + p^2) / 2`` on the invariant
    ellipse of the method's map of the oscillator at z, its one-step matrix M multiplied
    out here from the recipe (kicks and drifts) and the ellipse ``x^T Q x = 1`` with
    ``Q = [[-c, (a - d)/2], [(a - d)/2, b]]`` for ``M = [[a, b], [c, d]]`` (``M^T Q M = Q``
    when det M = 1); inf where ``|tr M| >= 2``. Verlet's is ``1 / (1 - z^2/4)``."""
    def drift(a):
        return np.array([[1.0, a * z], [0.0, 1.0]])

    def kick(b):
        return np.array([[1.0, 0.0], [-b * z, 1.0]])

    if name == "verlet":
        ops = [kick(0.5), drift(1.0), kick(0.5)]
    else:
        ops = [op for a, b in zip(PEFRL_DRIFTS, PEFRL_KICKS) for op in (drift(a), kick(b))]
        ops.append(drift(PEFRL_DRIFTS[-1]))
    M = np.eye(2)
    for op in ops:
        M = op @ M
    (a, b), (c, d) = M
    if not abs(a + d) < 2:
        return math.inf
    w = np.linalg.eigvalsh(np.array([[-c, (a - d) / 2], [(a - d) / 2, b]]))
    return float(w[1] / w[0]) if w[0] > 0 else float(w[0] / w[1])


def _own_counts(step, force, energy, q0, p0, h, steps, rho0):
    """The fractions *blown up* and *grown* (module docstring) of the test's own run of
    ``step`` (:func:`thermal_support.verlet` or :func:`thermal_support.pefrl`)."""
    qs = q0.reshape(q0.shape[0], -1)
    far = 1e3 * np.max(np.abs(qs))
    E0 = energy(q0, p0)

    def blown(q, p):
        return ~np.all(np.abs(q.reshape(q.shape[0], -1)) <= far, axis=1)

    def grown(q, p):
        return blown(q, p) | ~(energy(q, p) <= 4 * rho0 ** 2 * E0)

    return (float(step(force, q0.copy(), p0.copy(), h, steps, blown).mean()),
            float(step(force, q0.copy(), p0.copy(), h, steps, grown).mean()))


def _judged_against_own(safe, failures, trajectories, blown, grown, in_band):
    """The verdict and the analysis's failure count against the test's own two counts."""
    mine = failures / trajectories
    assert blown <= grown
    assert blown - _tolerance(blown, trajectories) <= mine <= \
        grown + _tolerance(grown, trajectories), (mine, blown, grown)
    if safe:
        assert grown <= SAFE_LOSS, (blown, grown)
    if clopper_pearson(round(grown * OWN), OWN)[0] > 0.01:
        assert not safe  # a step the test's own run sees failing is never SAFE
    if in_band:  # an UNSAFE verdict from a band: the test's own run fails there too
        assert clopper_pearson(round(grown * OWN), OWN)[0] > 0.01, grown


def _oscillator(kind, c):
    """The potential, H(q, p) and the force of ``q^2/2 + c q^3/3`` or ``q^2/2 + c q^4/4``
    written here, and where the cubic's well ends (its barrier)."""
    power = 3 if kind == "cubic" else 4

    def energy(q, p):
        return q * q / 2 + c * q ** power / power + p * p / 2

    def force(q):
        return -(q + c * q ** (power - 1))

    pot = cubic(c) if kind == "cubic" else quartic(c)
    return pot, energy, force, (-1 / c if kind == "cubic" else None)


#: More of the same, in the slow set (about 2 s each).
SLOW = [pytest.mark.slow]


@pytest.mark.parametrize("name, kind, c, kT, z, verdict", [
    # U = q^2/2 + q^3/30: barrier at q = -10, 16.7 high; kT = 0.05 and 0.5
    ("verlet", "cubic", 0.1, 0.05, 1.6, "safe"),  # between the 4:1 and 3:1 bands
    ("verlet", "cubic", 0.1, 0.05, 1.42, "band"),  # above 4:1 (sqrt 2): energy grows, bounded
    pytest.param("verlet", "cubic", 0.1, 0.05, 0.8, "safe", marks=SLOW),
    pytest.param("verlet", "cubic", 0.1, 0.05, 1.72, "band", marks=SLOW),  # most escape
    pytest.param("verlet", "cubic", 0.1, 0.5, 1.2, "safe", marks=SLOW),
    pytest.param("verlet", "cubic", 0.1, 0.5, 1.45, "band", marks=SLOW),
    pytest.param("verlet", "cubic", 0.1, 0.5, 1.75, "band", marks=SLOW),
    # U = q^2/2 + q^4/40: stiffening; kT = 0.05 and 0.5
    ("verlet", "quartic", 0.1, 0.5, 0.8, "safe"),
    ("verlet", "quartic", 0.1, 0.5, 1.2, "band"),  # above the linear limit at T, 1.09, too
    pytest.param("verlet", "quartic", 0.1, 0.5, 1.6, "band", marks=SLOW),
    pytest.param("verlet", "quartic", 0.1, 0.05, 0.8, "safe", marks=SLOW),
    pytest.param("verlet", "quartic", 0.1, 0.05, 1.6, "safe", marks=SLOW),
    pytest.param("verlet", "quartic", 0.1, 0.05, 1.85, "band", marks=SLOW),
    # PEFRL (4th order): safe far up; above its linear limit at temperature (about 1.58 on
    # the quartic at kT = 0.5) the check says UNSAFE where no failure shows in 2000 steps
    ("pefrl", "cubic", 0.1, 0.5, 2.05, "safe"),
    pytest.param("pefrl", "quartic", 0.1, 0.5, 1.5, "safe", marks=SLOW),
    pytest.param("pefrl", "quartic", 0.1, 0.5, 1.9, "linear", marks=SLOW)])
def test_oscillator_verdicts_at_temperature_against_the_tests_own_ensembles(name, kind, c, kT,
                                                                            z, verdict):
    """thermal_check at z (omega_0 = 1, a run of RUN steps): SAFE where the test's own run
    of the method loses nothing the threshold does not allow, UNSAFE in a band where its
    trajectories blow up or their energy grows past the linear map's bound, at the fraction
    the check's ensemble reports (module docstring), and UNSAFE above the linear limit at
    temperature, a bound on the frequencies the run meets, whatever the ensemble shows."""
    pot, energy, force, barrier = _oscillator(kind, c)
    check = thermal_check(method(name), pot, kT, z, steps=RUN)
    assert check.safe is (verdict == "safe"), check.reasons
    (_, probe), = check.probes
    assert probe.steps == RUN
    rng = np.random.default_rng(11)
    reach = 40 * math.sqrt(kT)
    q0 = boltzmann_1d(lambda s: energy(s, 0.0), kT, OWN, rng,
                      barrier if barrier is not None else -reach, reach)
    p0 = rng.standard_normal(OWN) * math.sqrt(kT)
    blown, grown = _own_counts(verlet if name == "verlet" else pefrl, force, energy, q0, p0,
                               z, probe.steps, _ellipse_ratio(name, z))
    _judged_against_own(check.safe, probe.failures, probe.trajectories, blown, grown,
                        verdict == "band")
    if verdict == "band":
        assert any("in a resonance band" in r or "failures not excluded" in r
                   for r in check.reasons)
    if verdict == "linear":
        assert check.reasons == ("above the linear limit at temperature",)


ALPHA = 0.25
#: The fastest mode of the 4-mass chain at rest, 2 sin(4 pi / 10).
OMEGA_0 = 2 * math.sin(0.4 * math.pi)


@pytest.mark.slow  # a scene's analysis at temperature (about 7 s) and the test's own runs
@pytest.mark.parametrize("kT, h, verdict", [
    (0.02, 0.7, "safe"), (0.02, 1.03, "band"), (0.08, 0.7, "safe"), (0.08, 0.95, "band")])
def test_fpu_scene_verdicts_at_two_temperatures_against_the_tests_own_ensembles(
        run, kT, h, verdict):
    """``stepsafe check examples/fpu-alpha.yaml --kT kT --steps 2000 --step h``: exit 0
    at h = 0.7 (two thirds of the 0 K limit 1.0515) at both temperatures; exit 1 at 0.95
    for kT = 0.08 and at 1.03 for kT = 0.02, steps the 0 K check calls SAFE. The test's own
    Verlet, from its own Metropolis draws of the chain at kT, agrees (module docstring)."""
    scene = str(ROOT / "examples" / "fpu-alpha.yaml")
    code, _, err = run("check", scene, "--step", str(h))
    assert code == 0, err  # safe at 0 K
    code, out, err = run("check", scene, "--step", str(h), "--kT", str(kT), "--steps",
                         str(RUN), "--json")
    assert code == (0 if verdict == "safe" else 1), err
    entry = json.loads(out)["checks"][0]
    thermal = entry["thermal"]
    assert thermal["safe"] is entry["safe"] is (verdict == "safe")
    assert thermal["kT"] == kT and thermal["run"]["steps"] == RUN
    (minimum,) = thermal["minima"]
    (probe,) = minimum["probes"]
    assert probe["target"] == "whole system" and probe["h"] == h and probe["steps"] == RUN

    n = 4
    ref, _ = metropolis(lambda q: fpu_energy(q, ALPHA), kT, np.zeros(n), 400, 6000,
                        0.7 * math.sqrt(kT), np.random.default_rng(31), 30)
    rng = np.random.default_rng(32)
    q0 = ref[rng.choice(ref.shape[0], OWN, replace=False)]
    p0 = rng.standard_normal(q0.shape) * math.sqrt(kT)

    def energy(q, p):
        return fpu_energy(q, ALPHA) + 0.5 * np.sum(p * p, axis=1)

    blown, grown = _own_counts(verlet, lambda q: fpu_force(q, ALPHA), energy, q0, p0, h,
                               probe["steps"], _ellipse_ratio("verlet", h * OMEGA_0))
    _judged_against_own(entry["safe"], probe["failures"], probe["trajectories"], blown,
                        grown, verdict == "band")

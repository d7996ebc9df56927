"""``hmc`` on ``potential:`` targets: its warm-up draws represent the target (estimates
agree with those on exact draws), and inputs that have no target are refused.

The reference draws exactly from the target (the banana and Neal's funnel have closed-form
samplers), gives each draw a fresh unit-mass momentum, runs L steps of velocity Verlet
(kick h/2, drift h, kick h/2) at one step per trajectory (uniform in h (1 +- J) when
jittered, as Stan's ``stepsize_jitter``), and averages min(1, e^-dH) (a proposal with
dH > 1000 or a non-finite state is divergent). Its standard error is that of an average of
independent terms. Nothing here calls stepsafe's samplers or integrators.
"""

from __future__ import annotations

import itertools
import json
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, Phase, example, given, settings
from hypothesis import strategies as st

from stepsafe.cli import main


def _hmc_json(scene: str, *args: str, verified: bool | None = True) -> dict:
    """``hmc --json`` on the scene: the report, printed either way; exit 0 for draws that
    pass the convergence diagnostics, 1 for draws that fail them (``verified`` False; None:
    either)."""
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "target.yaml"
        path.write_text(scene)
        result = CliRunner().invoke(main, ["hmc", str(path), *args, "--json"])
        assert result.exit_code in (0, 1), result.stderr
        data = json.loads(result.stdout)
        assert result.exit_code == (0 if data["verified"] else 1), result.stderr
        assert verified is None or data["verified"] is verified, data["unverified"]
        return data


def _verlet_energy_errors(grad, energy, q, h, steps: int, rng: np.random.Generator):
    """dH of L Verlet steps from (q, p ~ N(0, I)); h a scalar or one step per draw."""
    h = np.broadcast_to(np.asarray(h, float), q.shape[:1])[:, None]
    p = rng.normal(size=q.shape)
    h0 = energy(q) + (p * p).sum(-1) / 2
    with np.errstate(all="ignore"):
        g = grad(q)
        for _ in range(steps):
            p = p - 0.5 * h * g
            q = q + h * p
            g = grad(q)
            p = p - 0.5 * h * g
        dh = energy(q) + (p * p).sum(-1) / 2 - h0
    return np.where(np.isfinite(dh), dh, np.inf)


def _summary(dh: np.ndarray) -> tuple[float, float, float]:
    """(acceptance, its standard error, divergent share)."""
    acc = np.minimum(1.0, np.exp(-dh))
    return float(acc.mean()), float(acc.std() / math.sqrt(acc.size)), float((dh > 1000).mean())


def _agrees_within_4_se(row: dict, dh: np.ndarray) -> float:
    """Assert the row's acceptance is that of the energy errors ``dh`` within 4 combined
    standard errors; the divergent share of ``dh``."""
    acc, se, div = _summary(dh)
    assert abs(row["acceptance"] - acc) < 4 * math.hypot(se, row["acceptance_se"]), \
        (row["acceptance"], row["acceptance_se"], acc, se)
    return div


# ------------------------------------------------------------------------------- banana

def _banana(c: float):
    def energy(q):
        return q[..., 0] ** 2 / 2 + (q[..., 1] - c * q[..., 0] ** 2) ** 2 / 2

    def grad(q):
        x, r = q[..., 0], q[..., 1] - c * q[..., 0] ** 2
        return np.stack([x - 2 * c * x * r, r], -1)

    def draw(n, rng):
        x = rng.normal(size=n)
        return np.stack([x, c * x * x + rng.normal(size=n)], -1)

    return energy, grad, draw


BANANA_1 = (
    "system:\n"
    '  potential: "x**2/2 + (y - c*x**2)**2/2"\n'
    "  q: [x, y]\n"
    "  parameters: {c: 1.0}\n"
    "  start: [0, 0]\n"
)


def test_reference_banana_acceptance_is_one_at_a_vanishing_step():
    """The reference itself: at h = 1e-4 the energy error is O(h^2) and every proposal is
    accepted to within 1e-6; the exact draws have the banana's moments (E y = c)."""
    energy, grad, draw = _banana(1.0)
    rng = np.random.default_rng(0)
    q = draw(20_000, rng)
    assert abs(q[:, 1].mean() - 1.0) < 0.05
    acc, _, div = _summary(_verlet_energy_errors(grad, energy, q, 1e-4, 10, rng))
    assert acc > 1 - 1e-6 and div == 0


@pytest.mark.slow
def test_hmc_acceptance_on_a_jittered_banana_agrees_with_exact_draws():
    """The estimate at h at target must agree with the exact-draw reference within 4
    combined standard errors."""
    row = _hmc_json(BANANA_1, "--steps", "10", "--methods", "verlet",
                    "--jitter", "0.2")["methods"][0]
    energy, grad, draw = _banana(1.0)
    rng = np.random.default_rng(5)
    n = 200_000
    h = row["h_target"] * (1 + 0.2 * (2 * rng.random(n) - 1))
    acc, se, div = _summary(_verlet_energy_errors(grad, energy, draw(n, rng), h, 10, rng))
    z = (row["acceptance"] - acc) / math.hypot(row["acceptance_se"], se)
    assert abs(z) < 4, (f"stepsafe {row['acceptance']:.4f} +- {row['acceptance_se']:.4f} "
                        f"(divergent {row['divergent']}), reference {acc:.4f} +- {se:.4f} "
                        f"(divergent {div:.4f}) at h = {row['h_target']}: {z:.1f} SE")


# ------------------------------------------------------------------------------- funnel

FUNNEL = (
    "system:\n"
    '  potential: "v**2/18 + x1**2*exp(-v)/2 + x2**2*exp(-v)/2 + v"\n'
    "  q: [v, x1, x2]\n"
    "  start: [0, 0, 0]\n"
)


def _funnel():
    """Neal's funnel, v ~ N(0, 3^2), x_i | v ~ N(0, e^v), two x's."""
    def energy(q):
        v = q[..., 0]
        return v * v / 18 + (q[..., 1:] ** 2).sum(-1) * np.exp(-v) / 2 + v

    def grad(q):
        v = q[..., :1]
        x = q[..., 1:]
        gv = v / 9 - (x ** 2).sum(-1, keepdims=True) * np.exp(-v) / 2 + 1
        return np.concatenate([gv, x * np.exp(-v)], -1)

    def draw(n, rng):
        v = rng.normal(0, 3, n)
        x = rng.normal(size=(n, 2)) * np.exp(v / 2)[:, None]
        return np.concatenate([v[:, None], x], -1)

    return energy, grad, draw


@pytest.mark.slow
def test_hmc_divergent_share_on_the_funnel_agrees_with_exact_draws():
    """At h = 0.05 the divergent share on the warm-up draws must be within a factor 2 of the
    share on exact draws (binomial noise on 4800 proposals is far smaller)."""
    row = _hmc_json(FUNNEL, "--steps", "10", "--methods", "verlet",
                    "--step", "0.05", verified=False)["methods"][0]["at_step"]
    energy, grad, draw = _funnel()
    rng = np.random.default_rng(0)
    _, _, div = _summary(_verlet_energy_errors(grad, energy, draw(200_000, rng), 0.05, 10, rng))
    assert 0.002 < div < 0.02, div
    assert div / 2 < row["divergent"] < 2 * div, (row, div)


# ------------------------------------------------------------------------------ inputs

def _hmc_code(scene: str, *args: str) -> tuple[int, str]:
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "target.yaml"
        path.write_text(scene)
        result = CliRunner().invoke(main, ["hmc", str(path), *args])
        return result.exit_code, result.stderr


@pytest.mark.slow
@settings(max_examples=3, deadline=None, suppress_health_check=list(HealthCheck),
          phases=(Phase.explicit, Phase.reuse, Phase.generate))
@given(k=st.floats(1.5, 3.0), theta_exp=st.integers(-3, 3))
def test_a_positive_support_target_started_at_its_mode_is_analysed(k, theta_exp):
    """A proper target whose energy is finite at its mode (the start given) is analysed:
    a report (exit 0, or 1 with the draws' failing diagnostic named: R-hat and ESS, or the
    warm-up's divergent transitions where trajectories leave the support near x = 0, whose
    curvature grows without bound), never a refusal."""
    theta = 10.0 ** theta_exp
    scene = ("system:\n"
             f'  potential: "-(k - 1)*log(x) + x/theta"\n'
             "  q: [x]\n"
             f"  parameters: {{k: {k!r}, theta: {theta!r}}}\n"
             f"  start: [{(k - 1) * theta!r}]\n")
    code, err = _hmc_code(scene, "--steps", "10", "--methods", "verlet")
    assert code == 0 or (code == 1 and ("have not converged" in err
                                        or "divergent transitions" in err)), err


@pytest.mark.slow
@settings(max_examples=2, deadline=None, suppress_health_check=list(HealthCheck),
          phases=(Phase.explicit, Phase.reuse, Phase.generate))
@given(d=st.integers(2, 3), flat=st.integers(0, 2))
def test_an_improper_target_is_refused(d, flat):
    """U = sum of x_i^2/2 over every coordinate but one: exp(-U) has infinite mass."""
    flat = flat % d
    names = [f"x{i}" for i in range(d)]
    pot = " + ".join(f"{n}**2/2" for i, n in enumerate(names) if i != flat)
    scene = ("system:\n"
             f'  potential: "{pot}"\n'
             f"  q: [{', '.join(names)}]\n"
             f"  start: [{', '.join('0' for _ in names)}]\n")
    code, err = _hmc_code(scene, "--steps", "10", "--methods", "verlet")
    assert code == 2 and "target.yaml::$.system.potential" in err, (code, err)


def test_an_improper_target_names_the_scene_file_and_key():
    """U without positive curvature along a direction (flat, falling, linear) is refused
    with one line naming the scene file and its potential."""
    for pot, q in (("x**2/2", "[x, y]"), ("-x**2/2", "[x]"), ("x", "[x]")):
        names = q.strip("[]").split(", ")
        scene = ("system:\n"
                 f'  potential: "{pot}"\n'
                 f"  q: {q}\n"
                 f"  start: [{', '.join('0' for _ in names)}]\n")
        code, err = _hmc_code(scene, "--steps", "10", "--methods", "verlet")
        assert code == 2 and "target.yaml::$.system.potential" in err, (pot, code, err)
        assert "improper" in err and len(err.strip().splitlines()) == 1, err


def test_a_proper_target_with_a_degenerate_mode_is_analysed():
    """U = x^4 has no curvature at its mode but is proper (it grows along x): analysed, and
    its draws have the moment E x^2 = Gamma(3/4) / Gamma(1/4) of exp(-x^4) within 4 of its
    standard errors from the draws' effective sample size."""
    scene = ("system:\n"
             '  potential: "x**4"\n'
             "  q: [x]\n"
             "  start: [0.3]\n")
    data = _hmc_json(scene, "--steps", "10", "--methods", "verlet")
    assert data["draws"]["converged"] is True
    from stepsafe.core.hmc_target.draws import sample
    from stepsafe.systems.potential import potential_target

    found = potential_target({"potential": "x**4", "q": ["x"], "start": [0.3]})
    draws = sample(found.target, seed=data["seed"], start=found.start)
    x2 = draws.positions[..., 0] ** 2
    exact = math.gamma(0.75) / math.gamma(0.25)
    se = x2.std() / math.sqrt(draws.effective_size)
    assert abs(x2.mean() - exact) < 4 * se, (x2.mean(), exact, se)


def _reference_split_rhat(x: np.ndarray) -> float:
    """Rank-normalised split R-hat (bulk and folded, the larger), written from the
    published definition with numpy and scipy.stats.norm."""
    from scipy.stats import norm

    def normal_scores(y):
        # ranks 1..S, tied values sharing their mean rank
        values, inverse, counts = np.unique(y, return_inverse=True, return_counts=True)
        below = np.cumsum(counts) - counts
        ranks = (below + (counts + 1) / 2)[inverse.reshape(-1)]
        return norm.ppf((ranks - 3 / 8) / (y.size + 1 / 4)).reshape(y.shape)

    def split(y):
        n = y.shape[1] // 2
        s = np.vstack([y[:, :n], y[:, -n:]])
        w = s.var(axis=1, ddof=1).mean()
        b = n * s.mean(axis=1).var(ddof=1)
        return math.sqrt(((n - 1) / n * w + b / n) / w)

    return max(split(normal_scores(x)), split(normal_scores(np.abs(x - np.median(x)))))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), shift=st.floats(0.0, 2.0), chains=st.integers(1, 8),
       n=st.integers(4, 300))
def test_rhat_agrees_with_its_definition(seed, shift, chains, n):
    """R-hat of normal draws, chains shifted apart or not, equals the definition written in
    the test (the distances from the median tie in pairs: tied values share their rank)."""
    from stepsafe.core.hmc_target.statistics import rhat

    rng = np.random.default_rng(seed)
    x = rng.normal(size=(chains, n)) + shift * np.arange(chains)[:, None]
    assert rhat(x) == pytest.approx(_reference_split_rhat(x), rel=1e-12)


def test_rhat_separates_mixed_from_unmixed_chains():
    """32 chains of 150 independent N(0, 1) draws: R-hat below 1.01; one chain moved by
    3 standard deviations: above it."""
    from stepsafe.core.hmc_target.statistics import rhat

    x = np.random.default_rng(3).normal(size=(32, 150))
    assert rhat(x) < 1.01
    x[0] += 3.0
    assert rhat(x) > 1.01


def test_the_draws_state_their_diagnostics():
    """--json states the draws' R-hat, effective sample size and whether they converged,
    and the text says so; an effective sample size never exceeds m n log10(m n)."""
    data = _hmc_json(BANANA_1, "--steps", "10", "--methods", "verlet")
    d = data["draws"]
    assert 1.0 <= d["rhat"] < 1.1 and 0 < d["effective_size"]
    total = d["chains"] * d["per_chain"]
    assert d["effective_size"] <= total * math.log10(total)
    assert d["converged"] == (d["rhat"] <= 1.01 and d["effective_size"] >= 400)


DOUBLE_WELL = (
    "system:\n"
    '  potential: "10*(x**2 - 4)**2"\n'
    "  q: [x]\n"
    "  start: [0]\n"
)


@pytest.mark.slow
def test_draws_split_between_separated_wells_are_not_converged():
    """U = 10 (x^2 - 4)^2 started on its barrier (160 above the wells): the chains fall into
    either well and never cross, so their R-hat is far above 1.01; hmc says so (JSON, note),
    marks the report unverified and exits 1 after it; --require-converged exits 1 before
    the estimates, naming R-hat, the scene file and key; converged draws exit 0."""
    data = _hmc_json(DOUBLE_WELL, "--steps", "10", "--methods", "verlet", verified=False)
    assert data["draws"]["converged"] is False and data["draws"]["rhat"] > 1.1
    assert any("have not converged" in n for n in data["notes"])
    assert "R-hat" in data["unverified"] and "above 1.01" in data["unverified"]
    code, err = _hmc_code(DOUBLE_WELL, "--steps", "10", "--methods", "verlet",
                          "--require-converged")
    assert code == 1 and "--require-converged" in err and "R-hat" in err, (code, err)
    assert "target.yaml::$.system.potential" in err and len(err.strip().splitlines()) == 1
    code, _ = _hmc_code(BANANA_1, "--steps", "10", "--methods", "verlet",
                        "--require-converged")
    assert code == 0


def _normal_logdensity(q):
    return -0.5 * (q * q).sum(-1)


def _normal_gradient(q):
    return -q


def test_require_converged_refuses_draws_that_fail_a_diagnostic_and_names_it():
    """From Python, require_converged=True raises a StepsafeError naming the diagnostic
    that fails, before any estimate: chains drawn independently from N(0, 1) but shifted
    apart by 3 standard deviations fail R-hat; 4 chains of 50 independent draws (at most
    about 200 effective) fail the effective sample size; 3 draws per chain cannot be
    checked. The same draws are accepted without the keyword (a note says so)."""
    from stepsafe import hmc
    from stepsafe.exceptions import StepsafeError

    rng = np.random.default_rng(11)
    shifted = rng.normal(size=(8, 200, 1)) + 3.0 * np.arange(8)[:, None, None]
    short = rng.normal(size=(4, 50, 1))
    tiny = rng.normal(size=(8, 3, 1))
    kw = dict(logdensity=_normal_logdensity, gradient=_normal_gradient, start=[0.0],
              trajectory_steps=5)
    for draws, named in ((shifted, "R-hat"), (short, "effective sample size"),
                         (tiny, "cannot be checked")):
        with pytest.raises(StepsafeError) as caught:
            hmc(["verlet"], draws=draws, require_converged=True, **kw)
        assert named in str(caught.value) and "require_converged" in str(caught.value)
        assert caught.value.where == "draws"
    report = hmc(["verlet"], draws=short, **kw)
    assert report.draws.converged is False
    assert any("have not converged" in n for n in report.notes)


def test_require_converged_passes_converged_draws():
    """16 chains of 200 independent N(0, 1) draws converge (R-hat at most 1.01, effective
    size above 400): the estimate runs, and its acceptance of Verlet on N(0, 1) at the step
    found agrees with the exact Gaussian one within 4 standard errors."""
    from stepsafe import hmc

    draws = np.random.default_rng(12).normal(size=(16, 200, 1))
    report = hmc(["verlet"], logdensity=_normal_logdensity, gradient=_normal_gradient,
                 start=[0.0], trajectory_steps=5, draws=draws, require_converged=True)
    assert report.draws.converged is True
    row = report.rows[0]
    exact = hmc(["verlet"], sigma=[1.0], trajectory_steps=5, step=row.h_target)
    want = exact.rows[0].at_step["acceptance"]
    got = row.estimate
    assert abs(got.acceptance - want) < 4 * got.acceptance_se, (got.acceptance, want)


def test_require_converged_is_refused_where_nothing_is_drawn():
    from stepsafe import hmc
    from stepsafe.exceptions import StepsafeError

    with pytest.raises(StepsafeError, match="require_converged"):
        hmc(["verlet"], sigma=[1.0], trajectory_steps=5, require_converged=True)
    with pytest.raises(StepsafeError, match="True or False"):
        hmc(["verlet"], logdensity=_normal_logdensity, gradient=_normal_gradient,
            start=[0.0], trajectory_steps=5, require_converged="yes")


# ------------------------------------------------------------ slowly growing potentials

def _log_target(alpha, scale, d, quadratic=0):
    """U = sum of the first ``quadratic`` coordinates^2 / 2 + alpha log(1 + |y / scale|^2)
    over the others: exp(-U) ~ |y|^-(2 alpha) far out, integrable over the k = d -
    quadratic log coordinates iff 2 alpha > k. Its mode (the origin) and Laplace figures."""
    from stepsafe.core.hmc_target.draws import find_mode
    from stepsafe.core.hmc_target.potential import CallablePotential, target

    def energy(q):
        x, y = q[..., :quadratic], q[..., quadratic:] / scale
        return 0.5 * (x * x).sum(-1) + alpha * np.log1p((y * y).sum(-1))

    def gradient(q):
        x, y = q[..., :quadratic], q[..., quadratic:] / scale
        return np.concatenate([x, 2 * alpha * y / (1 + (y * y).sum(-1))[..., None] / scale],
                              axis=-1)

    found = target(CallablePotential(energy, gradient, d))
    return found, find_mode(found, np.full(d, 0.1 * min(scale, 1.0)))


@settings(max_examples=25, deadline=None)
@given(d=st.integers(1, 4), power=st.floats(0.02, 1.0), log_scale=st.floats(-50, 50))
def test_log_growth_too_slow_for_the_dimension_is_improper(d, power, log_scale):
    """alpha log(1 + |q / s|^2) in d dimensions with 2 alpha <= d (power * d, power in
    (0, 1], the limit included: exp(-U) ~ r^-d) is improper: found, at every scale."""
    from stepsafe.core.hmc_target.draws import slow_direction

    found, laplace = _log_target(0.5 * power * d, 10.0 ** log_scale, d)
    slow = slow_direction(found, laplace)
    assert slow is not None and slow.slope <= d * (1 + 1e-9)


@settings(max_examples=25, deadline=None)
@given(d=st.integers(1, 4), nu=st.floats(1.0, 60.0), log_scale=st.floats(-50, 50))
def test_student_t_tails_are_proper(d, nu, log_scale):
    """A Student-t with nu >= 1 degrees of freedom in d dimensions (Cauchy at nu = 1):
    U = (nu + d) / 2 log(1 + |q|^2 / (nu s^2)), exp(-U) ~ r^-(nu + d): never refused."""
    from stepsafe.core.hmc_target.draws import slow_direction

    found, laplace = _log_target(0.5 * (nu + d), math.sqrt(nu) * 10.0 ** log_scale, d)
    assert slow_direction(found, laplace) is None


@settings(max_examples=20, deadline=None)
@given(quadratic=st.integers(1, 3), power=st.floats(0.02, 4.0))
def test_one_slow_coordinate_beside_normal_ones_is_improper_iff_its_tail_diverges(
        quadratic, power):
    """x^2/2 over ``quadratic`` coordinates plus (power / 2) log(1 + y^2): exp(-U) ~ |y|^-power
    integrates over y iff power > 1, whatever the other coordinates (a tube around the y
    axis, not a cone: the normal coordinates do not widen with y)."""
    from stepsafe.core.hmc_target.draws import slow_direction

    found, laplace = _log_target(0.5 * power, 1.0, quadratic + 1, quadratic)
    slow = slow_direction(found, laplace)
    assert (slow is not None) == (power <= 1.0), (power, slow)
    if slow is not None:
        assert slow.neighbourhood == "tube"


@settings(max_examples=25, deadline=None)
@given(quadratic=st.integers(1, 3), height=st.floats(0.01, 100.0),
       log_width=st.floats(-12, 12))
def test_a_potential_bounded_along_a_direction_is_improper(quadratic, height, log_width):
    """|x / w|^2 / 2 over ``quadratic`` coordinates plus ``height * tanh(y^2 / w^2)``: U
    stays below its value at infinity along y (growth alpha -> 0 per factor e), so exp(-U)
    tends to e^-height there and does not integrate, although the curvature at the mode is
    positive in every direction: found flat, or growing slower than the tube's bound 1, at
    every height and at scales 10^-12 to 10^12 (the mode search runs in the target's own
    length scale)."""
    from stepsafe.core.hmc_target.draws import find_mode, flat_direction, slow_direction
    from stepsafe.core.hmc_target.potential import CallablePotential, target

    w = 10.0 ** log_width

    def energy(q):
        x, y = q[..., :quadratic] / w, q[..., quadratic] / w
        return 0.5 * (x * x).sum(-1) + height * np.tanh(y * y)

    def gradient(q):
        x, y = q[..., :quadratic] / w, q[..., quadratic] / w
        gy = height * 2 * y / np.cosh(y * y) ** 2 / w
        return np.concatenate([x / w, np.nan_to_num(gy)[..., None]], axis=-1)

    found = target(CallablePotential(energy, gradient, quadratic + 1))
    laplace = find_mode(found, np.full(quadratic + 1, 0.1 * w))
    assert laplace is not None
    slow = slow_direction(found, laplace)
    assert flat_direction(found, laplace) is not None or (
        slow is not None and slow.slope <= 1.0), (laplace, slow)


def test_a_slowly_growing_improper_target_is_refused_with_file_and_key():
    """U = x^2/2 + log(1 + y^2)/2 (the density ~ 1/|y|), U = log(1 + x^2 + y^2)/10 and
    U = x^2/2 + 4.5 tanh(y^2/9) (bounded along y, positive curvature at the mode), with
    unit or a dense mass (which does not change whether exp(-U) integrates): one line naming
    the scene file and its potential, exit 2; from Python, a StepsafeError naming
    logdensity."""
    from stepsafe import hmc
    from stepsafe.exceptions import StepsafeError

    for pot, mass in itertools.product(("x**2/2 + log(1 + y**2)/2",
                                        "log(1 + x**2 + y**2)/10",
                                        "x**2/2 + 4.5*tanh(y**2/9)"),
                                       ("", "  mass: [[2, 0.5], [0.5, 1]]\n")):
        scene = ("system:\n"
                 f'  potential: "{pot}"\n'
                 "  q: [x, y]\n"
                 + mass +
                 "  start: [0.1, 0.1]\n")
        code, err = _hmc_code(scene, "--steps", "10", "--methods", "verlet")
        assert code == 2 and "target.yaml::$.system.potential" in err, (pot, code, err)
        assert "improper" in err and len(err.strip().splitlines()) == 1, err
    with pytest.raises(StepsafeError) as caught:
        hmc(["verlet"], logdensity=lambda q: -0.1 * np.log1p((q * q).sum(-1)),
            gradient=lambda q: -0.2 * q / (1 + (q * q).sum(-1))[..., None],
            start=[0.1, 0.1, 0.1], trajectory_steps=10)
    assert caught.value.where == "logdensity" and "improper" in str(caught.value)


STUDENT_T3 = (
    "system:\n"
    '  potential: "2*log(1 + x**2/3)"\n'
    "  q: [x]\n"
    "  start: [0.5]\n"
)


def test_a_student_t_with_three_degrees_is_analysed_and_agrees_with_exact_draws():
    """U = 2 log(1 + x^2 / 3), Student-t with nu = 3: not refused (its heavy tail can leave
    R-hat just above 1.01, then marked unverified); the acceptance of
    Verlet at L = 10 at the step found agrees within 4 combined standard errors with the
    test's own Verlet from 200000 exact t draws (numpy's standard_t)."""
    data = _hmc_json(STUDENT_T3, "--steps", "10", "--methods", "verlet", verified=None)
    row = data["methods"][0]
    h = row["h_target"]
    rng = np.random.default_rng(21)
    q = rng.standard_t(3, size=(200_000, 1))
    dh = _verlet_energy_errors(lambda x: 4 * x / (3 + x * x),
                               lambda x: 2 * np.log1p((x * x).sum(-1) / 3), q, h, 10, rng)
    _agrees_within_4_se(row, dh)


# ------------------------------------------------------------------ divergences at target

QUARTIC_5 = (
    "system:\n"
    '  potential: "(a**4 + b**4 + c**4 + d**4 + e**4)/4"\n'
    "  q: [a, b, c, d, e]\n"
    "  start: [0.1, 0.1, 0.1, 0.1, 0.1]\n"
)


@pytest.mark.slow
def test_h_at_target_on_a_light_tailed_target_is_below_where_proposals_diverge():
    """U = sum x_i^4 / 4 in 5 dimensions: nonlinear instability of the trajectories sets in
    below the linear limit of the stiffest draw. Every method's h at target is capped where
    divergent proposals start (``capped_by``), and at that step the test's own Verlet (L =
    10) on 200000 exact draws (|x|^4 / 4 ~ Gamma(1/4, 1), a random sign) diverges on fewer
    than 1 proposal in 1000, with the acceptance the estimate states within 4 combined
    standard errors."""
    data = _hmc_json(QUARTIC_5, "--steps", "10", "--methods", "verlet,bcss2")
    rows = {r["method"]: r for r in data["methods"]}
    for r in rows.values():
        assert r["h_target"] <= r["stability_h"], r
        onset = r["divergence_onset"]
        assert onset["h_divergent"] is None or r["h_target"] <= onset["h_clean"], r
        assert r["divergent"] == 0.0, r
    row = rows["verlet"]
    assert row["capped_by"] == "divergence onset", row
    rng = np.random.default_rng(5)
    q = (4 * rng.gamma(0.25, 1.0, size=(200_000, 5))) ** 0.25
    q *= rng.choice([-1.0, 1.0], size=q.shape)
    dh = _verlet_energy_errors(lambda x: x ** 3, lambda x: (x ** 4).sum(-1) / 4, q,
                               row["h_target"], 10, rng)
    assert _agrees_within_4_se(row, dh) < 1e-3, row["h_target"]


# ------------------------------------------------------------- draws that miss a mode

MIXTURE = (
    "system:\n"
    '  potential: "-log(0.5*exp(-(x + 3)**2/2) + 0.5/0.2*exp(-(x - 3)**2/(2*0.04)))"\n'
    "  q: [x]\n"
    "  start: [-3]\n"
)


def test_an_estimate_off_by_more_than_its_error_is_never_a_verified_answer():
    """An equal mixture of N(-3, 1) and N(3, 0.2^2), started in the wide mode: the warm-up
    chains can miss the narrow mode's weight. Either the estimate at h at target agrees
    within 4 combined standard errors with the test's own Verlet (L = 10) on 200000 exact
    mixture draws, or the report is marked unverified, names the failing diagnostic and
    exits 1 (it is printed all the same)."""
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "target.yaml"
        path.write_text(MIXTURE)
        result = CliRunner().invoke(main, ["hmc", str(path), "--steps", "10", "--methods",
                                           "verlet", "--json"])
    data = json.loads(result.stdout)
    row = data["methods"][0]

    def energy(q):
        x = q[..., 0]
        return -np.log(0.5 * np.exp(-(x + 3) ** 2 / 2)
                       + 0.5 / 0.2 * np.exp(-(x - 3) ** 2 / (2 * 0.04)))

    def grad(q):
        x = q[..., 0]
        a = 0.5 * np.exp(-(x + 3) ** 2 / 2)
        b = 0.5 / 0.2 * np.exp(-(x - 3) ** 2 / (2 * 0.04))
        return ((a * (x + 3) + b * (x - 3) / 0.04) / (a + b))[..., None]

    rng = np.random.default_rng(8)
    narrow = rng.random(200_000) < 0.5
    q = np.where(narrow, 3 + 0.2 * rng.normal(size=narrow.size),
                 -3 + rng.normal(size=narrow.size))[:, None]
    acc, se, _ = _summary(_verlet_energy_errors(grad, energy, q, row["h_target"], 10, rng))
    agrees = abs(row["acceptance"] - acc) < 4 * math.hypot(se, row["acceptance_se"])
    if not agrees:
        assert data["verified"] is False and "R-hat" in data["unverified"], data["unverified"]
        assert result.exit_code == 1 and "not a recommendation" in result.stderr
        assert "R-hat" in result.stderr, result.stderr
    else:
        assert result.exit_code == (0 if data["verified"] else 1), result.stderr


# ------------------------------------------------------------ the Hessian at the mode

@settings(max_examples=30, deadline=None)
@given(log_k=st.floats(-8, 8), log_a=st.floats(-1, 1), c=st.floats(0.1, 1.0),
       m=st.floats(-5, 5), at_mode=st.booleans())
def test_the_laplace_hessian_of_a_callable_banana_is_exact_at_every_scale(
        log_k, log_a, c, m, at_mode):
    """The banana U = x^2/2 + (y - c x^2)^2/2 in x = (X - m k) / k, y = Y / (a k), given as
    numpy callables and started at its mode (m k, 0) or near it: the Hessian of the Laplace
    approximation is the exact one at the mode found (diag(1 / k^2, 1 / (a k)^2) at the
    mode itself) to 1e-6 at every scale k from 1e-8 to 1e8 (its curvature changes within a
    few standard deviations of the mode, so a difference width that does not follow k
    averages the wrong curvature)."""
    from stepsafe.core.hmc_target.draws import find_mode
    from stepsafe.core.hmc_target.potential import CallablePotential, target

    k, a = 10.0 ** log_k, 10.0 ** log_a
    centre = m * k

    def energy(q):
        x, y = (q[..., 0] - centre) / k, q[..., 1] / (a * k)
        return 0.5 * x * x + 0.5 * (y - c * x * x) ** 2

    def gradient(q):
        x, y = (q[..., 0] - centre) / k, q[..., 1] / (a * k)
        r = y - c * x * x
        return np.stack([(x - 2 * c * x * r) / k, r / (a * k)], axis=-1)

    start = np.array([centre, 0.0]) if at_mode else np.array([centre + 0.5 * k, -0.5 * a * k])
    laplace = find_mode(target(CallablePotential(energy, gradient, 2)), start)
    assert laplace is not None and laplace.converged
    # the exact Hessian at the mode found (the search stops within its tolerance of (m k, 0))
    x, y = (laplace.mode[0] - centre) / k, laplace.mode[1] / (a * k)
    assert abs(x) < 1e-3 and abs(y) < 1e-3, laplace.mode
    exact = np.array([[1 - 2 * c * (y - c * x * x) + 4 * c * c * x * x, -2 * c * x / a],
                      [-2 * c * x / a, 1 / (a * a)]]) / k**2
    assert np.abs(laplace.hessian - exact).max() <= 1e-6 * np.abs(exact).max(), (
        laplace.hessian, exact)


# ------------------------------------------------------------ directions of any scale

def _axes_target(energy, gradient, d):
    from stepsafe.core.hmc_target.draws import find_mode
    from stepsafe.core.hmc_target.potential import CallablePotential, target

    found = target(CallablePotential(energy, gradient, d))
    return found, find_mode(found, np.zeros(d))


@settings(max_examples=40, deadline=None)
@given(log_s=st.lists(st.floats(-12, 12), min_size=1, max_size=4))
def test_a_gaussian_with_any_standard_deviation_per_direction_is_proper(log_s):
    """U = sum of q_i^2 / (2 s_i^2) with every s_i from 1e-12 to 1e12 (ratios up to 1e24):
    exp(-U) integrates, so neither the flat-direction nor the slow-growth check finds an
    improper direction (each direction is followed in units of its own standard deviation,
    whatever the others')."""
    from stepsafe.core.hmc_target.draws import flat_direction, slow_direction

    s = 10.0 ** np.array(log_s)
    found, laplace = _axes_target(lambda q: 0.5 * ((q / s) ** 2).sum(-1),
                                  lambda q: q / s**2, s.size)
    assert laplace is not None and laplace.positive_definite
    np.testing.assert_allclose(np.sort(laplace.eigenvalues), np.sort(1 / s**2), rtol=1e-9)
    assert flat_direction(found, laplace) is None
    assert slow_direction(found, laplace) is None


@settings(max_examples=40, deadline=None)
@given(log_a=st.lists(st.floats(-12, 12), min_size=0, max_size=3), log_b=st.floats(-12, 12),
       kind=st.sampled_from(["log", "tanh", "isotropic-log"]))
def test_an_improper_direction_is_found_beside_directions_of_any_scale(log_a, log_b, kind):
    """Quadratic directions of standard deviations a_i beside one improper direction of
    scale b, each from 1e-12 to 1e12: (1/2) log(1 + (y/b)^2) (density ~ 1/|y|),
    4.5 tanh((y/b)^2) (bounded) or log(1 + |q/s|^2)/10 over every coordinate (density
    ~ r^-0.2): found flat or slowly growing at every combination of scales."""
    from stepsafe.core.hmc_target.draws import flat_direction, slow_direction

    a = 10.0 ** np.array(log_a, dtype=float)
    b = 10.0 ** log_b
    k = a.size
    if kind == "isotropic-log":
        s = np.append(a, b)

        def energy(q):
            return 0.1 * np.log1p(((q / s) ** 2).sum(-1))

        def gradient(q):
            return 0.2 * q / s**2 / (1 + ((q / s) ** 2).sum(-1))[..., None]
    else:
        def energy(q):
            x, y = q[..., :k] / a, q[..., k] / b
            tail = 0.5 * np.log1p(y * y) if kind == "log" else 4.5 * np.tanh(y * y)
            return 0.5 * (x * x).sum(-1) + tail

        def gradient(q):
            x, y = q[..., :k] / a, q[..., k] / b
            gy = y / (1 + y * y) if kind == "log" else np.nan_to_num(9 * y / np.cosh(y * y) ** 2)
            return np.concatenate([x / a, (gy / b)[..., None]], axis=-1)

    found, laplace = _axes_target(energy, gradient, k + 1)
    assert laplace is not None
    slow = slow_direction(found, laplace)
    assert flat_direction(found, laplace) is not None or slow is not None, (laplace, slow)


def test_a_gaussian_of_standard_deviations_1_and_1e12_is_analysed_not_refused():
    """x ~ N(0, 1), y ~ N(0, 1e24) with the mass that whitens it: a proper target, analysed
    (exit 0, its draws converged); it is not refused as improper."""
    data = _hmc_json("system:\n"
                     '  potential: "x**2/2 + y**2/(2*s**2)"\n'
                     "  q: [x, y]\n"
                     "  parameters: {s: 1e12}\n"
                     "  start: [0, 0]\n"
                     "  mass: [1, 1.0e-24]\n", "--steps", "10", "--methods", "verlet")
    assert data["laplace"]["beta_min"] == pytest.approx(1.0, rel=1e-9)
    assert data["methods"][0]["h_target"] is not None


# ------------------------------------------------------------ draws that cannot be checked

@settings(max_examples=6, deadline=None)
@given(chains=st.integers(1, 40), per_chain=st.integers(2, 3), spread=st.floats(0.01, 2.0))
def test_given_draws_too_few_per_chain_to_check_are_never_verified(chains, per_chain, spread):
    """Draws with fewer than 4 per chain have no R-hat or effective sample size: the report
    is unverified (saying the convergence cannot be checked), never a recommendation."""
    from stepsafe import hmc

    rng = np.random.default_rng(chains * 7 + per_chain)
    draws = spread * rng.normal(size=(chains, per_chain, 2))
    report = hmc(["verlet"], logdensity=_normal_logdensity, gradient=_normal_gradient,
                 start=[0.0, 0.0], trajectory_steps=5, draws=draws)
    assert report.verified is False and "cannot be checked" in report.unverified
    assert report.to_dict()["verified"] is False


@settings(max_examples=6, deadline=None)
@given(chains=st.integers(1, 8), moving=st.integers(0, 7), per_chain=st.integers(2, 500))
def test_draws_with_a_chain_stuck_at_one_position_are_never_verified(chains, moving,
                                                                     per_chain):
    """A chain whose draws are one position repeated rejected every proposal: however the
    other chains move, and although a constant series reads R-hat 1 and an effective size
    of all its draws, the report is unverified and names the stuck chains."""
    from stepsafe import hmc

    rng = np.random.default_rng(chains * 1000 + per_chain)
    draws = rng.normal(size=(chains + moving, per_chain, 2))
    draws[:chains] = rng.normal(size=(chains, 1, 2))
    report = hmc(["verlet"], logdensity=_normal_logdensity, gradient=_normal_gradient,
                 start=[0.0, 0.0], trajectory_steps=5, draws=draws)
    assert report.verified is False
    assert f"{chains} of {chains + moving} chain(s) stay at one position" in report.unverified
    assert report.to_dict()["draws"]["stuck_chains"] == chains


# ------------------------------------------------------------ the kept run

@settings(max_examples=4, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), keep=st.integers(20, 60))
def test_kept_draws_short_of_the_limits_are_extended_and_diagnosed_over_all(seed, keep):
    """Chains whose kept draws fall short of the effective-size limit (8 chains of 20 to 60
    draws cannot reach 400) run on: the kept run doubles while it fails narrowly, up to 4
    times the draws asked for, and the R-hat and effective size stated are those of every
    draw kept (recomputed here from the draws and their energies)."""
    from stepsafe.core.hmc_target.draws import diagnostics, sample
    from stepsafe.core.hmc_target.potential import CallablePotential, target

    found = target(CallablePotential(lambda q: 0.5 * (q * q).sum(-1), lambda q: q.copy(), 3))
    draws = sample(found, chains=8, warmup=100, keep=keep, seed=seed)
    assert draws.per_chain in (keep, 2 * keep, 4 * keep)
    assert draws.per_chain == 4 * keep or draws.converged or draws.rhat > 1.05
    energies = 0.5 * (draws.positions ** 2).sum(-1)
    r, ess = diagnostics(draws.positions, energies)
    assert (draws.rhat, draws.effective_size) == pytest.approx((r, ess), rel=1e-12)


@pytest.mark.slow
def test_well_mixed_chains_on_a_10_dimensional_gaussian_are_verified_at_every_seed():
    """A 10-dimensional standard Gaussian given as a potential, seeds 1 to 6: every report
    is verified, and each estimate agrees within 3 combined standard errors with the
    test's own Verlet on 100000 exact draws."""
    from stepsafe import hmc

    rng = np.random.default_rng(3)
    exact = rng.normal(size=(100_000, 10))
    for seed in range(1, 7):
        report = hmc(["verlet"], logdensity=_normal_logdensity, gradient=_normal_gradient,
                     start=np.zeros(10), trajectory_steps=10, seed=seed)
        assert report.verified, (seed, report.unverified)
        row = report.rows[0]
        acc, se, _ = _summary(_verlet_energy_errors(_normal_gradient_u, _normal_energy,
                                                    exact, row.h_target, 10, rng))
        assert abs(row.estimate.acceptance - acc) <= 3 * math.hypot(
            se, row.estimate.acceptance_se), (seed, row.estimate, acc, se)


def _normal_energy(q):
    return 0.5 * (q * q).sum(-1)


def _normal_gradient_u(q):
    return q


# ------------------------------------------------------------ a gradient given by the user

def _scaled_banana(k, offset, c=0.3):
    """The banana U = x^2/2 + (y - c x^2)^2/2 in (x, y) = q / k, plus a constant, with its
    exact gradient."""
    def energy(q):
        x, y = q[..., 0] / k, q[..., 1] / k
        return offset + 0.5 * x * x + 0.5 * (y - c * x * x) ** 2

    def gradient(q):
        x, y = q[..., 0] / k, q[..., 1] / k
        r = y - c * x * x
        return np.stack([x - 2 * c * x * r, r], axis=-1) / k

    return energy, gradient


@settings(max_examples=30, deadline=None)
@example(log_k=3.0, offset=1e6, start=(0.0, 0.0), wrong="swapped")  # (started at the mode)
@given(log_k=st.floats(-8, 8), offset=st.sampled_from([0.0, 1e6, -1e12, 1e15]),
       start=st.tuples(st.floats(-3, 3), st.floats(-3, 3)),
       wrong=st.sampled_from(["none", "twice", "sign", "swapped"]))
def test_a_gradient_inconsistent_with_its_energy_is_found_and_a_right_one_never(
        log_k, offset, start, wrong):
    """The gradient check compares the gradient given with central differences of the
    energy: the exact gradient of the banana passes at every scale k from 1e-8 to 1e8 and
    with constants up to 1e15 added to U (where rounding makes a difference unjudgeable,
    it is not judged), at any start; twice it, its negative or its coordinates swapped are
    found (at the start, or at the mode when the start cannot tell) wherever U's constant
    leaves the differences judgeable (below 1e12 here)."""
    from stepsafe.core.hmc_target.draws import find_mode, gradient_mismatch
    from stepsafe.core.hmc_target.potential import CallablePotential

    k = 10.0 ** log_k
    energy, exact = _scaled_banana(k, offset)
    given = {"none": exact, "twice": lambda q: 2 * exact(q), "sign": lambda q: -exact(q),
             "swapped": lambda q: exact(q)[..., ::-1]}[wrong]
    pot = CallablePotential(energy, given, 2)
    q0 = k * np.array(start)
    found = gradient_mismatch(pot, q0)
    if found is None and wrong != "none":
        from stepsafe.core.hmc_target.potential import target

        laplace = find_mode(target(CallablePotential(energy, exact, 2)), q0)
        found = gradient_mismatch(pot, laplace.mode)
    if wrong == "none":
        assert found is None, found
    elif abs(offset) < 1e12:
        # (beyond, U's rounding at the differences' widths leaves nothing to judge)
        assert found is not None


def test_hmc_refuses_a_gradient_that_is_not_the_log_densitys_naming_gradient():
    """stepsafe.hmc with logdensity= and a gradient= that is twice, minus or the swapped
    true one: a StepsafeError naming gradient, before any sampling."""
    from stepsafe import hmc
    from stepsafe.exceptions import StepsafeError

    energy, exact = _scaled_banana(1.0, 0.0)
    for wrong in (lambda q: -2 * exact(q), exact, lambda q: -exact(q)[..., ::-1]):
        with pytest.raises(StepsafeError, match="not that of the log-density") as caught:
            hmc(["verlet"], logdensity=lambda q: -energy(q), gradient=wrong,
                start=[0.3, 0.2], trajectory_steps=10)
        assert caught.value.where == "gradient"


@settings(max_examples=2, deadline=None)
@given(log_s=st.tuples(st.floats(-4, 4), st.floats(-4, 4)))
def test_force_gradient_estimates_are_the_same_at_every_scale_of_each_coordinate(log_s):
    """Two logistic marginals U = sum of z + 2 log(1 + e^-z), z = q / s, with the mass 1/s^2
    that whitens them and exact draws scaled by s: the same system as s = (1, 1) in other
    units, so chin-4a's estimate at h = 1.5 (a force-gradient method, whose Hessian comes
    from differences of the gradient over each coordinate's own spread) is the same to
    1e-6 whatever the scale of each coordinate (s from 1e-4 to 1e4)."""
    from stepsafe import hmc

    z = np.random.default_rng(4).logistic(size=(8, 400, 2))

    def at(s):
        s = np.asarray(s, dtype=float)

        def logdensity(q):
            y = q / s
            return -(y + 2 * np.log1p(np.exp(-y))).sum(-1)

        def gradient(q):
            return -np.tanh(q / s / 2) / s

        report = hmc(["chin-4a"], logdensity=logdensity, gradient=gradient, start=[0.0, 0.0],
                     mass=1 / s**2, trajectory_steps=10, step=1.5, draws=z * s)
        return report.rows[0].at_step.acceptance

    assert at(10.0 ** np.array(log_s)) == pytest.approx(at([1.0, 1.0]), rel=1e-6)


@settings(max_examples=20, deadline=None)
@given(d=st.integers(2, 5), bad=st.sampled_from([np.inf, -np.inf, np.nan]),
       row=st.integers(0, 3), dense=st.booleans())
def test_a_momentum_that_overflowed_gives_non_finite_velocities_not_an_error(d, bad, row,
                                                                          dense):
    """A kick whose force overflows leaves a non-finite momentum: with a diagonal or a
    dense mass, M^-1 p of that row is non-finite (the trajectory diverges and is frozen)
    and every other row is M^-1 p exactly as without it."""
    from stepsafe.core.hmc_target.potential import mass_matrix

    rng = np.random.default_rng(d)
    A = rng.normal(size=(d, d))
    M = A @ A.T + d * np.eye(d) if dense else rng.uniform(0.5, 2.0, d)
    mass = mass_matrix(M, d)
    p = rng.normal(size=(4, d))
    clean = mass.velocity(p)
    p[row, 0] = bad
    v = mass.velocity(p)
    assert not np.isfinite(v[row]).all()
    others = [k for k in range(4) if k != row]
    np.testing.assert_allclose(v[others], clean[others], rtol=1e-12)

"""Adversarial checks of ``hmc`` on ``potential:`` targets against an independent HMC
estimate.

The reference draws exactly from the target (the banana and Neal's funnel have closed-form
samplers), gives each draw a fresh unit-mass momentum, runs L steps of velocity Verlet
(kick h/2, drift h, kick h/2) at one step per trajectory (uniform in h (1 +- J) when
jittered, as Stan's ``stepsize_jitter``), and averages min(1, e^-dH) (a proposal with
dH > 1000 or a non-finite state is divergent). Its standard error is that of an average of
independent terms. Nothing here calls stepsafe's samplers or integrators.
"""

from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from stepsafe.cli import main


def _hmc_json(scene: str, *args: str) -> dict:
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "target.yaml"
        path.write_text(scene)
        result = CliRunner().invoke(main, ["hmc", str(path), *args, "--json"])
        assert result.exit_code == 0, result.stderr
        return json.loads(result.stdout)


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
@pytest.mark.xfail(strict=True, reason=(
    "hmc on the banana c = 1 (verlet, L = 10, jitter 0.2, default seed) estimates the "
    "acceptance at h at target as 0.9647 +- 0.0018 with no divergent proposal; exact draws "
    "give 0.9560 +- 0.0002 and 0.18% divergent: the warm-up draws miss the tails where the "
    "jittered steps diverge"))
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
@pytest.mark.xfail(strict=True, reason=(
    "hmc on Neal's funnel (verlet, L = 10, --step 0.05, default seed) reports 9.7% divergent "
    "proposals; exact draws give 0.58% (the warm-up chains sit in the neck: 1% of its draws "
    "at v ~ -15, where the target has probability 3e-7)"))
def test_hmc_divergent_share_on_the_funnel_agrees_with_exact_draws():
    """At h = 0.05 the divergent share on the warm-up draws must be within a factor 2 of the
    share on exact draws (binomial noise on 4800 proposals is far smaller)."""
    row = _hmc_json(FUNNEL, "--steps", "10", "--methods", "verlet",
                    "--step", "0.05")["methods"][0]["at_step"]
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


@pytest.mark.xfail(strict=True, reason=(
    "a Gamma(k, theta) target (U = -(k-1) log x + x/theta, start at its mode) is refused: the "
    "warm-up chains start from the Laplace Gaussian N(mode, H^-1), which puts some below 0, and "
    "the message blames the start given and names neither file nor key"))
@settings(max_examples=3, deadline=None, suppress_health_check=list(HealthCheck),
          phases=(Phase.explicit, Phase.reuse, Phase.generate))
@given(k=st.floats(1.5, 3.0), theta_exp=st.integers(-3, 3))
def test_a_positive_support_target_started_at_its_mode_is_analysed(k, theta_exp):
    """A proper target whose energy is finite at its mode (the start given) is analysed."""
    theta = 10.0 ** theta_exp
    scene = ("system:\n"
             f'  potential: "-(k - 1)*log(x) + x/theta"\n'
             "  q: [x]\n"
             f"  parameters: {{k: {k!r}, theta: {theta!r}}}\n"
             f"  start: [{(k - 1) * theta!r}]\n")
    code, err = _hmc_code(scene, "--steps", "10", "--methods", "verlet")
    assert code == 0, err


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason=(
    "hmc analyses an improper target (U flat along a coordinate: no normalisable density) and "
    "exits 0 with an acceptance, a step at target and a ranking"))
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
    assert code == 2, (code, err)

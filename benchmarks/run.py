"""stepsafe benchmarks: every figure measured side by side in one run, printed as a table.

    pip install '.[bench]' && python benchmarks/run.py [--big]

1. Peer (nodepy) on the tasks both do: the imaginary-axis stability interval and the
   stability function R(iy) of rk4, Gauss s = 2..5 and Lobatto IIIA s = 3..5; time for
   both and accuracy against mpmath (30 digits). Goal: >= 100x faster at equal or better
   accuracy. nodepy gets the same float tableaux where it has no built-in method. stepsafe's
   interval is ``classical_interval`` (roots of |Q(iy)|^2 - |P(iy)|^2, status decided from
   M(z)); its R(iy) is ``rkstability.stability_function``.
2. Region cost: warm time of ``find_region`` (three models) for every one-force library
   method (interleaved: every method once per round) and for the families s = 2..20.
   Goal: < 10 ms per model for library methods; cost growing no faster than s^3 (log-log
   slope).
3. Scale: ``advise`` over 10^6 and 10^7 frequencies; the extreme modes of a 10^5-dof
   sparse chain; the coupled analysis of non-separable definite Hessians of 50..400 dof
   (800 with ``--big``) with pefrl, as a ratio to one ``numpy.linalg.eig`` of the same
   size (interleaved medians, one BLAS thread for both), and at 200 dof with two threads;
   with ``--big`` also a 5000-dof dense stiffness.
4. Start-up (benchmarks/startup.py): ``import stepsafe``, ``stepsafe check`` on a built-in
   and on a scene file and ``stepsafe advise`` on a built-in, as ratios to
   ``python -c "import numpy"``, interleaved in the same rounds. Goals: 2x and 3x.
5. Equilibrium search: ``stepsafe advise`` on each shipped Hamiltonian scene, and the
   Henon-Heiles search with its walks as a ratio to its Newton starts alone.

Timings are medians of repeated runs; the machine and its load average are printed with
the table. Exit code 0
(a benchmark reports, it does not fail).
"""

from __future__ import annotations

import math
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from stepsafe.core.advice import Modes, advise  # noqa: E402
from stepsafe.core.regions import classical_interval, find_region  # noqa: E402
from stepsafe.core.rkstability import stability_function, stability_polynomials  # noqa: E402
from stepsafe.core.transfer import has_form, stage_operator  # noqa: E402
from stepsafe.methods.families import gauss, lobatto3a, lobatto3ab  # noqa: E402
from stepsafe.methods.library import builtin_names, resolve  # noqa: E402
from stepsafe.methods.tableaux import RungeKutta  # noqa: E402

ROWS: list[tuple[str, str, str, str]] = []


def row(figure: str, value: str, ratio: str = "", goal: str = "") -> None:
    ROWS.append((figure, value, ratio, goal))
    print(f"  {figure:58s} {value:>22s} {ratio:>10s}  {goal}", flush=True)


def timed(fn, repeat: int = 7, warm: bool = True) -> float:
    if warm:
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


# ------------------------------------------------------------------ 1. nodepy side by side


def _mp_R(A, b, y):
    import mpmath as mp

    s = len(b)
    Am = mp.matrix([[mp.mpf(float(x)) for x in r] for r in A])
    e = mp.matrix([1] * s)
    bm = mp.matrix([mp.mpf(float(x)) for x in b]).T
    w = mp.mpc(0, y)
    num = mp.det(mp.eye(s) - w * Am + w * e * bm)
    return num / mp.det(mp.eye(s) - w * Am)


def cold() -> None:
    stability_polynomials.cache_clear()
    stage_operator.cache_clear()


def stepsafe_R(method, y):
    """R(iy) from stepsafe's stability polynomials (stepsafe.core.rkstability)."""
    return stability_function(method, 1j * y)


def bench_nodepy() -> None:
    try:
        from nodepy import runge_kutta_method as rkm
        from nodepy import stability_function as sf
    except ImportError:
        row("nodepy comparison", "skipped", "", "pip install '.[bench]'")
        return
    import mpmath as mp

    rk4 = resolve("rk4")[0]
    cases = [("rk4", rk4, rkm.loadRKM("RK44"), 2 * math.sqrt(2))]
    for s in (2, 3, 4, 5):
        g = gauss(s)
        peer = rkm.loadRKM(f"GL{s}") if s <= 3 else rkm.RungeKuttaMethod(g.A, g.b)
        cases.append((f"gauss-s{s}", g, peer, math.inf))
    for s in (3, 4, 5):
        A, b, c = lobatto3a(s)
        m = RungeKutta(A, b, c, name=f"lobatto3a-s{s}", order=2 * s - 2)
        peer = rkm.loadRKM("LobattoIIIA3") if s == 3 else rkm.RungeKuttaMethod(A, b)
        cases.append((m.name, m, peer, math.inf))
    y = np.linspace(0.01, 10.0, 1000)
    y_ref = y[::50]
    speed = []
    for name, ours, peer, exact in cases:
        def ours_interval(ours=ours):
            cold()  # no per-method caches carried between calls: both sides start from A, b
            iv = classical_interval(ours, zmax=10.0)
            return iv[0].hi if iv and iv[0].lo == 0.0 else 0.0

        def peer_interval(peer=peer):
            p, q = peer.stability_function()
            return sf.imaginary_stability_interval(p, q)

        t_ours = timed(ours_interval, repeat=5)
        t_peer = timed(peer_interval, repeat=3)
        v_ours = ours_interval()
        v_ours = math.inf if v_ours is None else v_ours
        v_peer = float(peer_interval())
        speed.append(t_peer / t_ours)
        def err(v, exact=exact):
            if math.isinf(exact):
                return "right (unbounded)" if math.isinf(v) else f"WRONG ({v:.6g})"
            return f"rel err {abs(v - exact) / exact:.1e}"
        row(f"imag. interval {name}: stepsafe | nodepy",
            f"{t_ours * 1e3:.2f} | {t_peer * 1e3:.1f} ms", f"{t_peer / t_ours:.0f}x",
            f"ours {err(v_ours)}; nodepy {err(v_peer)}")

        def ours_R(ours=ours):
            cold()
            return stepsafe_R(ours, y)

        def peer_R(peer=peer):
            p, q = peer.stability_function()
            pf = np.poly1d(np.array(p.coeffs, dtype=float))
            qf = np.poly1d(np.array(q.coeffs, dtype=float))
            return pf(1j * y) / qf(1j * y)

        t_o, t_p = timed(ours_R, repeat=5), timed(peer_R, repeat=3)
        with mp.workdps(30):
            ref = np.array([complex(_mp_R(ours.A, ours.b, float(v))) for v in y_ref])
        e_o = np.max(np.abs(ours_R()[::50] - ref) / np.abs(ref))
        e_p = np.max(np.abs(peer_R()[::50] - ref) / np.abs(ref))
        row(f"R(iy) at 1000 points {name}: stepsafe | nodepy",
            f"{t_o * 1e3:.2f} | {t_p * 1e3:.1f} ms", f"{t_p / t_o:.0f}x",
            f"max rel err {e_o:.1e} | {e_p:.1e}")
    row("nodepy comparison, geometric mean speed-up (intervals)",
        f"{math.exp(np.mean(np.log(speed))):.0f}x", "", "goal >= 100x")


# ------------------------------------------------------------------ 2. region cost


def bench_regions() -> None:
    methods = {name: resolve(name)[0] for name in builtin_names(single_force=True)
               if name not in ("gauss", "lobatto3ab")}
    # the models each method has a form for (a force-gradient method: not the saddle)
    models = {name: [model for model in ("oscillator", "saddle", "inverted")
                     if has_form(m, model)] for name, m in methods.items()}
    for name, m in methods.items():  # warm: caches, first imports
        [find_region(m, model) for model in models[name]]
    # every method once per round, five rounds: a change of load hits all alike
    times = interleaved({name: (lambda m=m, name=name: [find_region(m, model)
                                                         for model in models[name]])
                         for name, m in methods.items()}, repeat=5)
    worst = 0.0
    for name, t in times.items():
        t /= len(models[name])
        worst = max(worst, t)
        row(f"region {name} (per model)", f"{t * 1e3:.1f} ms", f"{t / 0.01:.2f}x goal",
            "goal < 10 ms")
    row("region, slowest library method (per model)", f"{worst * 1e3:.1f} ms",
        f"{worst / 0.01:.2f}x goal", "goal < 10 ms")
    for family, build in (("gauss", gauss), ("lobatto3ab", lobatto3ab)):
        stages, times = [], []
        for s in (2, 4, 6, 8, 12, 16, 20):
            m = build(s)
            t = timed(lambda m=m: find_region(m, "oscillator"), repeat=3)
            stages.append(s)
            times.append(t)
        slope = np.polyfit(np.log(stages), np.log(times), 1)[0]
        row(f"region {family} s=2..20 (oscillator): s=2 | s=20",
            f"{times[0] * 1e3:.1f} | {times[-1] * 1e3:.1f} ms", f"slope {slope:.2f}",
            "goal: slope <= 3")


# ------------------------------------------------------------------ 3. scale


def interleaved(fns: dict, repeat: int) -> dict:
    """Median time of each function, the functions run in turn ``repeat`` times (so a
    change of machine load hits all of them alike)."""
    times: dict = {name: [] for name in fns}
    for _ in range(repeat):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    return {name: statistics.median(t) for name, t in times.items()}


def bench_scale(big: bool) -> None:
    from threadpoolctl import threadpool_limits

    m = resolve("pefrl")[0]
    for count in (10**6, 10**7):
        betas = np.exp(np.random.default_rng(0).uniform(np.log(1e-3), np.log(1e3), count))
        t = timed(lambda b=betas: advise(m, Modes.from_arrays({"oscillator": b})), repeat=3)
        row(f"advise, 10^{round(math.log10(count))} frequencies (pefrl)", f"{t * 1e3:.0f} ms",
            "", "goal well under 1 s" if count == 10**6 else "")
    import scipy.sparse as sp

    from stepsafe.systems.coupled import coupled_safe_steps
    from stepsafe.systems.linear import sparse_extreme_modes

    n = 100_000
    K = sp.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1], format="csr")
    t = timed(lambda: sparse_extreme_modes(K), repeat=3)
    row("10^5-dof sparse chain, extreme modes (h_max)", f"{t * 1e3:.0f} ms", "", "")
    for dof in (50, 100, 200, 400) + ((800,) if big else ()):
        rng = np.random.default_rng(0)
        A = rng.normal(size=(2 * dof, 2 * dof))
        S = A @ A.T / (2 * dof) + np.eye(2 * dof)
        with threadpool_limits(1, "blas"):
            t = interleaved({"ours": lambda S=S: coupled_safe_steps(m, S),
                             "eig": lambda S=S, A=A: np.linalg.eig(S + 0.1 * A)},
                            repeat=3 if dof <= 200 else 1)
        row(f"{dof}-dof coupled Hessian, pefrl", f"{t['ours']:.2f} s",
            f"{t['ours'] / t['eig']:.0f}x eig",
            "ratio to one eig (with vectors) of the same 2n x 2n size; goal <= 10x")
        if dof == 200:
            import stepsafe.core.threads

            pin, stepsafe.core.threads.THREADS = stepsafe.core.threads.THREADS, 0
            with threadpool_limits(2, "blas"):  # (stepsafe's own pinning switched off)
                two = interleaved({"ours": lambda S=S: coupled_safe_steps(m, S)}, repeat=3)
            stepsafe.core.threads.THREADS = pin
            row("  the same with two BLAS threads (stepsafe pins one)", f"{two['ours']:.2f} s",
                f"{two['ours'] / t['ours']:.2f}x", "")
    if big:
        rng = np.random.default_rng(0)
        A = rng.normal(size=(5000, 5000))
        K = A @ A.T / 5000 + np.eye(5000)
        t = timed(lambda: sparse_extreme_modes(K), repeat=1, warm=False)
        row("5000-dof dense stiffness, extreme modes (h_max)", f"{t:.1f} s", "", "")


# ------------------------------------------------------------------ 4. start-up


def bench_startup() -> None:
    """The start-up figures of benchmarks/startup.py (interleaved rounds, medians)."""
    from startup import COMMANDS, medians

    figures = medians(repeat=11)
    base = figures[0]
    for (label, _, goal), t in zip(COMMANDS, figures):
        row(label, f"{t * 1e3:.0f} ms", f"{t / base:.2f}x", f"goal {goal}" if goal else "")


# ------------------------------------------------------------------ 5. equilibrium search


#: The shipped Hamiltonian scenes (and the options they need) whose equilibria are searched.
HAMILTONIAN_EXAMPLES = (("pendulum", ()), ("double-well", ()), ("paper-section3-system", ()),
                        ("henon-heiles", ()), ("double-pendulum", ()), ("fpu-alpha", ()),
                        ("lagrange-points", ("-s", "2")))


def bench_equilibria() -> None:
    """``stepsafe advise`` on each shipped Hamiltonian scene (start-up included): Newton's
    starts, the descents and walks of stepsafe.systems.walks, the verification and the
    analysis; and how much of it the walks take (find_equilibria / find_many in process,
    with the walks and without)."""
    from stepsafe.files.yamlio import load_yaml
    from stepsafe.systems import manydof, walks
    from stepsafe.systems.loader import read_many

    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPATH"] = str(ROOT)
    for name, extra in HAMILTONIAN_EXAMPLES:
        args = [sys.executable, "-m", "stepsafe", "advise", f"examples/{name}.yaml", *extra]
        t = timed(lambda a=args: subprocess.run(a, capture_output=True, cwd=ROOT, env=env),
                  repeat=3)
        row(f"stepsafe advise examples/{name}.yaml", f"{t:.2f} s")
    tree = load_yaml(ROOT / "examples/henon-heiles.yaml")["system"]
    H, lo, hi = read_many(tree, "henon-heiles.yaml")
    explore = walks.explore

    def without(points, *args, **kwargs):  # the starts alone: no walk followed
        return [], walks.Walks()

    full = timed(lambda: manydof.find_many(H, lo, hi), repeat=3)
    manydof.explore = without
    try:
        starts = timed(lambda: manydof.find_many(H, lo, hi), repeat=3)
    finally:
        manydof.explore = explore
    row("Henon-Heiles search: starts + walks", f"{full:.2f} s", f"{full / starts:.2f}x",
        "of the starts alone")


def main() -> int:
    big = "--big" in sys.argv[1:]
    print(f"stepsafe benchmarks on {platform.machine()} {platform.processor() or ''}, "
          f"{os.cpu_count()} cores, Python {platform.python_version()}, numpy {np.__version__}; "
          f"load average {os.getloadavg()[0]:.2f}")
    print(f"  {'figure':58s} {'value':>22s} {'ratio':>10s}  goal / accuracy")
    bench_nodepy()
    bench_regions()
    bench_scale(big)
    bench_startup()
    bench_equilibria()
    print(f"load average at the end {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Runs of a method on the user's own system, as :func:`stepsafe.measure` makes them.

The scene's actual system (a 1-dof Hamiltonian expression, or a linear system: stiffness
and mass, Hessian, Gaussian precision or covariance) is integrated with the method at each
step h for a time T from one initial condition, by the engine of
:mod:`stepsafe.core.integrator`. Measured per h:

* the energy error: the spread ``(max_k H - min_k H) / (min_k H - H_e)`` of the energy
  over every step k = 0 .. n of the run (``H_e`` the energy of the equilibrium the start
  orbits, 0 for linear systems): the quantity the linear bound ``kappa - 1`` describes,
  whatever the start (with no equilibrium, the spread over ``|H(0)|``);
* the energy drift: the least-squares slope of ``(H(t_k) - H(0)) / |H(0) - H_e|`` against
  ``t_k = k h``, fitted through every step. Both are reduced on the fly, chunk by chunk,
  nothing stored (:class:`_EnergyTrace`): a sample every few steps would alias with the
  orbit's rotation (a stride of 3 steps on an orbit of period 6 steps sees one energy);
* the trajectory error at T (from the final state alone, no sampling):
  ``|x - x_exact|`` over ``|x_exact - x_e|`` in the energy norm of the Hessian at the
  equilibrium the start orbits, where the linear model's orbits are circles (the
  Euclidean norm where that Hessian is not definite or there is no equilibrium); the
  reference is ``expm(J S T)`` for linear systems, an adaptive 8th-order Dormand-Prince
  run at tolerance 2.5e-14 for expressions, whose own error (the floor below which no
  trajectory error can be told) is estimated by a second run at 1e-13
  (:func:`reference_run`); an error below the floor is reported as such, not as a number;
* force evaluations per unit time as counted (implicit methods: with their fixed-point
  iterations);
* the status: ``ok``; ``unstable`` when the state overflows or its energy moves by more
  than :data:`UNSTABLE` times the start's energy above the equilibrium; ``solver failed``
  when the stage iteration did not converge; ``beyond z*`` when the run stayed finite but
  z = beta h is past the method's first boundary for the vibration the start orbits,
  where the linear model predicts nothing; ``budget`` when the time budget ran out during
  the run, ``not run`` after it.

Beside each, the linear prediction for the vibration the start orbits (z = beta h): the
energy error bound ``kappa - 1`` (relative to the energy above that equilibrium) and the
trajectory error ``2 |sin(delta / 2)|`` of a phase drift ``delta = |theta/z - 1| beta T``
(``delta`` itself while small; 2 once the run is half a turn out of phase, and then no
ratio is formed), and the ratio measured / predicted: the nonlinear calibration of the
linear model.
"""

from __future__ import annotations

import math
import time as _time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from stepsafe.core.integrator import Engine, SolverFailure
from stepsafe.exceptions import StepsafeError, finite_real
from stepsafe.systems.dynamics import (
    check_finite_start,
    exact_linear,
    hamiltonian_system,
    linear_system,
    stiffness_hessian,
)
from stepsafe.systems.linear import check_square
from stepsafe.systems.loader import _matrix, analyse_system, read_many, units_scale
from stepsafe.systems.manydof import centres as elliptic_centres
from stepsafe.systems.manydof import parse_many, system_of
from stepsafe.systems.nonlinear import parse_hamiltonian
from stepsafe.systems.scene import load_scene

#: States buffered between two vectorised energy evaluations at most (the energy is
#: evaluated at every step, in chunks of this many steps, and not stored)...
ENERGY_CHUNK = 1024
#: ... and state values buffered at most (fewer steps per chunk for many dof).
CHUNK_VALUES = 1 << 20
#: A run whose energy moves by more than this many times the start's energy above the
#: equilibrium has grown without bound (bounded linear runs stay within kappa - 1).
UNSTABLE = 1e6


@dataclass(frozen=True)
class MeasuredSystem:
    """A system to run a method on: its dynamics, its start (rows of shape (1, dof)), the
    angular frequency ``beta`` of the vibration the start orbits (None: none), and its
    reference solution."""

    system: Any  # stepsafe.core.integrator.System
    q0: np.ndarray
    p0: np.ndarray
    beta: float | None
    description: str
    #: (times, deadline) -> the exact states (q then p) at those times
    reference: Callable[[list[float], float | None], list[np.ndarray]]
    reference_text: str
    equilibrium_energy: float | None = 0.0  # H at the equilibrium the start orbits
    #: the Hessian at that equilibrium when positive definite (the energy norm in which
    #: trajectory errors are measured), and the equilibrium's state
    metric: np.ndarray | None = None
    centre: np.ndarray | None = None
    #: the conserved quantities the scene declares (``invariants:``): name and a
    #: vectorised function of (q, p), rows of shape (m, dof)
    invariants: tuple[tuple[str, Callable[[np.ndarray, np.ndarray], np.ndarray]], ...] = ()


@dataclass(frozen=True)
class Run:
    """What one run of ``n`` steps of size ``h`` measured (None where not measured: every
    figure is None unless ``status`` is ``ok``)."""

    status: str
    energy_error: float | None = None
    energy_drift: float | None = None
    trajectory_error: float | None = None
    evaluations_per_time: float | None = None
    iterations_per_step: float | None = None
    jacobians_per_time: float | None = None
    gradients_per_time: float | None = None
    #: the energy error against time (:class:`Fit`) and each declared invariant's
    energy_fit: Fit | None = None
    invariants: tuple[tuple[str, Fit], ...] = ()
    #: wall-clock seconds of the run's steps per unit of simulated time (the energy and
    #: invariant monitoring included, the reference not)
    seconds_per_time: float | None = None


def run_steps(tableau: Any, problem: MeasuredSystem, h: float, n: int, exact: np.ndarray,
              tick: Callable[[int], None], solver: str = "fixed-point",
              deadline: float | None = None) -> Run:
    """Run ``n`` steps of size ``h`` of the method ``tableau`` on ``problem`` from its start,
    the energy reduced at every step (:class:`EnergyTrace`), the final state compared with
    ``exact``; ``tick(k)`` is called every 1024 steps and at the end. Status ``ok``,
    ``unstable``, ``solver failed`` or ``budget`` (the ``deadline`` passed)."""
    began = _time.perf_counter()
    engine = Engine(tableau, problem.system, solver=solver)
    system = problem.system
    q, p = problem.q0.copy(), problem.p0.copy()
    e0 = float(system.energy(q, p)[0])
    scale = abs(e0 - (problem.equilibrium_energy or 0.0)) or 1.0
    trace = EnergyTrace(engine, h, e0, scale, q.shape[1],
                        [f for _, f in problem.invariants], (q, p))
    q, p = engine.start(q, p, h)  # processed methods: P once (else the identity)
    status = "ok"
    with np.errstate(all="ignore"):
        for k in range(1, n + 1):
            try:
                q, p = engine.step(q, p, h)
            except SolverFailure:  # (a state that grew without bound first is unstable)
                status = "solver failed" if trace.flush() else "unstable"
                break
            if not trace.push(q, p, last=k == n):
                status = "unstable"
                break
            if k % 1024 == 0:
                tick(k)
                if deadline is not None and _time.monotonic() > deadline:
                    status = "budget"
                    break
    seconds = _time.perf_counter() - began
    tick(n)
    T = n * h
    if status != "ok":
        return Run(status)
    drift = trace.slope()
    q, p = engine.output(q, p, h)
    state = np.concatenate([q[0], p[0]])
    traj = _trajectory_error(state, exact, problem)
    # the processor's cost: P once and P^-1 once for the final state (the outputs the
    # energy trace evaluates are monitoring, not part of the integration)
    outputs = engine.output_evaluations // max(1, engine.output_calls)
    iterations = engine.iterations / n if engine.solves else None
    # the spread of the energy over the run relative to its lowest value above the
    # equilibrium (the quantity the linear bound kappa - 1 describes, whatever the start);
    # with no equilibrium, relative to |H(0)|
    spread: float | None
    if problem.equilibrium_energy is None:
        spread = trace.high - trace.low
    else:
        low = trace.low + (e0 - problem.equilibrium_energy) / scale
        spread = (trace.high - trace.low) / low if low > 0 else None
    return Run(status, spread, drift, traj, (engine.force_evaluations + outputs) / T,
               iterations, engine.jacobians / T if engine.jacobians else None,
               engine.gradient_evaluations / T if engine.gradient_evaluations else None,
               trace.energy.fit(),
               tuple((name, moments.fit()) for (name, _), (_, _, _, moments)
                     in zip(problem.invariants, trace.invariants)),
               seconds / T)


#: The least fraction of an error's variance over a run that its least-squares line must
#: explain (R^2) for the error to be called a drift rather than a bounded oscillation.
DRIFT_R2 = 0.5


@dataclass(frozen=True)
class Fit:
    """A relative error ``e_k`` against ``t_k = k h`` over every step of a run: its spread
    ``max e - min e``, the least-squares ``slope`` of the line through every step, and
    ``r2``, the fraction of the variance of ``e`` that line explains (``S_te^2 / (S_tt
    S_ee)``): a ``drift`` when it explains at least :data:`DRIFT_R2`, else ``bounded``
    (an oscillation about a level, the line's slope being the residue of its phases)."""

    spread: float
    slope: float | None
    r2: float | None

    @property
    def behaviour(self) -> str | None:
        if self.r2 is None:
            return None
        return "drift" if self.r2 >= DRIFT_R2 else "bounded"

    def to_dict(self) -> dict[str, Any]:
        return {"spread": self.spread, "slope": self.slope, "r2": self.r2,
                "behaviour": self.behaviour}


class Moments:
    """Least, greatest, means and co-moments of ``(t_k, e_k)`` merged chunk by chunk by the
    pairwise update of Chan, Golub and LeVeque (``n = n_a + n_b``, ``d = mean_b -
    mean_a``, ``S_tt = S_tt,a + S_tt,b + d_t^2 n_a n_b / n``, likewise ``S_te`` and
    ``S_ee``), so that the fit is that through every step, without the cancellation of raw
    sums. Starts with the point ``(0, 0)``."""

    def __init__(self) -> None:
        self.count, self.t_mean, self.e_mean = 1, 0.0, 0.0
        self.S_tt = self.S_te = self.S_ee = 0.0
        self.low = self.high = 0.0

    def add(self, t: np.ndarray, e: np.ndarray) -> None:
        m = t.size
        t_mean, e_mean = float(t.mean()), float(e.mean())
        dt, de = t - t_mean, e - e_mean
        total = self.count + m
        shift_t, shift_e = t_mean - self.t_mean, e_mean - self.e_mean
        weight = self.count * m / total
        self.S_tt += float(dt @ dt) + shift_t * shift_t * weight
        self.S_te += float(dt @ de) + shift_t * shift_e * weight
        self.S_ee += float(de @ de) + shift_e * shift_e * weight
        self.t_mean += shift_t * m / total
        self.e_mean += shift_e * m / total
        self.count = total
        self.low, self.high = min(self.low, float(e.min())), max(self.high, float(e.max()))

    def slope(self) -> float | None:
        """The least-squares slope of e against t over every step (None below 3 points)."""
        if self.count < 3 or not self.S_tt > 0:
            return None
        return self.S_te / self.S_tt

    def fit(self) -> Fit:
        slope = self.slope()
        r2 = None
        if slope is not None:
            r2 = 0.0 if not self.S_ee > 0 else \
                min(1.0, self.S_te * self.S_te / (self.S_tt * self.S_ee))
        return Fit(self.high - self.low, slope, r2)


class EnergyTrace:
    """The relative energy error ``e_k = (H(x_k) - H(x_0)) / scale`` at every step
    k = 0 .. n of a run (``x_k`` the output state: ``P^-1`` of the kernel's for processed
    methods), and likewise each invariant ``I`` the scene declares (``(I(x_k) - I(x_0)) /
    |I(x_0)|``, or absolute when ``I(x_0) = 0``), reduced on the fly (:class:`Moments`):
    least and greatest values, the least-squares slope against ``t_k = k h`` and the
    fraction of the variance it explains. No step is skipped (a sample every few steps can
    lock onto the rotation of the orbit and miss the extremes) and none is stored: the
    states of up to :data:`ENERGY_CHUNK` steps are buffered and evaluated in one
    vectorised call per quantity."""

    def __init__(self, engine: Any, h: float, e0: float, scale: float, dof: int,
                 invariants: Sequence[Callable[[np.ndarray, np.ndarray], np.ndarray]] = (),
                 start: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        self.engine, self.h, self.e0, self.scale = engine, h, e0, scale
        size = max(1, min(ENERGY_CHUNK, CHUNK_VALUES // (2 * dof)))
        self.Q, self.P = np.empty((size, dof)), np.empty((size, dof))
        self.filled = 0  # steps buffered
        self.step = 0  # steps pushed
        self.energy = Moments()
        self.invariants = []  # (function, value at the start, scale, moments)
        for f in invariants:
            i0 = float(f(*start)[0]) if start is not None else 0.0
            self.invariants.append((f, i0, abs(i0) or 1.0, Moments()))

    @property
    def low(self) -> float:
        return self.energy.low

    @property
    def high(self) -> float:
        return self.energy.high

    def push(self, q: np.ndarray, p: np.ndarray, last: bool = False) -> bool:
        """Buffer the state after the next step (rows of shape ``(1, dof)``); evaluate the
        buffer when full or ``last``. False once a state evaluated is unstable."""
        self.Q[self.filled], self.P[self.filled] = q[0], p[0]
        self.filled += 1
        self.step += 1
        if self.filled == self.Q.shape[0] or last:
            return self.flush()
        return True

    def flush(self) -> bool:
        """Evaluate the buffered steps: False when a state is not finite or its energy
        moved by more than :data:`UNSTABLE` times the scale (nothing is then added)."""
        m, self.filled = self.filled, 0
        if m == 0:
            return True
        Q, P = self.Q[:m], self.P[:m]
        out = self.engine.output(Q, P, self.h)
        e = (self.engine.system.energy(*out) - self.e0) / self.scale
        stable = np.isfinite(Q).all(axis=1) & np.isfinite(P).all(axis=1) & \
            (np.abs(e) <= UNSTABLE)  # (nan compares False)
        if not stable.all():
            return False
        t = self.h * np.arange(self.step - m + 1, self.step + 1, dtype=float)
        self.energy.add(t, e)
        for f, i0, scale, moments in self.invariants:
            moments.add(t, (np.asarray(f(*out), dtype=float) - i0) / scale)
        return True

    def slope(self) -> float | None:
        """The least-squares slope of the energy error against t over every step (None
        below 3 points)."""
        return self.energy.slope()


def _trajectory_error(state: np.ndarray, exact: np.ndarray, problem: MeasuredSystem) -> float:
    """``|x - x_exact| / |x_exact - x_e|`` in the energy norm of the equilibrium's Hessian
    (where a phase error delta is the chord 2 |sin(delta / 2)| of a circle), or the
    Euclidean norm without one."""
    centre = problem.centre if problem.centre is not None else np.zeros_like(exact)
    if problem.metric is None:
        size = float(np.linalg.norm(exact - centre))
        return float(np.linalg.norm(state - exact)) / max(size, 1e-300)
    d, r = state - exact, exact - centre
    return float(math.sqrt(max(d @ problem.metric @ d, 0.0))
                 / max(math.sqrt(max(r @ problem.metric @ r, 0.0)), 1e-300))


def _definite(S: np.ndarray | None) -> np.ndarray | None:
    """S (symmetrised) if positive definite, else None."""
    if S is None:
        return None
    S = 0.5 * (S + S.T)
    try:
        np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        return None
    return S


# ---------------------------------------------------------------- the system


def measured_system(tableau: Any, scene: Any, system: Mapping[str, Any] | None,
                    initial: Sequence[float] | None, energy: float | None,
                    time_unit: str | None = None) -> MeasuredSystem:
    """The system to measure on (a scene's ``system:``, or ``system`` itself), its start
    (``initial``, or near its elliptic equilibrium with ``energy``) and its reference
    solution; ``tableau`` is the method whose analysis finds the equilibria."""
    if energy is not None:
        energy = finite_real(energy, "energy")
    if system is not None:
        tree, where, folder = system, "system", Path(".")
    elif scene is not None:
        loaded = load_scene(scene, time_unit)
        time_unit = loaded.time_unit
        if loaded.system is None:
            raise StepsafeError("measure needs a scene with system: (a Hamiltonian "
                                "expression or a linear system), not modes:", loaded.where)
        tree, where, folder = loaded.system, loaded.where, loaded.folder
    else:
        raise StepsafeError("no system: give a scene file with system: (or system= in "
                            "Python)")
    if not isinstance(tree, Mapping):
        raise StepsafeError("system: must be a mapping", where)
    if "hamiltonian" in tree and ("q" in tree or "p" in tree):
        return _many_problem(tree, where, initial, energy)
    if "hamiltonian" in tree:
        return _expression_problem(tableau, tree, where, folder, initial, energy)
    if energy is not None:
        raise StepsafeError("--energy applies to Hamiltonian expressions; give --initial for "
                            "a linear system")
    return _linear_problem(tree, where, folder, initial, time_unit)


def _expression_problem(tableau, tree, where, folder, initial, energy) -> MeasuredSystem:
    try:
        items = analyse_system(tree, where, folder, tableau).items
    except StepsafeError:
        if initial is None:
            raise
        items = []  # nothing to predict from; the given start is still run
    params = {k: float(v) for k, v in (tree.get("parameters") or {}).items()}
    H = parse_hamiltonian(tree["hamiltonian"], params)
    system = hamiltonian_system(H)
    centres = [item for item in items if item["model"] == "oscillator"]
    if initial is not None:
        if energy is not None:
            raise StepsafeError("give --initial or --energy, not both")
        q0, p0 = _pair(initial)
    else:
        if not centres:
            raise StepsafeError("no elliptic equilibrium in the box to start near: give "
                                "--initial q,p", where)
        c = centres[0]
        if energy is None:
            box_q = [float(x) for x in tree["box"]["q"]]
            q0, p0 = c["q"] + 0.1 * (box_q[1] - box_q[0]) / 2, c["p"]
        else:
            q0, p0 = c["q"], _momentum_for(system, c["q"], c["p"], float(energy))
    q, p = np.array([[q0]]), np.array([[p0]])
    check_finite_start(system, q, p)
    beta = None
    if centres:
        nearest = min(centres, key=lambda c: math.hypot(c["q"] - q0, c["p"] - p0))
        beta = float(nearest["beta"])

    def reference(times: list[float], deadline: float | None) -> list[np.ndarray]:
        return reference_run(compiled_rhs(H.compiled, 1), np.array([q0, p0]), times,
                             deadline)

    centre_energy, metric, centre = None, None, None
    if beta is not None:
        centre_energy = float(system.energy(np.array([[nearest["q"]]]),
                                            np.array([[nearest["p"]]]))[0])
        hqq, hqp, hpp = H.jet(float(nearest["q"]), float(nearest["p"])).H
        metric = _definite(np.array([[hqq, hqp], [hqp, hpp]], dtype=float))
        centre = np.array([nearest["q"], nearest["p"]], dtype=float)
    def invariant(text: str, key: str) -> Callable:
        try:
            return hamiltonian_system(parse_hamiltonian(text, params)).energy
        except (StepsafeError, ValueError) as exc:
            raise StepsafeError(str(getattr(exc, "message", exc)), key) from None

    return MeasuredSystem(system, q, p, beta, f"H = {tree['hamiltonian']}", reference,
                    REFERENCE_TEXT, centre_energy, metric, centre,
                    _invariants(tree, where, invariant))


def _many_problem(tree, where, initial, energy) -> MeasuredSystem:
    """An n-dof Hamiltonian expression: the start given, or the lowest elliptic equilibrium
    with its first coordinate moved by a tenth of the box; the prediction for its fastest
    frequency."""
    if energy is not None:
        raise StepsafeError("--energy applies to 1-dof Hamiltonians; give --initial for "
                            "named coordinates")
    H, lo, hi = read_many(tree, where)
    n = len(H.q)

    def invariant(text: str, key: str) -> Callable:
        if isinstance(tree.get("q"), str):
            raise StepsafeError("invariants: apply to named variables (q: [x, y]), not "
                                "indexed ones", key)
        try:
            expr = parse_many(text, tree.get("q"), tree.get("p"), H.parameters, where)
        except StepsafeError as exc:
            raise StepsafeError(exc.message, key) from None
        return system_of(expr).energy

    invariants = _invariants(tree, where, invariant)  # (bad input before the search)
    centres = elliptic_centres(H, lo, hi)
    if initial is not None:
        x0 = _start(initial)
        if x0.size != 2 * n or not np.all(np.isfinite(x0)):
            raise StepsafeError(f"--initial: the initial condition must be {2 * n} finite numbers "
                                f"({', '.join(H.names)})")
    elif centres:
        x0 = centres[0].x.copy()
        x0[0] += 0.1 * (hi[0] - lo[0]) / 2
    else:
        raise StepsafeError("no elliptic equilibrium in the box to start near: give "
                            "--initial", where)
    system = system_of(H)
    q, p = x0[None, :n].copy(), x0[None, n:].copy()
    check_finite_start(system, q, p)
    beta, centre_energy, metric, centre = None, None, None, None
    if centres:
        nearest = min(centres, key=lambda e: float(np.linalg.norm((e.x - x0) / (hi - lo))))
        beta, centre_energy = max(nearest.frequencies), nearest.energy
        metric, centre = _definite(nearest.hessian), nearest.x

    def reference(times: list[float], deadline: float | None) -> list[np.ndarray]:
        return reference_run(compiled_rhs(H.compiled, n), x0, times, deadline)

    return MeasuredSystem(system, q, p, beta, f"H = {H.text} ({n} dof)", reference,
                    REFERENCE_TEXT, centre_energy, metric, centre, invariants)


#: Invariants one scene may declare at most.
MAX_INVARIANTS = 16


def _invariants(tree: Mapping[str, Any], where: str, parse: Callable[[str, str], Any]
                ) -> tuple[tuple[str, Callable[[np.ndarray, np.ndarray], np.ndarray]], ...]:
    """The scene's ``invariants:`` (a mapping of names to expressions in the system's
    variables and parameters), each parsed by ``parse(text, key)`` into a vectorised
    function of (q, p)."""
    declared = tree.get("invariants")
    if declared is None:
        return ()
    if not isinstance(declared, Mapping) or not declared:
        raise StepsafeError("must map names to expressions in the system's variables "
                            "(angular momentum: \"x*py - y*px\")", f"{where}::$.system.invariants")
    if len(declared) > MAX_INVARIANTS:
        raise StepsafeError(f"{len(declared)} invariants; at most {MAX_INVARIANTS}",
                            f"{where}::$.system.invariants")
    out = []
    for name, text in declared.items():
        key = f"{where}::$.system.invariants.{name}"
        if not isinstance(name, str) or not isinstance(text, str):
            raise StepsafeError("must be an expression (a quoted text) under a name", key)
        out.append((name, parse(text, key)))
    return tuple(out)


def compiled_rhs(compiled: Any, n: int) -> Callable:
    """Hamilton's equations ``(dH/dp, -dH/dq)`` of a compiled Hamiltonian of n degrees of
    freedom as the right-hand side ``f(t, y)`` of a state vector ``y = (q, p)``: the
    compiled gradient on the state's entries, no batch arrays."""
    gradient = compiled.function(compiled.gradient_nodes)

    def rhs(_: float, y: np.ndarray) -> np.ndarray:
        g = gradient(*y)  # (the caller sets np.errstate once for the run)
        return np.array(g[n:] + tuple(-v for v in g[:n]), dtype=float)

    return rhs


#: Steps of each reference run at most (it takes about a second per 4000 in Python).
REFERENCE_STEPS = 400_000
#: The reference run's tolerance (relative, and absolute times the start's largest
#: entry), near the least scipy's DOP853 accepts (100 float64 epsilons)...
REFERENCE_TOL = 2.5e-14
#: ... and the tolerance of the second run that estimates its error.
CHECK_TOL = 1e-13
#: What the reference of an expression system is, as reports print it.
REFERENCE_TEXT = (f"adaptive 8th-order Dormand-Prince (scipy DOP853), tolerance "
                  f"{REFERENCE_TOL:g}; its own error estimated from a second run at "
                  f"{CHECK_TOL:g}")


class ReferenceStates(list):
    """The reference states at the times asked for (a list, in their order) and ``check``,
    the states of a second run at a looser tolerance (None where the reference is the
    exact flow): ``|check - reference|`` estimates the reference's own error."""

    check: list[np.ndarray] | None = None


def reference_run(rhs: Callable, x0: np.ndarray, times: list[float],
                  deadline: float | None) -> ReferenceStates:
    """The states at ``times`` of an adaptive 8th-order Dormand-Prince run at tolerance
    :data:`REFERENCE_TOL`, with those of a second run at :data:`CHECK_TOL` as ``check``:
    each bounded by :data:`REFERENCE_STEPS` and the deadline.

    The global error of DOP853 is close to proportional to its tolerance (Kepler at
    e = 0.5 over 10 orbits, against the solution of Kepler's equation: 4.1e-9, 4.4e-10,
    1.1e-10 at 1e-12, 1e-13, 3e-14), so the difference of the two runs is about
    ``(1 - 1/4) err(CHECK_TOL)``, about 3 times the reference's own error: a conservative
    estimate of it, which the reports call the reference's floor."""
    states = ReferenceStates(_dop853(rhs, x0, times, deadline, REFERENCE_TOL))
    states.check = _dop853(rhs, x0, times, deadline, CHECK_TOL)
    return states


def _dop853(rhs: Callable, x0: np.ndarray, times: list[float], deadline: float | None,
            tol: float) -> list[np.ndarray]:
    """The states at ``times`` of one DOP853 run at ``tol`` (under one np.errstate: the
    compiled right-hand side sets none)."""
    with np.errstate(all="ignore"):
        return _dop853_run(rhs, x0, times, deadline, tol)


def _dop853_run(rhs: Callable, x0: np.ndarray, times: list[float], deadline: float | None,
                tol: float) -> list[np.ndarray]:
    import warnings

    from scipy.integrate import DOP853

    scale = max(float(np.abs(x0).max()), 1e-300)
    wanted = sorted(set(times))
    with warnings.catch_warnings():  # (a tolerance at scipy's least is not news)
        warnings.simplefilter("ignore", UserWarning)
        solver = DOP853(rhs, 0.0, np.array(x0, dtype=float), wanted[-1], rtol=tol,
                        atol=tol * scale)
    found: dict[float, np.ndarray] = {}
    k, steps = 0, 0
    while k < len(wanted):
        while k < len(wanted) and wanted[k] <= solver.t:
            found[wanted[k]] = solver.dense_output()(wanted[k]) if wanted[k] < solver.t \
                else np.array(solver.y)
            k += 1
        if k == len(wanted):
            break
        if solver.status != "running":
            raise StepsafeError(f"the reference integration failed at t = {solver.t:.6g}")
        solver.step()
        steps += 1
        if steps > REFERENCE_STEPS or (deadline is not None and steps % 256 == 0
                                       and _time.monotonic() > deadline):
            raise StepsafeError(f"the reference run to T = {wanted[-1]:.6g} needs more than "
                                f"{steps} adaptive steps or the time budget: a shorter "
                                "--time")
    return [np.array(found[t]) for t in times]


def reference_floor(state: np.ndarray, check: np.ndarray, problem: MeasuredSystem) -> float:
    """The reference's own error at one time, relative as trajectory errors are
    (:func:`_trajectory_error` of the check run's state against the reference's)."""
    return _trajectory_error(check, state, problem)


def _start(initial: Sequence[float]) -> np.ndarray:
    """The initial condition as finite floats (q then p), else a StepsafeError."""
    if isinstance(initial, (str, bytes)):
        raise StepsafeError("--initial: the initial condition must be a list of numbers")
    try:
        items = list(initial)
    except TypeError:
        raise StepsafeError("--initial: the initial condition must be a list of numbers") \
            from None
    return np.array([finite_real(v, "--initial") for v in items], dtype=float)


def _pair(initial: Sequence[float]) -> tuple[float, float]:
    values = _start(initial)
    if values.size != 2:
        raise StepsafeError("--initial: the initial condition of a 1-dof system is two finite "
                            "numbers q, p")
    return float(values[0]), float(values[1])


def _momentum_for(system, q: float, p: float, energy: float) -> float:
    """p > p_equilibrium with H(q, p) = energy (bisection on a bracket grown outwards)."""
    def f(x: float) -> float:
        return float(system.energy(np.array([[q]]), np.array([[x]]))[0]) - energy

    if not math.isfinite(energy):
        raise StepsafeError(f"--energy must be a finite number, got {energy}")
    if f(p) > 0:
        raise StepsafeError(f"--energy {energy:g} is below the energy {f(p) + energy:g} of "
                            "the equilibrium started from")
    step = max(abs(p), 1.0)
    hi = p + step
    for _ in range(200):
        if f(hi) >= 0:
            break
        hi = p + (hi - p) * 2
    else:
        raise StepsafeError(f"no momentum reaches the energy {energy:g}")
    lo = p
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        lo, hi = (mid, hi) if f(mid) < 0 else (lo, mid)
    return hi


def _linear_problem(tree, where, folder, initial, time_unit: str | None = None
                    ) -> MeasuredSystem:
    keys = set(tree)
    if "hessian" in keys:
        S = check_square(_matrix(tree["hessian"], where, "hessian", folder), "hessian")
    else:
        key = next((k for k in ("stiffness", "precision", "covariance") if k in keys), None)
        if key is None:
            raise StepsafeError("measure runs Hamiltonian expressions and linear systems "
                                "(stiffness, precision, covariance or hessian)", where)
        A = check_square(_matrix(tree[key], where, key, folder), key)
        scale = units_scale(tree, where, time_unit) if key == "stiffness" else None
        if scale is not None:
            with np.errstate(over="ignore"):
                A = A * scale
            if not np.all(np.isfinite(A)):
                raise StepsafeError("the stiffness overflows in rad per time unit (units:)",
                                    f"{where}::$.system.{key}")
        if key == "covariance":
            A = np.linalg.inv(A)
        M = check_square(_matrix(tree["mass"], where, "mass", folder), "mass") \
            if "mass" in tree else None
        S = stiffness_hessian(A, M)
    n = S.shape[0] // 2
    if n > 2000:
        raise StepsafeError(f"{n} degrees of freedom: measure runs dense systems up to 2000",
                            where)
    if initial is None:
        x0 = np.concatenate([np.random.default_rng(0).normal(size=n), np.zeros(n)])
    else:
        x0 = _start(initial)
        if x0.size != 2 * n or not np.all(np.isfinite(x0)):
            raise StepsafeError(f"--initial: the initial condition must be {2 * n} finite numbers "
                                "(q then p)")
    w2 = np.linalg.eigvals(np.block([[np.zeros((n, n)), np.eye(n)],
                                     [-np.eye(n), np.zeros((n, n))]]) @ S)
    vib = np.abs(w2[np.abs(w2.real) <= 1e-9 * np.abs(w2).max()].imag)
    beta = float(vib.max()) if vib.size else None
    return MeasuredSystem(linear_system(S), x0[None, :n].copy(), x0[None, n:].copy(), beta,
                    f"linear, {n} dof",
                    lambda times, deadline: [exact_linear(S, x0[None, :], t)[0]
                                             for t in times],
                    "the exact flow expm(J S T)", 0.0, _definite(S), np.zeros(2 * n))

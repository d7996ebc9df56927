"""Measure the trade on the user's own system: the public :func:`measure` behind
``stepsafe measure``.

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
  run at tolerance 1e-13 for expressions;
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

import copy
import math
import time as _time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from stepsafe.api import Integrator
from stepsafe.arguments import public
from stepsafe.exceptions import StepsafeError, finite_real, positive_finite

#: Steps of one run at most by default (each costs the method's evaluations in Python)...
MAX_STEPS = 2_000_000
#: ... and at most when asked (``max_steps``).
MAX_STEPS_CAP = 100_000_000
#: States buffered between two vectorised energy evaluations at most (the energy is
#: evaluated at every step, in chunks of this many steps, and not stored)...
ENERGY_CHUNK = 1024
#: ... and state values buffered at most (fewer steps per chunk for many dof).
CHUNK_VALUES = 1 << 20
#: Steps h measured in one call at most.
MAX_STEP_SIZES = 200
#: A run whose energy moves by more than this many times the start's energy above the
#: equilibrium has grown without bound (bounded linear runs stay within kappa - 1).
UNSTABLE = 1e6
#: Default length of a run, in periods of the vibration the start orbits.
DEFAULT_PERIODS = 100


@dataclass(frozen=True)
class MeasureRow:
    """What one step size h did on the system (None where not measured or predicted)."""

    h: float
    steps: int
    time: float
    status: str
    energy_error: float | None
    energy_drift: float | None
    trajectory_error: float | None
    evaluations_per_time: float | None
    iterations_per_step: float | None
    predicted_energy_error: float | None
    predicted_trajectory_error: float | None
    #: Hessian evaluations (and stage-matrix factorisations) per unit time: simplified
    #: Newton's method takes one per implicit step, on top of the force evaluations
    jacobians_per_time: float | None = None
    #: force-gradient terms (Hessian-vector products) per unit time, on top of the forces
    gradients_per_time: float | None = None

    @property
    def energy_ratio(self) -> float | None:
        return _ratio(self.energy_error, self.predicted_energy_error)

    @property
    def trajectory_ratio(self) -> float | None:
        """None once the predicted phase drift reaches half a turn (the prediction is then
        the largest error, 2, not the error)."""
        if self.predicted_trajectory_error is not None and \
                self.predicted_trajectory_error >= 2.0:
            return None
        return _ratio(self.trajectory_error, self.predicted_trajectory_error)

    def to_dict(self) -> dict[str, Any]:
        return {"h": self.h, "steps": self.steps, "time": self.time, "status": self.status,
                "energy_error": self.energy_error, "energy_drift": self.energy_drift,
                "trajectory_error": self.trajectory_error,
                "evaluations_per_time": self.evaluations_per_time,
                "iterations_per_step": self.iterations_per_step,
                "predicted_energy_error": self.predicted_energy_error,
                "predicted_trajectory_error": self.predicted_trajectory_error,
                "energy_ratio": self.energy_ratio, "trajectory_ratio": self.trajectory_ratio,
                "jacobians_per_time": self.jacobians_per_time,
                "gradients_per_time": self.gradients_per_time}


@dataclass(frozen=True)
class MeasureReport:
    """Measured errors and cost of ``method`` on the system for each h (``rows``), from
    ``initial`` (q then p), with the linear predictions for the vibration of angular
    frequency ``beta`` the start orbits (None: no prediction)."""

    method: str
    system: str
    initial: tuple[float, ...]
    energy: float
    beta: float | None
    reference: str
    rows: tuple[MeasureRow, ...]
    time_unit: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe measure --json`` prints."""
        return copy.deepcopy({"method": self.method, "system": self.system,
                              "initial": list(self.initial), "energy": self.energy,
                              "beta": self.beta, "reference": self.reference,
                              "time_unit": self.time_unit,
                              "rows": [r.to_dict() for r in self.rows]})


#: Predicted errors below this are rounding of an exact 0 (a method that conserves every
#: quadratic invariant has no energy error on a linear model): no ratio is formed.
NEGLIGIBLE = 1e-13


def _ratio(measured: float | None, predicted: float | None) -> float | None:
    if measured is None or predicted is None or predicted <= NEGLIGIBLE:
        return None
    return measured / predicted


@dataclass(frozen=True)
class _Problem:
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


@public()
def measure(method: Integrator | str, h: Sequence[float | str] | float | str, *,
            scene: str | Path | None = None,
            system: Mapping[str, Any] | None = None, time: float | str | None = None,
            initial: Sequence[float] | None = None, energy: float | None = None,
            time_unit: str | None = None, solver: str = "fixed-point",
            max_steps: int = MAX_STEPS, budget: float | None = None,
            progress: Callable[[float], None] | None = None) -> MeasureReport:
    """Integrate the system of ``scene`` (or ``system``: the mapping a scene's ``system:``
    holds) with ``method`` at each step size of ``h`` for a time ``time`` (default: 100
    periods of the vibration the start orbits), from ``initial`` (q then p) or, for a
    1-dof Hamiltonian, from the elliptic equilibrium with momentum raised to the
    ``energy`` given (default start: q displaced from that equilibrium by a tenth of the
    box). Implicit methods solve their stages by ``solver``: ``fixed-point`` iteration or
    simplified ``newton`` (the Jacobian from the Hessian at each step's start). A run of
    more than ``max_steps`` steps is refused; after ``budget`` seconds the run under way
    stops (status ``budget``) and the rest are not run (``not run``). Steps and the time
    are numbers in ``time_unit`` (else the scene's, else the unit their texts name), or
    texts with a time unit (``"0.5 fs"``). See the module docstring for what is measured.

    >>> report = measure("verlet", [0.1], system={"hamiltonian": "p**2/2 + q**2/2",
    ...                  "box": {"q": [-1, 1], "p": [-1, 1]}}, initial=[0.0, 1.0])
    >>> row = report.rows[0]
    >>> round(row.energy_ratio, 3), row.status   # the linear bound kappa - 1 is reached
    (1.0, 'ok')
    """
    from stepsafe.api import _integrator
    from stepsafe.core.integrator import Engine
    from stepsafe.systems.scene import time_unit_in_force
    from stepsafe.units import duration
    from stepsafe.units import time_unit as known_time_unit

    integrator = _integrator(method)
    time_unit = known_time_unit(time_unit)
    steps = [h] if isinstance(h, (int, float, str)) else h
    time_unit = time_unit_in_force(time_unit, scene,
                                   list(steps) if isinstance(steps, (list, tuple)) else None,
                                   time)
    hs = _steps(steps, time_unit)
    problem = _problem(integrator, scene, system, initial, energy, time_unit)
    if time is None:
        if problem.beta is None:
            raise StepsafeError("give the time to integrate (--time T): the start orbits no "
                                "vibration whose period would set it")
        time = DEFAULT_PERIODS * 2 * math.pi / problem.beta
    time = positive_finite(duration(time, "time", time_unit), "time")
    if isinstance(max_steps, bool) or not isinstance(max_steps, int) or \
            not 1 <= max_steps <= MAX_STEPS_CAP:
        raise StepsafeError(f"max_steps must be an integer from 1 to {MAX_STEPS_CAP}")
    deadline = None if budget is None else _time.monotonic() + positive_finite(budget,
                                                                                 "budget")
    longest = max(hs)
    if longest > time:
        raise StepsafeError(f"the step h = {longest:.6g} is longer than the run time "
                            f"{time:.6g}: give a longer --time or a smaller step")
    ratios = [time / h * (1 - 1e-12) for h in hs]  # (inf where T / h overflows)
    if not max(ratios) <= max_steps:
        raise StepsafeError(f"T / h = {max(ratios):.3g} steps exceeds the {max_steps} allowed "
                            "in one run: a shorter --time, larger steps or --max-steps")
    counts = [max(1, math.ceil(r)) for r in ratios]
    if not isinstance(solver, str) or solver not in ("fixed-point", "newton"):
        raise StepsafeError(f"solver must be fixed-point or newton, got {str(solver)[:20]!r}")
    try:
        Engine(integrator.tableau, problem.system, solver=solver)
    except ValueError as exc:
        raise StepsafeError(f"{integrator.name}: {exc}") from None
    total, done = float(sum(counts)), 0
    exact = problem.reference([n * step for step, n in zip(hs, counts)], deadline)
    rows = []
    for step, n, state in zip(hs, counts, exact):
        def tick(k: int, done=done) -> None:
            if progress:
                progress((done + k) / total)

        if deadline is not None and _time.monotonic() > deadline:
            rows.append(MeasureRow(step, n, n * step, "not run", *(None,) * 7))
            continue
        rows.append(_run(integrator, problem, step, n, state, tick, solver, deadline))
        done += n
    state = np.concatenate([problem.q0[0], problem.p0[0]])
    return MeasureReport(integrator.name, problem.description, tuple(map(float, state)),
                         float(problem.system.energy(problem.q0, problem.p0)[0]),
                         problem.beta, problem.reference_text, tuple(rows), time_unit)


def _steps(steps: Sequence[float | str], time_unit: str | None) -> list[float]:
    """The step sizes h in ``time_unit`` (numbers, or texts with a time unit)."""
    from stepsafe.units import duration

    try:
        items = list(steps)
    except TypeError:
        raise StepsafeError("h must be a step size or a list of step sizes") from None
    if not items:
        raise StepsafeError("no step sizes: give --h H (repeatable) or --h-range LO,HI,N")
    if len(items) > MAX_STEP_SIZES:
        raise StepsafeError(f"{len(items)} step sizes; at most {MAX_STEP_SIZES} per run")
    return [positive_finite(duration(h, "h", time_unit), "h") for h in items]


def _run(integrator: Integrator, problem: _Problem, h: float, n: int, exact: np.ndarray,
         tick: Callable[[int], None], solver: str = "fixed-point",
         deadline: float | None = None) -> MeasureRow:
    from stepsafe.core.integrator import Engine, SolverFailure

    engine = Engine(integrator.tableau, problem.system, solver=solver)
    system = problem.system
    q, p = problem.q0.copy(), problem.p0.copy()
    e0 = float(system.energy(q, p)[0])
    q, p = engine.start(q, p, h)  # processed methods: P once (else the identity)
    scale = abs(e0 - (problem.equilibrium_energy or 0.0)) or 1.0
    trace = _EnergyTrace(engine, h, e0, scale, q.shape[1])
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
    tick(n)
    T = n * h
    prediction = _prediction(integrator, problem.beta, h, T)
    if status == "ok" and problem.beta is not None and prediction[0] is None:
        status = "beyond z*"  # ran, but past the linear model's first boundary
    if status not in ("ok", "beyond z*"):
        return MeasureRow(h, n, T, status, None, None, None, None, None, *prediction)
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
    return MeasureRow(h, n, T, status, spread, drift, traj,
                      (engine.force_evaluations + outputs) / T, iterations, *prediction,
                      engine.jacobians / T if engine.jacobians else None,
                      engine.gradient_evaluations / T if engine.gradient_evaluations else None)


class _EnergyTrace:
    """The relative energy error ``e_k = (H(x_k) - H(x_0)) / scale`` at every step
    k = 0 .. n of a run (``x_k`` the output state: ``P^-1`` of the kernel's for processed
    methods), reduced on the fly: its least and greatest values (``low``, ``high``) and
    the least-squares slope of ``e_k`` against ``t_k = k h``. No step is skipped (a
    sample every few steps can lock onto the rotation of the orbit and miss the
    extremes) and none is stored: the states of up to :data:`ENERGY_CHUNK` steps are
    buffered, their energies evaluated in one vectorised call, and the chunk's means and
    co-moments merged into the totals by the pairwise update of Chan, Golub and LeVeque
    (``n = n_a + n_b``, ``d = mean_b - mean_a``,
    ``S_tt = S_tt,a + S_tt,b + d_t^2 n_a n_b / n``, likewise ``S_te``), so that the slope
    ``S_te / S_tt`` is that of the fit through every step, without the cancellation of
    raw sums."""

    def __init__(self, engine: Any, h: float, e0: float, scale: float, dof: int) -> None:
        self.engine, self.h, self.e0, self.scale = engine, h, e0, scale
        size = max(1, min(ENERGY_CHUNK, CHUNK_VALUES // (2 * dof)))
        self.Q, self.P = np.empty((size, dof)), np.empty((size, dof))
        self.filled = 0  # steps buffered
        self.step = 0  # steps pushed
        # the start: k = 0, e_0 = 0
        self.count, self.t_mean, self.e_mean, self.S_tt, self.S_te = 1, 0.0, 0.0, 0.0, 0.0
        self.low = self.high = 0.0

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
        e = (self.engine.system.energy(*self.engine.output(Q, P, self.h)) - self.e0) \
            / self.scale
        stable = np.isfinite(Q).all(axis=1) & np.isfinite(P).all(axis=1) & \
            (np.abs(e) <= UNSTABLE)  # (nan compares False)
        if not stable.all():
            return False
        t = self.h * np.arange(self.step - m + 1, self.step + 1, dtype=float)
        t_mean, e_mean = float(t.mean()), float(e.mean())
        dt = t - t_mean
        total = self.count + m
        shift_t, shift_e = t_mean - self.t_mean, e_mean - self.e_mean
        weight = self.count * m / total
        self.S_tt += float(dt @ dt) + shift_t * shift_t * weight
        self.S_te += float(dt @ (e - e_mean)) + shift_t * shift_e * weight
        self.t_mean += shift_t * m / total
        self.e_mean += shift_e * m / total
        self.count = total
        self.low, self.high = min(self.low, float(e.min())), max(self.high, float(e.max()))
        return True

    def slope(self) -> float | None:
        """The least-squares slope of e against t over every step (None below 3 points)."""
        if self.count < 3 or not self.S_tt > 0:
            return None
        return self.S_te / self.S_tt


def _trajectory_error(state: np.ndarray, exact: np.ndarray, problem: _Problem) -> float:
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


def _prediction(integrator: Integrator, beta: float | None, h: float, T: float
                ) -> tuple[float | None, float | None]:
    """The linear model's energy error bound and phase drift over T (None beyond the
    method's first boundary or without a vibration)."""
    if beta is None:
        return None, None
    from stepsafe.core.accuracy import errors
    from stepsafe.core.regions import find_region

    z = beta * h
    boundary = find_region(integrator.tableau, "oscillator", max(10.0, 1.1 * z)).first_boundary
    if boundary is not None and z >= boundary:
        return None, None
    e = errors(integrator.tableau, np.array([z]), "oscillator")
    energy, phase = float(np.asarray(e.energy)[0]), float(np.asarray(e.phase)[0])
    if not (math.isfinite(energy) and math.isfinite(phase)):
        return None, None
    drift = abs(phase) * beta * T  # the phase the run falls behind (or ahead) by
    energy = abs(energy) if abs(energy) > NEGLIGIBLE else 0.0
    return energy, 2.0 * abs(math.sin(min(drift, math.pi) / 2))


# ---------------------------------------------------------------- the system


def _problem(integrator: Integrator, scene: Any, system: Mapping[str, Any] | None,
             initial: Sequence[float] | None, energy: float | None,
             time_unit: str | None = None) -> _Problem:
    from stepsafe.systems.scene import load_scene

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
        return _expression_problem(integrator, tree, where, folder, initial, energy)
    if energy is not None:
        raise StepsafeError("--energy applies to Hamiltonian expressions; give --initial for "
                            "a linear system")
    return _linear_problem(tree, where, folder, initial, time_unit)


def _expression_problem(integrator, tree, where, folder, initial, energy) -> _Problem:
    from stepsafe.systems.dynamics import check_finite_start, hamiltonian_system
    from stepsafe.systems.loader import analyse_system
    from stepsafe.systems.nonlinear import parse_hamiltonian

    try:
        items = analyse_system(tree, where, folder, integrator.tableau).items
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
        def rhs(_, y):
            dq, dp = system.rates(np.array([[y[0]]]), np.array([[y[1]]]))
            return [dq[0, 0], dp[0, 0]]

        return _reference(rhs, np.array([q0, p0]), times, deadline)

    centre_energy, metric, centre = None, None, None
    if beta is not None:
        centre_energy = float(system.energy(np.array([[nearest["q"]]]),
                                            np.array([[nearest["p"]]]))[0])
        hqq, hqp, hpp = H.jet(float(nearest["q"]), float(nearest["p"])).H
        metric = _definite(np.array([[hqq, hqp], [hqp, hpp]], dtype=float))
        centre = np.array([nearest["q"], nearest["p"]], dtype=float)
    return _Problem(system, q, p, beta, f"H = {tree['hamiltonian']}", reference,
                    "adaptive 8th-order Dormand-Prince (scipy DOP853), tolerance 1e-13",
                    centre_energy, metric, centre)


def _many_problem(tree, where, initial, energy) -> _Problem:
    """An n-dof Hamiltonian expression: the start given, or the lowest elliptic equilibrium
    with its first coordinate moved by a tenth of the box; the prediction for its fastest
    frequency."""
    from stepsafe.systems.dynamics import check_finite_start
    from stepsafe.systems.loader import read_many
    from stepsafe.systems.manydof import find_many, system_of

    if energy is not None:
        raise StepsafeError("--energy applies to 1-dof Hamiltonians; give --initial for "
                            "named coordinates")
    H, lo, hi = read_many(tree, where)
    n = len(H.q)
    centres = [e for e in find_many(H, lo, hi).equilibria if e.kind == "elliptic"]
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
        def rhs(_, y):
            dq, dp = system.rates(y[None, :n], y[None, n:])
            return np.concatenate([dq[0], dp[0]])

        return _reference(rhs, x0, times, deadline)

    return _Problem(system, q, p, beta, f"H = {H.text} ({n} dof)", reference,
                    "adaptive 8th-order Dormand-Prince (scipy DOP853), tolerance 1e-13",
                    centre_energy, metric, centre)


#: Steps of the reference run at most (it takes about a second per 4000 in Python).
REFERENCE_STEPS = 400_000


def _reference(rhs: Callable, x0: np.ndarray, times: list[float],
               deadline: float | None) -> list[np.ndarray]:
    """The states at ``times`` of an adaptive 8th-order Dormand-Prince run (tolerance
    1e-13), bounded by :data:`REFERENCE_STEPS` and the deadline."""
    from scipy.integrate import DOP853

    scale = max(float(np.abs(x0).max()), 1e-300)
    wanted = sorted(set(times))
    solver = DOP853(rhs, 0.0, np.array(x0, dtype=float), wanted[-1], rtol=1e-13,
                    atol=1e-13 * scale)
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
                    ) -> _Problem:
    from stepsafe.systems.dynamics import exact_linear, linear_system, stiffness_hessian
    from stepsafe.systems.linear import check_square
    from stepsafe.systems.loader import _matrix, units_scale

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
    return _Problem(linear_system(S), x0[None, :n].copy(), x0[None, n:].copy(), beta,
                    f"linear, {n} dof",
                    lambda times, deadline: [exact_linear(S, x0[None, :], t)[0]
                                             for t in times],
                    "the exact flow expm(J S T)", 0.0, _definite(S), np.zeros(2 * n))


# ---------------------------------------------------------------- refinement by measurement

#: Measurement runs of one refinement at most, and the relative bracket it stops at.
MAX_REFINE_RUNS = 24
REFINE_REL = 1e-3


@dataclass(frozen=True)
class Refinement:
    """The largest step ``h`` (within the safe steps for the vibration the start orbits)
    whose measured ``quantity`` (``energy``: the energy spread; ``trajectory``: the
    trajectory error at T) is at most ``tol``, found by bisection on measurements
    (``runs``: every run made, in order), beside ``predicted``, the h the linear model
    gives for the same tolerance. ``limited_by``: ``tolerance``, ``safety`` (met up to the
    safe limit) or ``unreachable`` (not met down to the smallest h tried)."""

    quantity: str
    tol: float
    h: float | None
    error: float | None
    predicted: float | None
    h_safe: float | None
    limited_by: str
    runs: MeasureReport

    def to_dict(self) -> dict[str, Any]:
        return {"quantity": self.quantity, "tol": self.tol, "h": self.h, "error": self.error,
                "predicted_h": self.predicted, "h_safe": self.h_safe,
                "limited_by": self.limited_by, "runs": self.runs.to_dict()}


@public()
def refine(method: Integrator | str, quantity: str, tol: float, *,
           scene: str | Path | None = None, system: Mapping[str, Any] | None = None,
           time: float | str | None = None, initial: Sequence[float] | None = None,
           energy: float | None = None, time_unit: str | None = None,
           solver: str = "fixed-point",
           progress: Callable[[float], None] | None = None) -> Refinement:
    """The largest h whose measured error meets ``tol`` on the scene's own system, by
    bisection on measurements started from the linear prediction (what
    ``advise --tol-*`` predicts, checked and corrected by running the method).
    ``quantity``: ``energy`` or ``trajectory`` (see :class:`MeasureRow`).

    >>> r = refine("verlet", "energy", 1e-3, system={"hamiltonian": "p**2/2 - cos(q)",
    ...            "box": {"q": [-4, 4], "p": [-1, 1]}}, initial=[0.0, 0.5], time=20.0)
    >>> r.limited_by, round(r.h / r.predicted, 2)   # the pendulum allows a little more
    ('tolerance', 1.01)
    """
    from stepsafe.api import _integrator
    from stepsafe.core.accuracy import z_for_tolerance
    from stepsafe.core.regions import find_region
    from stepsafe.systems.scene import time_unit_in_force
    from stepsafe.units import duration
    from stepsafe.units import time_unit as known_time_unit

    if not isinstance(quantity, str) or quantity not in ("energy", "trajectory"):
        raise StepsafeError(f"quantity must be energy or trajectory, got {quantity!r}")
    tol = positive_finite(tol, f"the {quantity} tolerance")
    integrator = _integrator(method)
    time_unit = time_unit_in_force(known_time_unit(time_unit), scene, time)
    problem = _problem(integrator, scene, system, initial, energy, time_unit)
    if problem.beta is None:
        raise StepsafeError("the start orbits no vibration: nothing to predict h from")
    beta = problem.beta
    if time is None:
        time = DEFAULT_PERIODS * 2 * math.pi / beta
    time = positive_finite(duration(time, "time", time_unit), "time")
    z_star = find_region(integrator.tableau, "oscillator").first_boundary or 10.0
    h_safe = z_star / beta
    if quantity == "energy":
        step = z_for_tolerance(integrator.tableau, tol, z_star, kind="energy")
    else:  # the phase error whose drift over T gives that trajectory error
        phase_tol = 2 * math.asin(min(tol, 2.0) / 2) / (beta * time)
        step = z_for_tolerance(integrator.tableau, phase_tol, z_star, kind="phase")
    predicted = None if step.z is None else step.z / beta
    key = "energy_error" if quantity == "energy" else "trajectory_error"
    top = h_safe * (1 - 1e-9)
    rows: list[MeasureRow] = []

    def error_at(h: float) -> float:
        if len(rows) >= MAX_REFINE_RUNS:
            raise _Exhausted
        try:
            report = measure(integrator, [h], scene=scene, system=system, time=time,
                             initial=initial, energy=energy, time_unit=time_unit,
                             solver=solver)
        except StepsafeError:
            raise _Exhausted from None  # a run too long for the step budget: stop here
        row = report.rows[0]
        rows.append(row)
        if progress:
            progress(len(rows) / MAX_REFINE_RUNS)
        value = getattr(row, key)
        return math.inf if row.status != "ok" or value is None else value

    lo = hi = None
    h = min(predicted or h_safe / 10, top)
    limited = "tolerance"
    if predicted is None:  # the linear model meets the tolerance at no step: say so
        return Refinement(quantity, tol, None, None, None, h_safe, "unreachable",
                          MeasureReport(integrator.name, problem.description, (), float("nan"),
                                        beta, problem.reference_text, (), time_unit))
    try:
        if error_at(h) <= tol:
            lo = h
            while hi is None:
                if lo >= top:
                    limited = "safety"
                    break
                h = min(2 * lo, top)
                if error_at(h) <= tol:
                    lo = h
                else:
                    hi = h
        else:
            hi = h
            while lo is None:
                h = hi / 4
                if error_at(h) <= tol:
                    lo = h
                else:
                    hi = h
        while hi is not None and hi / lo > 1 + REFINE_REL:
            mid = math.sqrt(lo * hi)
            if error_at(mid) <= tol:
                lo = mid
            else:
                hi = mid
    except _Exhausted:
        if lo is None:
            limited = "unreachable"
    best = None if lo is None else next(getattr(r, key) for r in rows if r.h == lo)
    runs = MeasureReport(integrator.name, problem.description,
                         tuple(map(float, np.concatenate([problem.q0[0], problem.p0[0]]))),
                         float(problem.system.energy(problem.q0, problem.p0)[0]), beta,
                         problem.reference_text, tuple(rows), time_unit)
    return Refinement(quantity, tol, lo, best, predicted, h_safe, limited, runs)


class _Exhausted(Exception):
    """The refinement used all its runs."""


__all__ = ["MeasureReport", "MeasureRow", "Refinement", "measure", "refine"]

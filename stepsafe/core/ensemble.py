"""Many trajectories of a method's nonlinear map at once: the one engine behind ensembles of
initial conditions (``measure --ensemble``, the thermal bands and drift, HMC proposals on a
target).

The rows of arrays ``q``, ``p`` of shape ``(n, d)`` are n trajectories of a system of d
degrees of freedom (a :class:`~stepsafe.core.integrator.System`: ``dH/dq``, ``dH/dp`` and
``H`` on such arrays). :func:`integrate` advances all of them by the method's own step,
:class:`~stepsafe.core.integrator.Engine` (every kind the protocol decomposes into blocks:
splittings, compositions, processed methods ``P^-1 K^N P``, force-gradient splittings,
explicit and implicit Runge–Kutta and partitioned RK), each row at its own step h when h
is a column. After each step k = 1 .. N it

* marks a row **escaped** when its state (or, where measured, its energy) is not finite,
  when the state of an implicit method's stage iteration does not converge for it (the
  batch is halved until the failing rows are alone), when a coordinate leaves
  ``|q - centre| <= reach`` (optional), or when, with a ``growth`` g given,
  ``H_k - E_ref > g (H_0 - E_ref)`` (``(H_k - H_0) + (H_0 - E_ref) <= g max(H_0 - E_ref, 0)``
  fails; a NaN bound is no bound), or when a caller's test ``leaves(q, p)`` of the output
  state holds (where the energy is measured). An escaped row is
  **frozen**: its state is kept as it was at that step, and no force is asked for it
  again (the arrays shrink to the rows still running, the force just taken going with
  them);
* measures, every ``energy_every`` steps and at the last (0: never), the energy error
  ``dH_k = H_k - H_0`` of every running row, on the method's output (``P^-1`` of the state
  for a processed method; ``H_0`` that of the given start), and keeps each row's largest
  ``|dH_k|``;
* with ``fit`` (every step measured), accumulates per row ``sum x``, ``sum k x``,
  ``sum x^2`` of ``x = dH_k / unit``: the least-squares slope of ``dH`` against k, per step,
  ``b = (N sum k x - S_1 sum x) / (N S_2 - S_1^2)`` (``S_1 = N (N + 1) / 2``,
  ``S_2 = N (N + 1) (2N + 1) / 6``), and the variance of ``dH`` over time, with nothing
  stored per step (memory O(n d) whatever N);
* with ``sample_every`` m, stores ``dH_k`` at k = m, 2m, ... (NaN once escaped);
* with ``stop_escapes`` s, stops after the step at which the s-th row escaped: a caller
  whose verdict is settled by s escapes (a step with one failure is not safe) need not run
  the rest. Each row's trajectory is the same whether the run stops or not (its start
  alone decides it), so the escapes seen are those of the full run up to that step.

An implicit step (and any step on an H that mixes q and p) iterates its stage equations
until they change by at most ``tol`` times their size or 1
(:class:`~stepsafe.core.integrator.Engine`): it runs in the coordinates ``q / Lq``,
``p / Lp``, with ``Lq`` and ``Lp`` the powers of two at or just above the largest
``|q0|`` and ``|p0|`` of the batch (exact, and the same trajectories in exact arithmetic),
so that the test is relative in any units.

Costs: the force evaluations (calls of ``dH/dq``) are counted row by row, summed over the
trajectories; a force at the start given as ``force0`` is not counted (a sampler has it
from its previous iteration).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

import numpy as np

from stepsafe.core.integrator import Engine, SolverFailure, System
from stepsafe.exceptions import StepsafeError
from stepsafe.methods.tableaux import Method


@dataclass(frozen=True)
class Trajectories:
    """What :func:`integrate` returns (n trajectories of d degrees of freedom, N steps).

    Attributes
    ----------
    q, p : ndarray
        The states after the last step (n, d), on the method's output; an escaped row's
        the state at the step it escaped (as the step left it: possibly not finite, and a
        processed method's kernel variables).
    energy0 : ndarray or None
        ``H_0`` of each row (n,) (None where no energy was asked for).
    escaped : ndarray
        Bool (n,).
    escaped_at : ndarray
        The step at which each row escaped (0 for a row that did not).
    worst : ndarray or None
        The largest ``|H_k - H_0|`` over the measured steps (n,), ``inf`` for an escaped
        row (None when no energy was measured).
    last : ndarray or None
        ``H_N - H_0`` (n,), ``inf`` for an escaped row.
    sums : ndarray or None
        ``(3, n)``: ``sum x``, ``sum k x``, ``sum x^2`` over k = 1 .. N with
        ``x = dH_k / unit`` (zeros for escaped rows; None without ``fit``).
    samples : ndarray or None
        ``(N // m, n)``: ``dH_k`` at ``k = m, 2m, ...`` (NaN from a row's escape on).
    forces : float
        Force evaluations summed over the trajectories.
    steps : int
        N: the steps run (fewer than asked when the run stopped at ``stop_escapes``
        escapes; the fit and ``last`` are over them).
    unit : float
        The unit of ``sums``.
    """

    q: np.ndarray
    p: np.ndarray
    energy0: np.ndarray | None
    escaped: np.ndarray
    escaped_at: np.ndarray
    worst: np.ndarray | None
    last: np.ndarray | None
    sums: np.ndarray | None
    samples: np.ndarray | None
    forces: float
    steps: int
    unit: float = 1.0

    def slopes(self) -> np.ndarray:
        """Each row's least-squares slope of ``dH_k / unit`` against the step number k
        (per step; see the module docstring). NaN for escaped rows."""
        if self.sums is None:
            raise ValueError("the run was not asked to fit the energy (fit=True)")
        N = float(self.steps)
        sum_n = N * (N + 1) / 2
        sum_nn = N * (N + 1) * (2 * N + 1) / 6
        s = self.sums
        b = (N * s[1] - sum_n * s[0]) / (N * sum_nn - sum_n ** 2)
        return np.where(self.escaped, np.nan, b)

    def variances(self) -> np.ndarray:
        """Each row's variance of ``dH_k / unit`` over k = 1 .. N (NaN for escaped rows)."""
        if self.sums is None:
            raise ValueError("the run was not asked to fit the energy (fit=True)")
        N = float(self.steps)
        s = self.sums
        v = np.maximum(s[2] / N - (s[0] / N) ** 2, 0.0)
        return np.where(self.escaped, np.nan, v)


def separable_system(gradient: Callable[[np.ndarray], np.ndarray],
                     potential: Callable[[np.ndarray], np.ndarray],
                     masses: Any) -> System:
    """The system ``H = U(q) + p^T M^-1 p / 2`` with ``M = diag(masses)``.

    Parameters
    ----------
    gradient : callable
        ``grad U`` on arrays (n, d) -> (n, d).
    potential : callable
        ``U`` on arrays (n, d) -> (n,).
    masses : array_like
        (d,), positive.

    Returns
    -------
    System
    """
    inverse = 1.0 / np.asarray(masses, dtype=float)
    if inverse.ndim != 1 or not np.all(np.isfinite(inverse)) or not np.all(inverse > 0):
        raise StepsafeError("masses must be a vector of positive finite numbers")

    def energy(q: np.ndarray, p: np.ndarray) -> np.ndarray:
        return potential(q) + 0.5 * np.einsum("mi,mi->m", p * inverse, p)

    return System(dH_dq=lambda q, p: gradient(q), dH_dp=lambda q, p: p * inverse,
                  energy=energy, separable=True, dimension=int(inverse.size))


def engine_for(method: Method, system: System, **options: Any) -> Engine:
    """The method's :class:`~stepsafe.core.integrator.Engine` on the system, a method it
    cannot run there (a Langevin step, a processed or force-gradient method on an H that
    mixes q and p, a force-gradient method without the Hessian) refused by a
    :class:`StepsafeError` naming the method."""
    try:
        return Engine(method, system, **options)
    except ValueError as exc:
        name, text = getattr(method, "name", type(method).__name__), str(exc)
        raise StepsafeError(text if text.startswith(f"{name}:") else f"{name}: {text}"
                            ) from None


def integrate(method: Method, system: System, q0: np.ndarray, p0: np.ndarray, h: Any,
              steps: int, *, energy_every: int = 1, reference_energy: float = 0.0,
              growth: Any = None, centre: np.ndarray | None = None, reach: Any = None,
              fit: bool = False, unit: float = 1.0, sample_every: int = 0,
              energy0: np.ndarray | None = None, force0: np.ndarray | None = None,
              tol: float = 1e-14, max_iterations: int = 200,
              stop_escapes: int | None = None,
              leaves: Callable[[np.ndarray, np.ndarray, np.ndarray | None], np.ndarray]
              | None = None, leave_data: np.ndarray | None = None,
              progress: Callable[[float], None] | None = None) -> Trajectories:
    """Advance the trajectories from the rows of ``(q0, p0)`` by ``steps`` steps of the
    method (module docstring).

    Parameters
    ----------
    method : Method
        Any deterministic method of :mod:`stepsafe.methods.tableaux`.
    system : System
        ``H`` through its gradients, on arrays (n, d).
    q0, p0 : ndarray
        The starts (n, d) (not modified).
    h : float or ndarray
        The step, or one per row (n,).
    steps : int
        N >= 1.
    energy_every : int
        Measure the energy every this many steps and at the last; 0: never (then
        ``worst``, ``last`` are None and neither ``growth`` nor ``fit`` may be given).
    reference_energy : float
        ``E_ref`` of the growth test (the energy at the minimum).
    growth : float or ndarray, optional
        The escape multiple g (scalar or per row): ``H_k - E_ref > g (H_0 - E_ref)``
        escapes.
    centre, reach : ndarray, optional
        A row escapes when a coordinate of its output leaves ``|q - centre| <= reach``
        (``reach`` (d,) or per row (n, d); tested every step).
    fit : bool
        Accumulate the sums of the energy fit (every step measured).
    unit : float
        Energies are divided by it in the sums (their squares of ``1e200`` overflow).
    sample_every : int
        Store ``dH_k`` every this many steps (0: not).
    energy0 : ndarray, optional
        ``H(q0, p0)`` if known.
    force0 : ndarray, optional
        ``dH/dq(q0, p0)`` if known (not counted).
    tol, max_iterations : float, int
        The stage iteration of implicit methods
        (:class:`~stepsafe.core.integrator.Engine`).
    stop_escapes : int, optional
        Stop after the step at which this many rows have escaped (module docstring).
    leaves : callable, optional
        ``leaves(q, p, data)`` of the running rows' output state (r, d) and their rows of
        ``leave_data`` (None without it): True for those that escape (tested where the
        energy is measured).
    leave_data : ndarray, optional
        Per row (n, ...), what ``leaves`` needs of each row's start.
    progress : callable, optional
        Called with the fraction of steps done.

    Returns
    -------
    Trajectories
    """
    q0 = np.asarray(q0, dtype=float)
    p0 = np.asarray(p0, dtype=float)
    if q0.ndim != 2 or p0.shape != q0.shape:
        raise StepsafeError(f"q0 and p0 must be arrays of one shape (n, d); got {q0.shape} "
                            f"and {p0.shape}")
    steps = int(steps)
    if steps < 1:
        raise StepsafeError(f"at least 1 step is needed, got {steps}")
    every = int(energy_every)
    if every < 0:
        raise StepsafeError(f"energy_every must not be negative, got {every}")
    if every == 0 and (growth is not None or fit or sample_every or leaves is not None):
        raise StepsafeError("the growth and escape tests, the fit and the samples need the "
                            "energy")
    if fit and every != 1:
        raise StepsafeError("the energy fit needs the energy at every step")
    if sample_every and every != 1 and sample_every % every:
        raise StepsafeError("samples are taken where the energy is measured")
    n = q0.shape[0]
    hh = np.asarray(h, dtype=float)
    hcol: Any = hh[:, None] if hh.ndim == 1 else float(hh)
    if hh.ndim == 1 and hh.shape[0] != n:
        raise StepsafeError(f"h must be one step or one per trajectory ({n}), got {hh.size}")
    # count the force evaluations row by row (calls of dH/dq on the running rows)
    count = [0.0]
    force = system.dH_dq

    def counted(q: np.ndarray, p: np.ndarray) -> np.ndarray:
        count[0] += q.shape[0]
        return force(q, p)

    # an implicit step iterates its stages until they change by at most tol times their
    # size (and 1): in units where the starts are of order 1 (powers of two, exact) that
    # test is relative at every scale
    Lq = Lp = 1.0
    run_system = dataclasses.replace(system, dH_dq=counted)
    if not method.explicit or not system.separable:
        Lq, Lp = _unit(q0), _unit(p0)
        run_system = _scaled(run_system, Lq, Lp)
    engine = engine_for(method, run_system, tol=tol, max_iterations=max_iterations)
    processed = method.processor_operations is not None
    measuring = every > 0
    with np.errstate(all="ignore"):
        H0 = None
        if measuring:
            H0 = system.energy(q0, p0) if energy0 is None else np.asarray(energy0, float)
        limit = None
        if growth is not None and H0 is not None:
            offset = H0 - reference_energy
            with np.errstate(invalid="ignore"):
                limit = np.broadcast_to(growth, (n,)) * np.maximum(offset, 0.0)
            limit = np.where(np.isnan(limit), np.inf, limit)
        ref = reach_run = None
        if reach is not None:
            ref = None if centre is None or not np.any(np.asarray(centre)) else \
                np.asarray(centre, dtype=float)[None, :] / Lq  # (None: the origin)
            reach_run = np.asarray(reach, dtype=float) / Lq
            per_row = reach_run.ndim == 2
            reach_run = np.broadcast_to(reach_run, q0.shape) if per_row else reach_run[None, :]
        q, p = (q0, p0) if Lq == Lp == 1.0 else (q0 / Lq, p0 / Lp)
        if force0 is not None:
            engine.know_force(q, p, np.asarray(force0, dtype=float) / Lp)
        q_out, p_out = q.copy(), p.copy()
        q, p = engine.start(q, p, hcol)

        live = np.arange(n)  # the rows still running, in order
        escaped_at = np.zeros(n, dtype=int)
        worst = np.zeros(n) if measuring else None
        last = np.full(n, np.nan) if measuring else None
        sums = np.zeros((3, n)) if fit else None
        samples = np.full((steps // sample_every, n), np.nan) if sample_every else None
        H0_run, lim_run = H0, limit
        # per running row, compacted as rows escape (written back at the end)
        excess_run = None if H0 is None else H0 - reference_energy
        data_run = None if leave_data is None else np.asarray(leave_data)
        worst_run = np.zeros(n) if measuring else None
        sums_run = np.zeros((3, n)) if fit else None
        stop = n + 1 if stop_escapes is None else max(1, int(stop_escapes))
        ran = steps
        for k in range(1, steps + 1):
            q, p, bad = _step(engine, q, p, hcol)
            # (the box test below fails a coordinate that is not finite; each test first
            # over the whole batch, by rows only when some row fails it)
            if reach_run is None:
                bad |= _not_finite(q) | _not_finite(p)
            elif not np.isfinite(np.add.reduce(p, axis=None)):
                bad |= _not_finite(p)
            measured = measuring and (k % every == 0 or k == steps)
            if processed and (measured or reach_run is not None):
                qo, po = engine.output(q, p, hcol)
            else:
                qo, po = q, p
            if reach_run is not None:
                inside = np.abs(qo if ref is None else qo - ref) <= reach_run
                if not inside.all():
                    bad |= ~inside.all(axis=1)
            if measured:
                assert H0_run is not None
                dH = run_system.energy(qo, po) - H0_run
                fine = np.isfinite(dH)
                if lim_run is not None:
                    assert excess_run is not None
                    fine &= dH + excess_run <= lim_run
                if leaves is not None:
                    fine &= ~np.asarray(leaves(qo * Lq, po * Lp, data_run), dtype=bool)
                if not fine.all():
                    bad |= ~fine
            if bad.any():
                gone = live[bad]
                q_out[gone], p_out[gone] = q[bad], p[bad]
                escaped_at[gone] = k
                if worst is not None:
                    worst[gone] = np.inf
                keep = ~bad
                live = live[keep]
                q, p = engine.take(keep, q, p)
                if isinstance(hcol, np.ndarray):
                    hcol = hcol[keep]
                if H0_run is not None:
                    H0_run = H0_run[keep]
                if excess_run is not None:
                    excess_run = excess_run[keep]
                if data_run is not None:
                    data_run = data_run[keep]
                if worst_run is not None:
                    worst_run = worst_run[keep]
                if sums_run is not None:
                    sums_run = sums_run[:, keep]
                if lim_run is not None:
                    lim_run = lim_run[keep]
                if reach_run is not None and per_row:
                    reach_run = reach_run[keep]
                if measured:
                    dH = dH[keep]
                if not live.size:
                    break
            stopping = n - live.size >= stop
            if measured:
                assert worst_run is not None
                worst_run = np.fmax(worst_run, np.abs(dH))
                if k == steps or stopping:
                    assert last is not None
                    last[live] = dH
                if sums_run is not None:  # (in units: squares of energies of 1e200 overflow)
                    x = dH / unit
                    sums_run[0] += x
                    sums_run[1] += k * x
                    sums_run[2] += x * x
                if samples is not None and k % sample_every == 0:
                    samples[k // sample_every - 1, live] = dH
            if progress is not None and k % 256 == 0:
                progress(k / steps)
            if stopping:
                ran = k
                break
        if worst is not None and worst_run is not None:
            worst[live] = worst_run
        if sums is not None and sums_run is not None:
            sums[:, live] = sums_run
        out_bad: np.ndarray = np.zeros(live.size, dtype=bool)
        if live.size:
            qo, po = engine.output(q, p, hcol) if processed else (q, p)
            out_bad = np.asarray(~(np.isfinite(qo).all(axis=1) & np.isfinite(po).all(axis=1)))
            q_out[live], p_out[live] = qo, po
        if Lq != 1.0 or Lp != 1.0:
            q_out *= Lq
            p_out *= Lp
            if out_bad.any():  # (the output map itself left the finite numbers)
                escaped_at[live[out_bad]] = ran
                if worst is not None:
                    worst[live[out_bad]] = np.inf
        escaped = escaped_at > 0
        if last is not None:
            last = np.where(escaped, np.inf, last)
        if sums is not None:
            sums[:, escaped] = 0.0
    if progress is not None:
        progress(1.0)
    return Trajectories(q_out, p_out, H0, escaped, escaped_at, worst, last, sums, samples,
                        count[0], ran, float(unit))


def _unit(x: np.ndarray) -> float:
    """The power of two at or just above the largest ``|x|`` (1 when that is 0 or not
    finite)."""
    with np.errstate(all="ignore"):
        size = float(np.max(np.abs(x))) if x.size else 0.0
    if not (size > 0 and np.isfinite(size)):
        return 1.0
    return float(np.ldexp(1.0, int(np.frexp(size)[1])))


def _scaled(system: System, Lq: float, Lp: float) -> System:
    """The system in the coordinates ``x = q / Lq``, ``y = p / Lp`` (Lq, Lp powers of two:
    exact): ``dx/dt = dH/dp / Lq``, ``dy/dt = -dH/dq / Lp``, H unchanged in value."""
    if Lq == Lp == 1.0:
        return system
    hessian = system.hessian

    def scaled_hessian(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, ...]:
        assert hessian is not None
        H_qq, H_qp, H_pp = hessian(Lq * x, Lp * y)
        return H_qq * (Lq / Lp), H_qp, H_pp * (Lp / Lq)

    return System(lambda x, y: system.dH_dq(Lq * x, Lp * y) / Lp,
                  lambda x, y: system.dH_dp(Lq * x, Lp * y) / Lq,
                  lambda x, y: system.energy(Lq * x, Lp * y), system.separable,
                  system.dimension, None,
                  None if hessian is None else scaled_hessian)


def _not_finite(x: np.ndarray) -> np.ndarray:
    """The rows of x with a value that is not finite: by one sum over the whole array when
    that is finite (then every value is: an infinity or NaN would make it so), by rows
    when it is not (a sum of finite values may overflow)."""
    if np.isfinite(np.add.reduce(x, axis=None)):
        return np.zeros(x.shape[0], dtype=bool)
    return ~np.isfinite(x).all(axis=1)


def _step(engine: Engine, q: np.ndarray, p: np.ndarray, h: Any
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One step of every row; rows whose implicit stage iteration fails are returned
    unchanged and marked (the batch is halved until the failing rows are alone)."""
    try:
        q1, p1 = engine.step(q, p, cast(float, h))
        return q1, p1, np.zeros(q.shape[0], dtype=bool)
    except SolverFailure:
        if q.shape[0] == 1:
            return q, p, np.ones(1, dtype=bool)
    half = q.shape[0] // 2
    split = isinstance(h, np.ndarray) and h.shape[0] == q.shape[0]
    ha, hb = (h[:half], h[half:]) if split else (h, h)
    qa, pa, fa = _step(engine, q[:half], p[:half], ha)
    qb, pb, fb = _step(engine, q[half:], p[half:], hb)
    return np.concatenate([qa, qb]), np.concatenate([pa, pb]), np.concatenate([fa, fb])

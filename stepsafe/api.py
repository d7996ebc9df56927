"""The public Python API: the same answers as the command line, as frozen objects.

Every function takes numbers and arrays (or file paths for scenes and method files), never
prints and never exits; bad input raises :class:`~stepsafe.exceptions.StepsafeError` (exit code
2 on the command line), whose ``where`` names the file and key at fault, and so does an
argument a function does not take (the error lists those it takes). Arguments after the
first one or two (the method, the frequencies, the step) are given by name. Each result has
``to_dict()``, which is exactly the command's ``--json`` output.

Conventions: z = beta*h; a vibration of angular frequency ``beta`` (rad per time unit) is
the model ``oscillator`` (q' = p, p' = -beta^2 q), a barrier top of rate beta ``inverted``
(q' = p, p' = +beta^2 q), a saddle ``saddle`` (H = beta p q). ``margin`` F in (0, 1]
allows every frequency to be up to 1/F times larger. Steps h are in ``time_unit`` (else in
the time unit of 1/beta). The keywords for frequencies in other forms, each with its unit,
are listed in :mod:`stepsafe.arguments`.

>>> import stepsafe
>>> verlet = stepsafe.method("verlet")
>>> verlet.order, verlet.kind, verlet.evaluations
(2, 'splitting', 1)
>>> advice = stepsafe.advise(verlet, beta=[1.0, 4.0])
>>> round(advice.h_max, 12)   # Verlet keeps a centre a centre for beta*h < 2
0.5
>>> stepsafe.check(verlet, 0.6, beta=[4.0]).safe
False
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from stepsafe.arguments import public
from stepsafe.exceptions import StepsafeError

#: Models accepted by :func:`region` besides ``"all"`` (which means the main three).
REGION_MODELS = ("oscillator", "saddle", "inverted", "saddle-p")
ArrayLike = Sequence[float] | np.ndarray | float


@dataclass(frozen=True)
class PartitionedTableau:
    """One step of a partitioned Runge–Kutta method for q' = dH/dp, p' = -dH/dq:
    stages Q_i = q + h sum_j A_q[i, j] dH/dp(Q_j, P_j), P_i = p - h sum_j A_p[i, j]
    dH/dq(Q_j, P_j), then q + h b_q . dH/dp, p - h b_p . dH/dq (read-only arrays)."""

    A_q: np.ndarray = field(repr=False)
    b_q: np.ndarray = field(repr=False)
    A_p: np.ndarray = field(repr=False)
    b_p: np.ndarray = field(repr=False)

    @property
    def stages(self) -> int:
        return int(self.b_q.size)


@dataclass(frozen=True)
class Integrator:
    """A method ready to analyse: its identity, and its coefficients as ``tableau``.

    ``tableau`` is the frozen coefficient object (:mod:`stepsafe.methods.tableaux`);
    ``reference`` is how to rebuild it at high precision (name or path, stages, base).
    """

    name: str
    kind: str
    title: str
    order: int | None
    stages: int
    evaluations: int | None
    source: str
    explicit: bool
    tableau: Any = field(repr=False, compare=False)
    entry: Any = field(repr=False, compare=False)
    reference: tuple[str, int | None, str | None] = field(repr=False, default=("", None, None))
    #: force-gradient terms (Hessian-vector products) per step, besides ``evaluations``
    gradient_evaluations: int = 0

    def cost_per_step(self, gradient_cost: float = 1.0) -> float | int | None:
        """Work per step in force evaluations: ``evaluations + gradient_cost *
        gradient_evaluations`` (see :data:`stepsafe.methods.tableaux.GRADIENT_COST`); the
        plain ``evaluations`` for methods without force-gradient terms."""
        if self.evaluations is None or not self.gradient_evaluations:
            return self.evaluations
        from stepsafe.methods.tableaux import validate_gradient_cost

        return self.evaluations + validate_gradient_cost(gradient_cost) * \
            self.gradient_evaluations

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe show METHOD --json`` prints."""
        from stepsafe.core.records import coefficients, method_data

        return {**method_data(self.tableau, self.entry),
                "coefficients": coefficients(self.tableau)}

    @property
    def operations(self) -> tuple[tuple[str, float], ...] | None:
        """One step of a splitting method (or a composition of one) as its sequence of
        ``("drift", a)`` (q += a h dT/dp) and ``("kick", b)`` (p -= b h dV/dq), zero
        coefficients dropped and neighbours merged; None for Runge–Kutta methods. For a
        processed method ``P^-1 K P`` the kernel K's step (see :attr:`processor`).

        >>> method("verlet").operations
        (('kick', 0.5), ('drift', 1.0), ('kick', 0.5))
        """
        from stepsafe.methods.tableaux import Composition, Processed, Splitting

        m = self.tableau
        if isinstance(m, Processed):
            m = m.kernel_splitting
        if isinstance(m, Composition) and isinstance(m.flattened().base, Splitting):
            m = m.as_splitting()
        return tuple(m.operations) if isinstance(m, Splitting) else None

    @property
    def processor(self) -> tuple[tuple[str, float], ...] | None:
        """A processed method's processor P as drift/kick operations (run once before the
        first step; ``P^-1``, the same reversed with negated coefficients, at each output);
        None for any other method.

        >>> method("bcr764").processor[-1]
        ('kick', -0.5)
        """
        from stepsafe.methods.tableaux import Processed

        m = self.tableau
        return tuple(m.processor_operations) if isinstance(m, Processed) else None

    @property
    def partitioned_tableau(self) -> PartitionedTableau | None:
        """The coefficients of a Runge–Kutta or partitioned Runge–Kutta method (an RK method
        has both tableaux equal); None for splittings and compositions."""
        from stepsafe.methods.tableaux import PartitionedRK, RungeKutta

        if not isinstance(self.tableau, (RungeKutta, PartitionedRK)):
            return None
        prk = self.tableau.as_prk()
        arrays = [np.array(a, dtype=float) for a in (prk.A_q, prk.b_q, prk.A_p, prk.b_p)]
        for a in arrays:
            a.flags.writeable = False
        return PartitionedTableau(*arrays)

    @contextmanager
    def naming_its_file(self) -> Iterator[None]:
        """An analysis error about a method read from a user's file names that file."""
        from stepsafe.methods.library import builtin_dir

        try:
            yield
        except StepsafeError as exc:
            path = self.entry.path
            if exc.where or not path or Path(path).parent == builtin_dir():
                raise
            raise StepsafeError(exc.message, path) from None


def _text(value: Any, name: str, optional: bool = False) -> Any:
    """``value`` if it is a text (or None when ``optional``), else a StepsafeError."""
    if value is None and optional:
        return None
    if isinstance(value, Path):
        value = str(value)
    if not isinstance(value, str) or "\x00" in value:
        raise StepsafeError(f"{name} must be a text, got {type(value).__name__}"
                            if not isinstance(value, str) else f"{name} contains a NUL byte")
    return value


def _flag(value: Any, name: str) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise StepsafeError(f"{name} must be True or False, got {type(value).__name__}")
    return bool(value)


def _stage_count(value: Any) -> int | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise StepsafeError(f"stages must be an integer, got {type(value).__name__}")
    return int(value)


@public()
def method(name: str, *, stages: int | None = None, base: str | None = None) -> Integrator:
    """A built-in method (``stepsafe methods`` lists them), a family member
    (``method("gauss", stages=3)``) or a method file given by path.

    ``base`` swaps the base of a composition (``"midpoint"``, or ``"gauss:2"``).

    >>> method("gauss", stages=2).order
    4
    """
    from stepsafe.methods.library import resolve
    from stepsafe.methods.tableaux import gradient_evaluations

    name, base = _text(name, "method"), _text(base, "base", optional=True)
    stages = _stage_count(stages)
    tableau, entry = resolve(name, stages, base)
    return Integrator(entry.name, tableau.kind, entry.title, tableau.order, tableau.stages,
                      entry.evaluations, entry.source, bool(tableau.explicit), tableau, entry,
                      (name, stages, base), gradient_evaluations(tableau))


@public()
def method_from_file(path: str | Path, *, base: str | None = None) -> Integrator:
    """A method file (YAML, see ``stepsafe schema method``), read by path even when its
    name is also a built-in's."""
    from stepsafe.methods.library import _looks_like_path

    text = str(path)
    return method(text if _looks_like_path(text) else f"./{text}", base=base)


def _integrator(value: Integrator | str) -> Integrator:
    if isinstance(value, Integrator):
        return single_force(value)
    if isinstance(value, str):
        return single_force(method(value))
    raise StepsafeError(f"method must be a name, a path or a stepsafe.Integrator, "
                        f"got {type(value).__name__}")


def single_force(integrator: Integrator) -> Integrator:
    """``integrator`` if one force drives it; an impulse method needs two (a
    :class:`StepsafeError` that points to :func:`stepsafe.impulse`)."""
    if integrator.kind == "impulse":
        raise StepsafeError(f"{integrator.name} is an impulse (multiple time stepping) method: "
                            "it needs a fast and a slow frequency per mode (stepsafe respa, "
                            "region --ratio, a scene whose modes give fast: and slow:, or "
                            "stepsafe.impulse)")
    return integrator


def _frozen(data: dict[str, Any]) -> Mapping[str, Any]:
    from stepsafe.core.records import json_ready

    return MappingProxyType(json_ready(data))


def _verification(integrator: Integrator, regions: Mapping[str, Any],
                  up_to: float | None = None) -> dict[str, Any]:
    """Recompute the regions' points with mpmath; a JSON-ready verdict."""
    from stepsafe.reference.verify import DPS, TOLERANCE, verify_regions

    name, stages, base = integrator.reference
    checks = verify_regions(name, stages, base, dict(regions), up_to=up_to)
    worst = max((c.discrepancy for c in checks), default=0.0)
    failed = [{"model": c.model, "z": c.point.z, "kind": c.point.kind,
               "reference": c.reference,
               "discrepancy": None if c.discrepancy == float("inf") else c.discrepancy}
              for c in checks if not c.ok]
    return {"digits": DPS, "points": len(checks),
            "largest_discrepancy": None if worst == float("inf") else worst,
            "tolerance": TOLERANCE, "ok": not failed, "failed": failed,
            "conservative": sum(c.conservative for c in checks)}


# --------------------------------------------------------------------------- region


@dataclass(frozen=True)
class RegionReport:
    """Every interval of z = beta*h where the method keeps each model's structure.

    ``regions[model]`` is a :class:`stepsafe.core.regions.Region` (intervals, islands,
    resonances, poles); ``not_analysed[model]`` says why a model has no form for this
    method. ``verification`` is the ``--verify`` verdict when asked for.
    """

    integrator: Integrator
    regions: Mapping[str, Any]
    not_analysed: Mapping[str, str] = field(default_factory=dict)
    verification: Mapping[str, Any] | None = None
    #: oscillator: the nonlinear resonances n theta = 2 pi m in the interval from 0
    nonlinear: tuple[Any, ...] = ()
    #: ``structure`` or ``stability`` (see :func:`region`)
    criterion: str = "structure"
    #: under ``stability``: each model's first boundary under ``structure``
    structure_boundaries: Mapping[str, float | None] = field(default_factory=dict)

    def first_boundary(self, model: str = "oscillator") -> float | None:
        """z*, the end of the preserved interval from 0 (None: none below zmax)."""
        return self.regions[model].first_boundary

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe region METHOD --json`` prints."""
        from stepsafe.core.records import method_data, region_data

        head = method_data(self.integrator.tableau, self.integrator.entry)
        models = {m: region_data(self.regions[m]) if m in self.regions
                  else {"not_analysed": self.not_analysed[m]}
                  for m in (*self.regions, *self.not_analysed)}
        out = {key: head[key] for key in ("method", "title", "kind", "stages", "order",
                                          "symplectic")}
        out["models"] = {m: models[m] for m in _ordered(models)}
        out["criterion"] = self.criterion
        for m, z_star in self.structure_boundaries.items():
            out["models"][m]["structure_first_boundary"] = z_star
        if "oscillator" in self.regions and self.regions["oscillator"].symplectic:
            from stepsafe.core.records import nonlinear_data

            out["models"]["oscillator"]["nonlinear_resonances"] = nonlinear_data(self.nonlinear)
        if self.verification is not None:
            out["verify"] = copy.deepcopy(dict(self.verification))
        return out


def _ordered(models: Mapping[str, Any]) -> list[str]:
    rank = {m: i for i, m in enumerate(REGION_MODELS)}
    return sorted(models, key=lambda m: rank.get(m, len(rank)))


@public()
def region(method: Integrator | str, model: str = "all", *, zmax: float = 10.0,
           verify: bool = False, resonance_orders: Sequence[int] = (3, 4, 5, 6),
           criterion: str = "structure") -> RegionReport:
    """The regions of ``method`` for ``model`` (``"all"``: oscillator, saddle and inverted;
    a model the method has no form for is then listed in ``not_analysed``). On the
    oscillator, also the nonlinear resonances ``n theta = 2 pi m`` of the orders n in
    ``resonance_orders`` below the first boundary. ``criterion``: ``structure`` keeps the
    flow's type and orientation, ``stability`` the type only (for the oscillator
    ``|tr M| <= 2``, the stability interval of the HMC literature; islands of reversed
    orientation join the intervals).

    >>> round(region("verlet", "oscillator").first_boundary(), 12)
    2.0
    """
    from stepsafe.core.models import MAIN_MODELS
    from stepsafe.core.regions import find_region, under_criterion, validate_criterion
    from stepsafe.exceptions import positive_finite

    integrator = _integrator(method)
    criterion = validate_criterion(criterion)
    model, verify = _text(model, "model"), _flag(verify, "verify")
    if model != "all" and model not in REGION_MODELS:
        raise StepsafeError(f"unknown model {model!r}; choose one of "
                            f"{', '.join(REGION_MODELS)} or all")
    zmax = positive_finite(zmax, "zmax")
    models = MAIN_MODELS if model == "all" else (model,)
    regions, skipped, first_error = {}, {}, None
    with integrator.naming_its_file():
        for name in models:
            try:
                regions[name] = find_region(integrator.tableau, name, zmax)
            except StepsafeError as exc:
                skipped[name], first_error = exc.message, first_error or exc
        if first_error and (model != "all" or not regions):  # nothing the user asked for
            raise first_error
    nonlinear: tuple[Any, ...] = ()
    if "oscillator" in regions and regions["oscillator"].symplectic:
        from stepsafe.core.resonances import nonlinear_resonances, validate_orders

        orders = validate_orders(resonance_orders)
        nonlinear = nonlinear_resonances(integrator.tableau, regions["oscillator"], orders)
    verdict = _verification(integrator, regions) if verify else None
    structure = {}
    if criterion != "structure":
        structure = {m: r.first_boundary for m, r in regions.items() if r.symplectic}
        regions = {m: under_criterion(r, criterion) for m, r in regions.items()}
    return RegionReport(integrator, MappingProxyType(regions), MappingProxyType(skipped),
                        None if verdict is None else _frozen(verdict), nonlinear, criterion,
                        MappingProxyType(structure))


# --------------------------------------------------------------------------- inputs


@dataclass(frozen=True)
class Problem:
    """What advise and check analyse: a method, the frequencies (``modes``) or an analysed
    system, the margin, zmax, and the step (given, or named by the scene). Built by
    :func:`problem`."""

    integrator: Integrator
    modes: Any  # stepsafe.core.advice.Modes, or None for a system
    system: Any  # stepsafe.systems.loader.SystemReport, or None
    margin: float
    zmax: float
    h: float | None = None  # in time_unit
    scene: str | None = None
    labels: Mapping[str, tuple[str | None, ...]] = field(default_factory=dict)
    time_unit: str | None = None  # the unit of h (None: the time unit of 1/beta)


#: Vibrations given as ordinary frequency, wavenumber, period or standard deviation: numbers
#: in the keyword's unit, or texts with a unit (see :mod:`stepsafe.units`).
UnitValues = Sequence[float | str] | np.ndarray | float | str

#: The keywords of vibrations given in another form than beta, and the form
#: :func:`stepsafe.units.quantity` reads each as.
CONVERTED = (("ordinary_frequency", "frequency"), ("wavenumber", "wavenumber"),
             ("period", "period"), ("sigma", "sigma"))


def _converted(values: Mapping[str, UnitValues | None], time_unit: str | None
               ) -> list[np.ndarray]:
    """beta (rad per time unit) of each vibration given in another form (``CONVERTED``). A
    text must name its unit: a number is given as a number."""
    from stepsafe.units import parse_quantity, quantity

    out = []
    for keyword, form in CONVERTED:
        given = values.get(keyword)
        if given is None:
            continue
        try:
            array = np.asarray(given, dtype=object)
            if array.ndim > 1:
                raise StepsafeError(f"{keyword} must be one-dimensional, got an array of "
                                    f"shape {array.shape}")
            items = [given] if isinstance(given, (str, int, float)) else list(array.ravel())
        except (TypeError, ValueError):
            raise StepsafeError(f"{keyword} must be a number, a text with a unit or a list of "
                                "them") from None
        betas = []
        for item in items:
            item = item.item() if isinstance(item, np.generic) else item
            try:
                beta = quantity(item, form, time_unit)  # (a bad value says what it may be)
                if isinstance(item, str) and parse_quantity(item)[1] is None:
                    raise StepsafeError(f"give numbers as numbers; a text names its unit "
                                        f"(such as '3700 cm-1', '100 THz', '9 fs'), got "
                                        f"{item[:40]!r}")
                betas.append(beta)
            except StepsafeError as exc:
                raise StepsafeError(exc.message if exc.message.startswith(keyword) else
                                    f"{keyword}: {exc.message}") from None
        out.append(np.array(betas, dtype=float))
    return out


def _modes_dict(given: Sequence[tuple[str, str, Any]]) -> dict[str, np.ndarray]:
    """The frequencies of each ``(keyword, model, values)`` grouped by model, in order."""
    parts: dict[str, list[np.ndarray]] = {}
    for keyword, model, values in given:
        if values is None:
            continue
        try:
            arr = np.asarray(values)
            if arr.dtype.kind == "c":
                raise StepsafeError(f"{keyword} must be real (rad per time unit), got complex "
                                    "values")
            if arr.dtype.kind not in "iuf" and not (
                    arr.dtype == object and all(isinstance(v, (int, float, np.integer,
                                                               np.floating))
                                                and not isinstance(v, bool)
                                                for v in arr.ravel())):
                raise TypeError
            if arr.ndim > 1:
                raise StepsafeError(f"{keyword} must be one-dimensional, got an array of "
                                    f"shape {arr.shape}")
            arr = np.atleast_1d(arr.astype(float))
        except (TypeError, ValueError, OverflowError):
            raise StepsafeError(f"{keyword} must be a number or a list or array of real numbers "
                                "(rad per time unit)") from None
        if arr.size:
            parts.setdefault(model, []).append(arr)
    return {model: np.concatenate(v) for model, v in parts.items()}


def _frequencies(beta: Any, saddle_beta: Any, inverted_beta: Any, modes: Any,
                 converted: Sequence[np.ndarray] = ()) -> dict[str, np.ndarray]:
    """Every frequency given by keyword, per model: ``beta`` and the ``converted``
    vibrations, ``saddle_beta``, ``inverted_beta``, then ``modes`` (in that order)."""
    if modes is not None and not isinstance(modes, Mapping):
        raise StepsafeError(f"modes must map model names to frequencies (rad per time unit), "
                            f"got {type(modes).__name__}")
    return _modes_dict([("beta", "oscillator", beta),
                        *(("beta", "oscillator", v) for v in converted),
                        ("saddle_beta", "saddle", saddle_beta),
                        ("inverted_beta", "inverted", inverted_beta),
                        *((f"modes[{model!r}]", model, v) for model, v in (modes or {}).items())])


def _step(h: Any, time_unit: str | None) -> float:
    """A step ``h``: a number in ``time_unit``, or a text with a time unit (converted)."""
    from stepsafe.exceptions import positive_finite
    from stepsafe.units import duration

    return positive_finite(duration(h, "h", time_unit), "h")


@public()
def problem(method: Integrator | str | None = None, beta: ArrayLike | None = None, *,
            saddle_beta: ArrayLike | None = None, inverted_beta: ArrayLike | None = None,
            modes: Mapping[str, ArrayLike] | None = None,
            ordinary_frequency: UnitValues | None = None, wavenumber: UnitValues | None = None,
            period: UnitValues | None = None, sigma: ArrayLike | None = None,
            time_unit: str | None = None, h: float | str | None = None,
            labels: Mapping[str, Sequence[str | None]] | None = None,
            system: Mapping[str, Any] | None = None, scene: str | Path | None = None,
            stages: int | None = None, base: str | None = None, margin: float | None = None,
            zmax: float | None = None,
            progress: Callable[[float], None] | None = None, budget: float | None = None
            ) -> Problem:
    """Merge a scene file with explicit arguments (the arguments win, as options do on the
    command line).

    Frequencies given by keyword are used together, in this order (``labels[model][i]``
    names mode i of ``model`` in it); else the scene's ``modes:``; else a ``system``,
    analysed for the method (an explicit ``system`` replaces the scene's ``modes:`` or
    ``system:``, and is refused together with explicit frequencies).

    Parameters
    ----------
    method : Integrator or str, optional
        The method (name, ``family`` with ``stages``, or path); default: the scene's.
    beta : array_like, optional
        Angular frequencies of vibrations, rad per time unit.
    saddle_beta, inverted_beta : array_like, optional
        Rates of saddles (H = beta p q) and of barrier tops (p' = +beta^2 q), rad per time
        unit.
    modes : mapping, optional
        ``{model: betas}``, rad per time unit (models as in :func:`region`).
    ordinary_frequency : number, text or list, optional
        f = beta / (2 pi) of vibrations: cycles per time unit, or texts with a frequency
        unit (``"100 THz"``, ``"3 ps-1"``).
    wavenumber : number, text or list, optional
        Vibrations in cm^-1 (``3700`` or ``"3700 cm-1"``); needs a time unit.
    period : number, text or list, optional
        T = 2 pi / beta of vibrations: in the time unit, or texts with a time unit
        (``"9 fs"``).
    sigma : array_like, optional
        Standard deviations of a Gaussian target (HMC, unit mass), in the units of q:
        beta = 1 / sigma.
    time_unit : str, optional
        The unit of every step in and out (``"fs"``, ``"ps"``, ...; see
        :data:`stepsafe.units.TIME_UNITS`). Default: the scene's, else the unit that the
        texts of ``h`` and ``period`` name, else the time unit of 1/beta.
    h : float or str, optional
        The step to check, in the time unit or as a text with a time unit (``"0.5 fs"``);
        default: the scene's ``h:``.
    labels : mapping, optional
        Names of the modes given by keyword, per model.
    system : mapping, optional
        ``{"stiffness": K, "mass": M}``, ``{"precision": P}`` or ``{"covariance": C}`` with
        an optional mass, ``{"hessian": H}``, or a scene's ``system:`` (a Hamiltonian).
    scene : str or Path, optional
        A scene file (see ``stepsafe schema scene``), or a :func:`load_scene` result.
    stages, base : optional
        A family's stage count; a composition's base.
    margin : float, optional
        F in (0, 1]: every frequency may be up to 1/F times larger (default: the scene's,
        else 1).
    zmax : float, optional
        How far in z = beta*h to analyse (default: the scene's, else 10).
    progress : callable, optional
        Called with the fraction done of a coupled analysis.
    budget : float, optional
        Seconds after which a coupled analysis stops (steps above the h reached are then
        not analysed).

    Returns
    -------
    Problem
    """
    import time

    from stepsafe.core.advice import Modes, validate_margin
    from stepsafe.core.regions import DEFAULT_ZMAX
    from stepsafe.exceptions import positive_finite
    from stepsafe.systems.scene import Scene, load_scene, time_unit_in_force
    from stepsafe.units import time_unit as known_time_unit

    if zmax is not None:  # checked before any file is read or analysed
        zmax = positive_finite(zmax, "zmax")
    if budget is not None:
        budget = positive_finite(budget, "budget")
    if margin is not None:
        margin = validate_margin(margin)
    explicit = known_time_unit(time_unit)
    time_unit = time_unit_in_force(explicit, scene, h, period)
    if isinstance(scene, Scene):
        loaded = scene
        if explicit is not None and scene.time_unit not in (None, explicit):
            raise StepsafeError(f"the scene's time_unit is {scene.time_unit}, not {explicit}")
        if scene.time_unit is None and time_unit is not None:
            loaded = copy.copy(scene)  # its values have no unit: they are in this one
            loaded.time_unit = time_unit
        scene = scene.where or None
    elif scene is not None:
        loaded = load_scene(_text(scene, "scene"), time_unit)
    else:
        loaded = Scene(time_unit=time_unit)
    margin = validate_margin(margin if margin is not None else
                             (loaded.margin if loaded.margin is not None else 1.0))
    zmax = zmax if zmax is not None else (
        loaded.zmax if loaded.zmax is not None else DEFAULT_ZMAX)
    step = loaded.h if h is None else _step(h, loaded.time_unit)
    integrator = _scene_method(method, loaded, stages, base)
    converted = _converted({"ordinary_frequency": ordinary_frequency, "wavenumber": wavenumber,
                            "period": period, "sigma": sigma}, loaded.time_unit)
    given = _frequencies(beta, saddle_beta, inverted_beta, modes, converted)
    if given and system is not None:
        raise StepsafeError("give either frequencies (or modes) or a system, not both (one "
                            "would be ignored)")
    report = None
    arrays: Mapping[str, Any]
    if given:
        arrays, labels = given, _labels(labels, given)
    elif loaded.modes and system is None:
        arrays, labels = loaded.modes, loaded.labels
    elif system is not None or loaded.system is not None:
        from stepsafe.systems.loader import analyse_system

        deadline = None if budget is None else time.monotonic() + budget
        tree, where, folder = ((system, "system", Path(".")) if system is not None
                               else (loaded.system, loaded.where, loaded.folder))
        report = analyse_system(tree, where, folder, integrator.tableau, zmax, progress,
                                deadline, loaded.time_unit)
        arrays = report.modes.betas if report.modes is not None else {"oscillator": [0.0]}
        labels = {}
    else:
        raise StepsafeError("no frequencies: give --beta/--saddle-beta/--inverted-beta, "
                            "--modes FILE, or modes: or system: in a scene file (in Python: "
                            "beta=, saddle_beta=, inverted_beta=, modes=, system= or scene=)")
    return Problem(integrator, Modes.from_arrays(arrays), report, margin, zmax, step,
                   str(scene) if scene is not None else None, MappingProxyType(dict(labels)),
                   loaded.time_unit)


def _labels(labels: Mapping[str, Sequence[str | None]] | None,
            arrays: Mapping[str, np.ndarray]) -> dict[str, tuple[str | None, ...]]:
    """``labels`` checked against the frequencies they name."""
    if labels is not None and not isinstance(labels, Mapping):
        raise StepsafeError(f"labels must map model names to lists of texts, got "
                            f"{type(labels).__name__}")
    out = {}
    for model, names in (labels or {}).items():
        if isinstance(names, str) or not isinstance(names, Sequence):
            raise StepsafeError(f"labels[{model!r}] must be a list of texts (or None)")
        if not all(n is None or isinstance(n, str) for n in names):
            raise StepsafeError(f"labels[{model!r}] must hold texts or None")
        if len(names) > len(arrays.get(model, ())):
            raise StepsafeError(f"labels[{model!r}] names {len(names)} modes, there are "
                                f"{len(arrays.get(model, ()))}")
        out[model] = tuple(names)
    return out


def _problem_of(method: Integrator | str | None, beta: ArrayLike | None,
                inputs: dict[str, Any], times: Sequence[Any] = ()) -> Problem:
    """A ``problem=`` given (it already holds the method, frequencies and options: any of
    them given beside it would be ignored, so that is refused), else :func:`problem` of
    the inputs (their names are checked by :func:`stepsafe.arguments.public`). ``times``
    are steps or durations of the caller (texts with a unit name the time unit when
    nothing else does)."""
    given = inputs.pop("problem", None)
    if given is None:
        from stepsafe.systems.scene import time_unit_in_force
        from stepsafe.units import implied_time_unit

        if inputs.get("time_unit") is None and implied_time_unit(*times) is not None:
            inputs["time_unit"] = time_unit_in_force(None, inputs.get("scene"), *times,
                                                     inputs.get("h"), inputs.get("period"))
        return problem(method, beta, **inputs)
    if not isinstance(given, Problem):
        raise StepsafeError(f"problem must be a stepsafe.Problem (from stepsafe.problem), got "
                            f"{type(given).__name__}")
    extra = ([name for name, value in (("method", method), ("beta", beta))
              if value is not None] + sorted(k for k, v in inputs.items() if v is not None))
    if extra:
        raise StepsafeError(f"problem= already holds the method, frequencies and options: "
                            f"give {', '.join(extra)} to stepsafe.problem instead (beside "
                            "problem= it would be ignored)")
    return given


def _scene_method(method: Integrator | str | None, scene: Any, stages: int | None,
                  base: str | None) -> Integrator:
    if isinstance(method, Integrator):
        return single_force(method)
    load = globals()["method"]
    if method is not None:
        return single_force(load(method, stages=stages, base=base))
    ref = scene.method
    if ref is None:
        raise StepsafeError("no method: give --method METHOD or a scene file with method:")
    try:
        return single_force(load(ref.name, stages=stages if stages is not None else ref.stages,
                                 base=base if base is not None else ref.base))
    except StepsafeError as exc:
        if exc.where or not scene.where:
            raise
        message = exc.message.replace("with -s N", "with method: {name: ..., stages: N} "
                                                   "(or -s N)")
        raise StepsafeError(message, f"{scene.where}::$.method") from None


# --------------------------------------------------------------------------- advise


@dataclass(frozen=True)
class AdviceReport:
    """Safe steps: ``h_max`` ends the safe interval from 0 (``h_max_limited_by``:
    ``boundary``, ``resonance n:m`` when the nonlinear resonance n theta = 2 pi m of the
    ``resonance_order`` asked for ends it, ``horizon`` when no boundary was found below
    how far the analysis looked, ``none`` when no step is safe); ``safe_h`` lists every
    safe interval of h (islands included, ``None`` for no upper end). ``advice`` is the
    core result (with the regions used) for decoupled modes. ``undecided_h``: intervals of
    h that float64 could not decide in the coupled analysis of a nearly semidefinite
    system too large for the high-precision criterion (neither certified nor certainly
    unsafe)."""

    method: str
    h_max: float | None
    h_max_limited_by: str
    safe_h: tuple[tuple[float, float | None], ...]
    horizon: float | None
    record: Mapping[str, Any] = field(repr=False)
    advice: Any = field(repr=False, default=None)
    verification: Mapping[str, Any] | None = None
    undecided_h: tuple[tuple[float, float], ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe advise ... --json`` prints."""
        out = copy.deepcopy(dict(self.record))
        if self.verification is not None:
            out["verify"] = copy.deepcopy(dict(self.verification))
        return out


@public(lambda: problem, drop=("h",))
def advise(method: Integrator | str | None = None, beta: ArrayLike | None = None, *,
           tol_phase: float | None = None, tol_energy: float | None = None,
           resonance_order: int | None = None, solver: str = "fixed-point",
           criterion: str = "structure", verify: bool = False, gradient_cost: float = 1.0,
           **inputs: Any) -> AdviceReport:
    """Safe step sizes for a method and angular frequencies ``beta`` (rad per time unit;
    or a scene, or a system): see :func:`problem` for the other inputs and their units
    (``saddle_beta``, ``inverted_beta``, ``modes``, ``ordinary_frequency``,
    ``wavenumber``, ``period``, ``sigma``, ``time_unit``, ``system``, ``scene``,
    ``labels``, ``stages``, ``base``, ``margin``, ``zmax``, ``budget``, ``progress``).
    ``tol_phase``/``tol_energy`` also bound the phase (growth-rate) and energy errors
    and add the usable step and its cost (implicit methods: the force evaluations of
    fixed-point iteration, ``solver="nominal"`` for one per stage). ``resonance_order`` N
    also keeps every
    vibration below its first nonlinear resonance n theta = 2 pi m with n <= N; the
    resonances of orders 3 to 6 (and up to N) of the fastest vibration are listed in
    ``record["nonlinear_resonances"]`` either way. ``criterion``: ``structure`` (type and
    orientation) or ``stability`` (type only: ``|tr M| <= 2`` for vibrations); where the
    other criterion gives another ``h_max``, ``record["other_criterion"]`` holds it.
    ``gradient_cost``: force evaluations one force-gradient term costs (force-gradient
    methods; see :data:`stepsafe.methods.tableaux.GRADIENT_COST`).

    >>> report = advise("yoshida4", [3.2], inverted_beta=[1.1])
    >>> report.h_max_limited_by, f"{report.h_max:.6f}"
    ('boundary', '0.491688')
    """
    from stepsafe.core.advice import advise as core_advise
    from stepsafe.core.records import advice_data, tradeoff_data
    from stepsafe.core.regions import validate_criterion

    criterion = validate_criterion(criterion)
    p = _problem_of(method, beta, inputs)
    integrator, result = p.integrator, None
    with integrator.naming_its_file():
        if p.system is not None:
            from stepsafe.systems.advice import system_advice

            if tol_phase is not None or tol_energy is not None:
                raise StepsafeError("--tol-phase/--tol-energy apply to frequencies, not yet "
                                    "to system: scenes")
            data = system_advice(integrator.tableau, p.system, p.margin, p.zmax,
                                 integrator.name, criterion, _order(resonance_order))
            data["fixed_point_limit"] = _system_solver_limit(integrator, p)
        elif tol_phase is None and tol_energy is None:
            result = core_advise(integrator.tableau, p.modes, p.margin, p.zmax, integrator.name,
                                 resonance_order=_order(resonance_order), criterion=criterion)
            data = advice_data(result)
        else:
            from stepsafe.core.tradeoff import Tolerance, tradeoff

            tols = tuple(Tolerance(k, _tolerance(k, v)) for k, v in
                         (("phase", tol_phase), ("energy", tol_energy)) if v is not None)
            res = tradeoff(integrator.tableau, p.modes, tols, p.margin, integrator.name,
                           _step_cost(integrator, gradient_cost), p.zmax,
                           _order(resonance_order),
                           _solver(solver), criterion)
            result = res.advice
            data = tradeoff_data(res)
        if result is not None:
            other = _other_criterion(integrator, p, result, resonance_order)
            if other is not None:
                data["other_criterion"] = other
            data["nonlinear_resonances"] = _fastest_resonances(
                integrator, result, p, resonance_order)
            from stepsafe.core.solver import step_limit

            data["fixed_point_limit"] = step_limit(integrator.tableau, p.modes.betas)
    if result is not None and p.labels:
        from stepsafe.core.records import label_limits

        label_limits(data, p.modes.betas, p.labels)
    data["time_unit"] = p.time_unit
    verdict = (_verification(integrator, result.regions)
               if _flag(verify, "verify") and result else None)
    safe = tuple((float(lo), hi) for lo, hi in data["safe_h"])
    return AdviceReport(data["method"], data["h_max"], data["h_max_limited_by"], safe,
                        data["horizon"], _frozen(data), result,
                        None if verdict is None else _frozen(verdict),
                        tuple((float(lo), float(hi)) for lo, hi in data.get("undecided_h", ())))


def _other_criterion(integrator: Integrator, p: Problem, result: Any,
                     resonance_order: int | None, h: float | None = None
                     ) -> dict[str, Any] | None:
    """The safe steps under the criterion not asked for, when they differ (with ``h``:
    whether that step is safe under it)."""
    from stepsafe.core.advice import advise as core_advise
    from stepsafe.core.records import advice_data
    from stepsafe.core.regions import CRITERIA

    other = next(c for c in CRITERIA if c != result.criterion)
    zmax = max(r.zmax for r in result.regions.values())
    alt = advice_data(core_advise(integrator.tableau, p.modes, p.margin, zmax,
                                  integrator.name, resonance_order=_order(resonance_order),
                                  criterion=other))
    if alt["safe_h"] == [[float(lo), hi] for lo, hi in result.safe_h]:
        return None
    out = {key: alt[key] for key in ("criterion", "h_max", "h_max_limited_by", "limiting",
                                     "safe_h")}
    if h is not None:
        out["safe"] = any(lo < h and (hi is None or h < hi) for lo, hi in alt["safe_h"])
    return out


def _order(order: int | None) -> int | None:
    from stepsafe.core.resonances import validate_orders

    return None if order is None else validate_orders((order,))[0]


def _fastest_resonances(integrator: Integrator, result: Any, p: Problem,
                        order: int | None) -> list[dict[str, Any]]:
    """The nonlinear resonances of the fastest vibration below its first boundary (or
    below the resonance that caps it), with their steps h."""
    from stepsafe.core.records import nonlinear_data
    from stepsafe.core.resonances import DEFAULT_ORDERS, nonlinear_resonances

    region = result.regions.get("oscillator")
    betas = p.modes.betas.get("oscillator")
    if region is None or betas is None or not region.symplectic or not betas.max() > 0:
        return []
    orders = tuple(range(3, max(order or 0, max(DEFAULT_ORDERS)) + 1))
    found = nonlinear_resonances(integrator.tableau, region, orders)
    return nonlinear_data(found, float(betas.max()), p.margin)


def _system_solver_limit(integrator: Integrator, p: Problem) -> float | None:
    """The step beyond which fixed-point iteration of an implicit method's stages diverges
    for the problem's frequencies or system (None: explicit, or no limit)."""
    from stepsafe.core.solver import system_step_limit

    if integrator.explicit:
        return None
    if p.system is None:
        return system_step_limit(integrator.tableau, p.modes.betas, [])
    betas = p.system.modes.betas if p.system.modes is not None else None
    return system_step_limit(integrator.tableau, betas, [S for _, S in p.system.coupled])


def _check_solver(value: Any) -> str:
    if not isinstance(value, str) or value not in ("fixed-point", "newton"):
        raise StepsafeError(f"solver must be fixed-point or newton, got {str(value)[:20]!r}")
    return value


def _solver(value: Any) -> str:
    from stepsafe.core.tradeoff import SOLVERS

    if not isinstance(value, str) or value not in SOLVERS:
        raise StepsafeError(f"solver must be one of {', '.join(SOLVERS)}, got "
                            f"{str(value)[:20]!r}")
    return value


def _tolerance(kind: str, value: float) -> float:
    try:
        if isinstance(value, (bool, str)):
            raise TypeError
        value = float(value)
    except (TypeError, ValueError, OverflowError):
        raise StepsafeError(f"--tol-{kind} must be a positive finite number, got "
                            f"{str(value)[:40]}") from None
    if not (0 < value < float("inf")):
        raise StepsafeError(f"--tol-{kind} must be a positive finite number, got {value}")
    return value


# --------------------------------------------------------------------------- check


@dataclass(frozen=True)
class CheckReport:
    """Whether step ``h`` keeps every mode's structure (``safe``), the failing modes with
    their reasons, and the safe steps for all modes (``h_max``, ``safe_h``)."""

    method: str
    h: float
    safe: bool
    h_max: float | None
    failures: tuple[Mapping[str, Any], ...]
    scene: str | None
    record: Mapping[str, Any] = field(repr=False)
    result: Any = field(repr=False, default=None)
    verification: Mapping[str, Any] | None = None

    def entry(self) -> dict[str, Any]:
        """This check's entry of ``checks`` in ``stepsafe check ... --json``."""
        out = copy.deepcopy(dict(self.record))
        if self.verification is not None:
            out["verify"] = copy.deepcopy(dict(self.verification))
        return out

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe check ... --json`` prints for this input:
        ``{"safe": safe, "checks": [entry]}``."""
        return {"safe": self.safe, "checks": [self.entry()]}


@public(lambda: problem)
def check(method: Integrator | str | None = None, h: float | str | None = None,
          beta: ArrayLike | None = None, *, resonance_order: int | None = None,
          criterion: str = "structure", verify: bool = False, solver: str = "fixed-point",
          require_complete_search: bool = False, **inputs: Any) -> CheckReport:
    """Is step ``h`` safe for every frequency? ``h`` is a number in the time unit, or a
    text with a time unit (``"0.5 fs"``, converted); ``beta`` are angular frequencies (rad
    per time unit); see :func:`problem` for the other inputs and their units. A scene
    may give the step (``h:``). A step exactly on a resonance or a pole is unsafe. With
    ``resonance_order`` N, a vibration at or beyond its first nonlinear resonance of order
    at most N is unsafe too. ``criterion`` as for :func:`advise` (``record["other_criterion"]``
    says whether ``h`` is safe under the other one, when its ``h_max`` differs). With
    ``solver="fixed-point"`` (the default) an implicit method's step must also lie below
    the convergence limit of fixed-point iteration of its stages for every vibration and
    barrier (``record["solver_failure"]`` says why not); ``"newton"`` has no such limit.
    With ``require_complete_search`` a system given by a Hamiltonian fails when its
    equilibrium search cannot vouch that it found every equilibrium
    (``record["system"]["search"]`` says what was searched, ``record["search_failure"]``
    why it falls short; see :mod:`stepsafe.systems.walks`); other inputs are unaffected.

    >>> check("verlet", 0.49, [4.0]).safe
    True
    """
    from stepsafe.core.advice import check_step
    from stepsafe.core.records import check_data
    from stepsafe.core.regions import validate_criterion

    criterion = validate_criterion(criterion)
    require_complete_search = _flag(require_complete_search, "require_complete_search")
    if inputs.get("problem") is None:
        p = _problem_of(method, beta, {**inputs, "h": h})
        step = p.h
    else:
        p = _problem_of(method, beta, inputs)
        step = p.h if h is None else _step(h, p.time_unit)
    if step is None:
        raise StepsafeError(f"{p.scene or 'check'}: no step: give --step H or h: in the "
                            "scene file (h= in Python)")
    integrator, result = p.integrator, None
    with integrator.naming_its_file():
        if p.system is not None:
            from stepsafe.systems.advice import system_check

            data = system_check(integrator.tableau, p.system, step, p.margin, p.zmax,
                                integrator.name, criterion, _order(resonance_order),
                                require_complete_search)
        else:
            result = check_step(integrator.tableau, p.modes, step, p.margin, p.zmax,
                                integrator.name, _order(resonance_order), criterion)
            data = check_data(result, p.labels)
            other = _other_criterion(integrator, p, result.advice, resonance_order,
                                     float(step))
            if other is not None:
                data["other_criterion"] = other
        if _check_solver(solver) == "fixed-point":
            limit = _system_solver_limit(integrator, p)
            if limit is not None and float(step) >= p.margin * limit:
                data["safe"] = False
                data["solver_failure"] = (
                    f"fixed-point iteration of the stages diverges at this step (it "
                    f"converges for h < {p.margin * limit:.12g}); solve them by Newton's "
                    "method (--solver newton) or take a smaller step")
    data["scene"] = p.scene
    data["time_unit"] = p.time_unit
    verdict = None
    if _flag(verify, "verify") and result is not None:
        top = max(float(b.max()) for b in p.modes.betas.values()) * float(step) / p.margin
        verdict = _verification(integrator, result.advice.regions, up_to=1.05 * top)
    return CheckReport(data["method"], float(step), bool(data["safe"]), data["h_max"],
                       tuple(MappingProxyType(f) for f in copy.deepcopy(data["failures"])),
                       p.scene, _frozen(data), result,
                       None if verdict is None else _frozen(verdict))


@dataclass(frozen=True)
class CheckError:
    """A scene file that could not be checked (bad input: exit code 2): its file, the
    message and where (the file and key) the error lies."""

    scene: str | None
    message: str
    where: str | None = None

    def entry(self) -> dict[str, Any]:
        """Its entry of ``checks`` in ``stepsafe check ... --json``: ``safe`` is null."""
        return {"scene": self.scene, "safe": None, "error": self.message, "where": self.where}


@dataclass(frozen=True)
class SceneChecks:
    """The checks of several scene files, in their order: each a :class:`CheckReport`, an
    impulse method's :class:`~stepsafe.respa_advice.ImpulseModesReport`, or a
    :class:`CheckError` for a file that could not be checked."""

    checks: tuple[Any, ...]

    @property
    def safe(self) -> bool:
        """Every step checked is safe (a file that could not be checked is not)."""
        return all(not isinstance(c, CheckError) and bool(c.safe) for c in self.checks)

    @property
    def exit_code(self) -> int:
        """The command's exit code (the worst of the files'): 2 when a file could not be
        checked, else 1 when a step is unsafe, else 0 (a failed ``verify`` is 3, decided
        by the command)."""
        if any(isinstance(c, CheckError) for c in self.checks):
            return 2
        return 0 if self.safe else 1

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe check A.yaml B.yaml ... --json`` prints:
        ``{"safe": safe, "checks": [one entry per file]}``."""
        return {"safe": self.safe,
                "checks": [c.to_dict() if not isinstance(c, (CheckReport, CheckError))
                           else c.entry() for c in self.checks]}


#: The inputs that describe a method's single-force frequencies: an impulse method's modes
#: come from its scene's fast: and slow: frequencies instead.
_SINGLE_FORCE = ("beta", "saddle_beta", "inverted_beta", "modes", "ordinary_frequency",
                 "wavenumber", "period", "sigma", "labels", "system", "margin", "zmax",
                 "budget", "stages", "base")


@public(lambda: problem, drop=("scene", "h"))
def check_scenes(scenes: Sequence[str | Path], *, h: float | str | None = None,
                 resonance_order: int | None = None, criterion: str = "structure",
                 verify: bool = False, solver: str = "fixed-point",
                 require_complete_search: bool = False, substeps: int | None = None,
                 **inputs: Any) -> SceneChecks:
    """:func:`check` of each scene file in ``scenes``, the other inputs the same for all
    (as ``stepsafe check A.yaml B.yaml`` with options): a file that cannot be checked
    (bad input) becomes a :class:`CheckError` in its place and the others are checked
    still. A scene whose method is an impulse method is checked by
    :func:`stepsafe.impulse_advice` (``substeps`` overrides its count).

    Parameters
    ----------
    scenes : list of str or Path
        The scene files, checked in this order.
    h : float or str, optional
        The step for every scene, in its time unit or as a text with a time unit
        (``"0.5 fs"``); default: each scene's ``h:``.
    resonance_order, criterion, verify, solver, require_complete_search
        As for :func:`check`.
    substeps : int, optional
        Inner steps per outer drift of an impulse method's scenes.
    **inputs
        The keywords of :func:`problem` (frequencies with their units, ``time_unit``,
        ``margin``, ...) but ``scene``, the same for every scene.

    Returns
    -------
    SceneChecks
        ``checks`` in the order of ``scenes``; ``safe``, ``exit_code`` and ``to_dict()``
        (what ``stepsafe check A.yaml B.yaml ... --json`` prints).

    >>> checks = check_scenes(["examples/scene.yaml", "examples/paper-section3.yaml"])
    >>> checks.safe, checks.exit_code
    (False, 1)
    """
    from stepsafe.units import time_unit as known_time_unit

    if isinstance(scenes, (str, Path)) or not isinstance(scenes, Sequence) or not scenes:
        raise StepsafeError("scenes must be a non-empty list of scene files")
    known_time_unit(inputs.get("time_unit"))  # (before any scene is read with it)
    out: list[Any] = []
    for scene in scenes:
        try:
            impulse = _impulse_of(scene, inputs)
            if impulse is None:
                if substeps is not None:
                    raise StepsafeError("substeps applies to impulse (multiple time stepping) "
                                        "methods only")
                out.append(check(h=h, scene=scene, resonance_order=resonance_order,
                                 criterion=criterion, verify=verify, solver=solver,
                                 require_complete_search=require_complete_search, **inputs))
                continue
            out.append(_impulse_check(impulse, scene, h, substeps, criterion,
                                      resonance_order, verify, inputs))
        except StepsafeError as exc:
            out.append(CheckError(_text(scene, "scene") if isinstance(scene, (str, Path))
                                  else None, exc.message, exc.where))
    return SceneChecks(tuple(out))


def _impulse_of(scene: Any, inputs: Mapping[str, Any]) -> Integrator | None:
    """The impulse method a scene is checked with (``method`` given, else the scene's), or
    None for any other method."""
    from stepsafe.systems.scene import load_scene

    name = inputs.get("method")
    if isinstance(name, Integrator):
        return name if name.kind == "impulse" else None
    if inputs.get("stages") is not None or inputs.get("base") is not None:
        return None
    if name is None:
        ref = load_scene(_text(scene, "scene"), inputs.get("time_unit")).method
        name = None if ref is None or ref.stages or ref.base else ref.name
    if not isinstance(name, str):
        return None
    try:
        integrator = method(name)
    except StepsafeError:
        return None  # the check of any other method reports it in context
    return integrator if integrator.kind == "impulse" else None


def _impulse_check(integrator: Integrator, scene: Any, h: Any, substeps: int | None,
                   criterion: str, resonance_order: int | None, verify: bool,
                   inputs: Mapping[str, Any]) -> Any:
    from stepsafe.respa_advice import impulse_advice

    given = [key for key in _SINGLE_FORCE if inputs.get(key) is not None]
    if given or _flag(verify, "verify"):
        raise StepsafeError(f"{(given or ['verify'])[0]} does not apply to the impulse method "
                            f"{integrator.name}: its modes come as fast: and slow: frequencies "
                            "in a scene file (or use stepsafe.impulse for one pair)")
    report = impulse_advice(integrator, scene=_text(scene, "scene"), substeps=substeps, step=h,
                            time_unit=inputs.get("time_unit"), criterion=criterion,
                            resonance_order=resonance_order, use_scene_step=h is None)
    if report.step is None:
        raise StepsafeError("no step to check: give --step H or h: in the scene", str(scene))
    return report


# --------------------------------------------------------------------------- errors


@dataclass(frozen=True)
class ErrorTable:
    """Accuracy of one step at each z: ``phase`` (theta/z - 1 for a vibration, log(mu)/z - 1
    for a saddle or barrier) and ``energy`` (relative energy error bound, vibrations), NaN
    where the structure is lost; ``overflow`` where M(z) leaves float64. A processed method
    ``P^-1 K P`` also has ``kernel_energy``, the energy error bound of its kernel run alone
    (its phase error is the kernel's: the processor changes the invariant ellipse, not the
    rotation); None for other methods."""

    method: str
    model: str
    z: np.ndarray = field(repr=False)
    phase: np.ndarray = field(repr=False)
    energy: np.ndarray = field(repr=False)
    overflow: np.ndarray = field(repr=False)
    kernel_energy: np.ndarray | None = field(repr=False, default=None)

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe error METHOD --json`` prints."""
        oscillator = self.model == "oscillator"
        rows = [{"z": float(zz), "phase_error": None if over else _finite(p),
                 "energy_error": _finite(en) if oscillator and not over
                 else None, "overflow": bool(over)}
                for zz, p, en, over in zip(self.z, self.phase, self.energy, self.overflow)]
        if self.kernel_energy is not None and oscillator:
            for row, en, over in zip(rows, self.kernel_energy, self.overflow):
                row["kernel_energy_error"] = None if over else _finite(en)
        return {"method": self.method, "model": self.model,
                "phase_error": "theta/z - 1" if self.model == "oscillator"
                else "log(mu)/z - 1", "rows": rows}


#: |M| beyond this: products of its entries leave float64, the errors cannot be evaluated.
OVERFLOW = 1e150


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


@public()
def errors(method: Integrator | str, z: ArrayLike, model: str = "oscillator") -> ErrorTable:
    """Phase and energy errors of one step at each z = beta*h > 0.

    >>> table = errors("verlet", [0.1])
    >>> f"{table.phase[0]:.3e}"
    '4.171e-04'
    """
    from stepsafe.core.accuracy import errors as core_errors
    from stepsafe.core.accuracy import kernel_errors
    from stepsafe.core.transfer import transfer_matrix

    integrator = _integrator(method)
    model = _text(model, "model")
    if model not in REGION_MODELS:
        raise StepsafeError(f"unknown model {model!r}; choose one of {', '.join(REGION_MODELS)}")
    zs = _z_values(z)
    if not zs.size or not np.all(np.isfinite(zs) & (zs > 0)):
        raise StepsafeError("z must be positive finite numbers")
    with np.errstate(all="ignore"):  # far out, M(z) overflows: those rows say so
        e = core_errors(integrator.tableau, zs, model)
        M = np.asarray(transfer_matrix(integrator.tableau, zs, model))
        size = np.abs(M).max(axis=(1, 2))
        kernel = kernel_errors(integrator.tableau, zs, model)
    overflow = ~(np.isfinite(M).all(axis=(1, 2)) & (size <= OVERFLOW))
    phase = np.where(overflow, np.nan, np.asarray(e.phase, dtype=float))
    energy = np.where(overflow, np.nan, np.asarray(e.energy, dtype=float))
    kernel_energy = None if kernel is None else \
        np.where(overflow, np.nan, np.asarray(kernel.energy, dtype=float))
    for arr in (zs, phase, energy, overflow) + (() if kernel_energy is None
                                                 else (kernel_energy,)):
        arr.flags.writeable = False
    return ErrorTable(integrator.name, model, zs, phase, energy, overflow, kernel_energy)


def _z_values(z: Any) -> np.ndarray:
    """z as a flat float array; complex, text or ragged input is a StepsafeError."""
    try:
        arr = np.asarray(z)
        if arr.dtype.kind not in "iuf":
            raise TypeError
        return np.atleast_1d(arr.astype(float)).ravel()
    except (TypeError, ValueError, OverflowError):
        raise StepsafeError("z must be a number or a list or array of real numbers") from None


@public()
def transfer_matrices(method: Integrator | str, z: ArrayLike,
                      model: str = "oscillator") -> np.ndarray:
    """The one-step matrices M(z) of ``method`` on ``model`` at each z = beta*h, shape
    (len(z), 2, 2), read-only: (q, p) after one step = M (q, p) before, in units where
    beta = 1 (p scaled by beta). The structure is kept where |tr M| < 2 (oscillator) or
    tr M > 2 (saddle, barrier). NaN where the implicit stage equations are singular (a pole);
    entries may overflow to inf far out; no warning is raised.

    >>> M = transfer_matrices("verlet", [1.0])[0]
    >>> float(M[0, 0] + M[1, 1])   # 2 - z^2
    1.0
    """
    from stepsafe.core.transfer import transfer_matrix

    integrator = _integrator(method)
    model = _text(model, "model")
    if model not in REGION_MODELS:
        raise StepsafeError(f"unknown model {model!r}; choose one of {', '.join(REGION_MODELS)}")
    zs = _z_values(z)
    if not np.all(np.isfinite(zs) & (zs >= 0)):
        raise StepsafeError("z must be finite numbers >= 0")
    with np.errstate(all="ignore"), integrator.naming_its_file():
        M = np.array(transfer_matrix(integrator.tableau, zs, model), dtype=float)
    M.flags.writeable = False
    return M


def _step_cost(integrator: Integrator, gradient_cost: float) -> float | int | None:
    """:meth:`Integrator.cost_per_step`, a bad ``gradient_cost`` as a StepsafeError."""
    from stepsafe.methods.tableaux import validate_gradient_cost

    try:
        validate_gradient_cost(gradient_cost)
    except StepsafeError as exc:
        raise StepsafeError(exc.message) from None
    return integrator.cost_per_step(gradient_cost)


# --------------------------------------------------------------------------- compare

#: What ``compare`` ranks when no methods are named.
COMPARE_DEFAULT = ("verlet", "yoshida4", "suzuki4", "pefrl", "blanes-moan6", "kahan-li8",
                   "gauss:2", "lobatto3ab:3")


@dataclass(frozen=True)
class CompareRow:
    """One method in a :class:`CompareReport`: ``first_boundary`` z* on the oscillator,
    ``h_max`` the safe limit, ``h_tol`` the largest step meeting the tolerances (0: none
    does), ``h`` the step to use (``bound_by`` says which limit), ``cost`` force
    evaluations per unit of simulated time at ``h``, ``rank`` (cheapest first; None when
    there is no cost). A processed method also has ``processor_evaluations``, the forces
    of its processor P, spent once before the first step, and as many for P^-1 at each
    output (not in ``cost``; JSON: ``{"start": n, "per_output": n}``)."""

    method: str
    implicit: bool
    first_boundary: float | None
    h_max: float | None
    h_tol: float | None
    tolerance_status: tuple[str, ...]
    h: float | None
    bound_by: str
    evaluations: int | None
    solver_iterations: int | None
    cost: float | None
    rank: int | None
    processor_evaluations: int | None = None


@dataclass(frozen=True)
class CompareReport:
    """Methods ranked by cost per unit of simulated time for the same frequencies."""

    rows: tuple[CompareRow, ...]
    modes: Mapping[str, int]
    tolerances: Mapping[str, float]
    margin: float
    time_unit: str | None = None
    solver: str = "fixed-point"
    criterion: str = "structure"

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe compare ... --json`` prints."""
        from dataclasses import asdict

        return {"modes": dict(self.modes), "tolerances": dict(self.tolerances),
                "margin": self.margin, "time_unit": self.time_unit, "solver": self.solver,
                "criterion": self.criterion,
                "cost_unit": "force evaluations per unit of simulated time",
                "methods": [_compare_row_dict(asdict(r)) for r in self.rows]}


def _compare_row_dict(row: dict[str, Any]) -> dict[str, Any]:
    row["tolerance_status"] = list(row["tolerance_status"])
    if row["processor_evaluations"] is None:
        del row["processor_evaluations"]  # only processed methods have one
    else:
        n = row["processor_evaluations"]
        row["processor_evaluations"] = {"start": n, "per_output": n}
    return row


@public()
def compare(methods: Sequence[Integrator | str] | str | None = None,
            beta: ArrayLike | None = None, *, saddle_beta: ArrayLike | None = None,
            inverted_beta: ArrayLike | None = None,
            modes: Mapping[str, ArrayLike] | None = None,
            tol_phase: float | None = None, tol_energy: float | None = None,
            margin: float = 1.0, zmax: float | None = None,
            ordinary_frequency: UnitValues | None = None, wavenumber: UnitValues | None = None,
            period: UnitValues | None = None, sigma: ArrayLike | None = None,
            time_unit: str | None = None, solver: str = "fixed-point",
            criterion: str = "structure", gradient_cost: float = 1.0) -> CompareReport:
    """Rank ``methods`` (names, ``"family:N"`` such as ``"gauss:2"``, Integrators; ``"all"``:
    every built-in method with the families at s = 2 and 3; None: :data:`COMPARE_DEFAULT`)
    by the cost of the usable step h = min(safe, accurate) for the same frequencies
    (``beta`` in rad per time unit, the others with their units as for :func:`problem`;
    h in ``time_unit``; ``"all"`` leaves out the methods
    with no form for a given model: force-gradient methods on saddles). Implicit methods
    cost the force
    evaluations of fixed-point iteration of their stages at that h (``solver="nominal"``:
    one per stage), and h stays below 0.9 of that iteration's convergence limit. The safe
    step follows ``criterion`` (see :func:`advise`). A force-gradient method costs its
    forces plus ``gradient_cost`` forces per force-gradient term.

    >>> best = compare(["verlet", "pefrl"], [1.0], tol_phase=1e-6).rows[0]
    >>> best.method, best.bound_by
    ('pefrl', 'accuracy')
    """
    from stepsafe.core.advice import Modes, validate_margin
    from stepsafe.core.records import compare_row
    from stepsafe.core.regions import validate_criterion
    from stepsafe.core.tradeoff import Tolerance, tradeoff
    from stepsafe.exceptions import positive_finite
    from stepsafe.units import time_unit as known_time_unit

    criterion = validate_criterion(criterion)
    from stepsafe.units import implied_time_unit

    time_unit = known_time_unit(time_unit) or implied_time_unit(period)
    converted = _converted({"ordinary_frequency": ordinary_frequency, "wavenumber": wavenumber,
                            "period": period, "sigma": sigma}, time_unit)
    grid = Modes.from_arrays(_frequencies(beta, saddle_beta, inverted_beta, modes, converted))
    tolerances = tuple(Tolerance(k, _tolerance(k, v)) for k, v in
                       (("phase", tol_phase), ("energy", tol_energy)) if v is not None)
    margin = validate_margin(margin)
    if zmax is not None:
        zmax = positive_finite(zmax, "zmax")
    from stepsafe.core.transfer import has_form

    rows = []
    compared = _compared(methods)
    if isinstance(methods, str) and methods == "all":  # every method that applies to the modes
        compared = [i for i in compared if all(has_form(i.tableau, model)
                                               for model in grid.betas)]
    for integrator in compared:
        with integrator.naming_its_file():
            res = tradeoff(integrator.tableau, grid, tolerances, margin, integrator.name,
                           _step_cost(integrator, gradient_cost), zmax, solver=_solver(solver),
                           criterion=criterion)
        rows.append(compare_row(res, integrator.explicit))
    rows.sort(key=lambda r: (r["cost"] is None, r["cost"] or 0.0))
    ranked = []
    for i, r in enumerate(rows, 1):
        r["rank"] = i if r["cost"] is not None else None
        if "processor_evaluations" in r:
            r["processor_evaluations"] = r["processor_evaluations"]["start"]
        ranked.append(CompareRow(**{**r, "tolerance_status": tuple(r["tolerance_status"])}))
    return CompareReport(tuple(ranked),
                         MappingProxyType({k: int(v.size) for k, v in grid.betas.items()}),
                         MappingProxyType({t.kind: t.value for t in tolerances}), margin,
                         time_unit, solver, criterion)


def named_method(item: str) -> Integrator:
    """A method by name, path or ``family:N`` (``"gauss:2"``)."""
    name, _, stages = _text(item, "method").strip().partition(":")
    if stages and not (stages.isascii() and stages.isdigit() and len(stages) <= 30):
        raise StepsafeError(f"bad stage count in {item!r} (use family:N)")
    return method(name, stages=int(stages) if stages else None)


def _compared(methods: Sequence[Integrator | str] | str | None) -> list[Integrator]:
    from stepsafe.methods.library import FAMILIES, builtin_names

    if isinstance(methods, str) and methods == "all":
        return ([method(n) for n in builtin_names(single_force=True) if n not in FAMILIES]
                + [method(f, stages=s) for f in FAMILIES for s in (2, 3)])
    if isinstance(methods, str) or (methods is not None and not isinstance(
            methods, (list, tuple))):
        raise StepsafeError(f"methods must be a list of names or 'all', got "
                            f"{str(methods)[:40]}")
    out = []
    for item in COMPARE_DEFAULT if methods is None else methods:
        if not isinstance(item, str):
            out.append(_integrator(item))
            continue
        out.append(single_force(named_method(item)))
    if not out:
        raise StepsafeError("no methods to compare")
    return out


@public()
def load_scene(path: str | Path) -> Any:
    """A scene file (see ``stepsafe schema scene``) as a :class:`stepsafe.systems.scene.Scene`;
    pass its path as ``scene=`` to :func:`advise` or :func:`check`."""
    from stepsafe.systems.scene import load_scene as _load

    return _load(_text(path, "path"))

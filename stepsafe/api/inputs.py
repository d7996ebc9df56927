"""The inputs of the public API and their checks: the method (:func:`method`, an
:class:`Integrator`), the problem advise and check analyse (:func:`problem`, a
:class:`Problem`: frequencies with their units, a scene, a system, the margin and the step),
and the validation every public function shares (a bad value is a
:class:`~stepsafe.exceptions.StepsafeError`).

Conventions: z = beta*h; a vibration of angular frequency ``beta`` (rad per time unit) is
the model ``oscillator`` (q' = p, p' = -beta^2 q), a barrier top of rate beta ``inverted``
(q' = p, p' = +beta^2 q), a saddle ``saddle`` (H = beta p q). ``margin`` F in (0, 1]
allows every frequency to be up to 1/F times larger. Steps h are in ``time_unit`` (else in
the time unit of 1/beta). The keywords for frequencies in other forms, each with its unit,
are listed in :mod:`stepsafe.arguments`.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np

from stepsafe.api.keywords import shared_keywords
from stepsafe.arguments import public
from stepsafe.comparison import compared
from stepsafe.core.advice import Modes, validate_margin
from stepsafe.core.records import coefficients, json_ready, method_data, versioned
from stepsafe.core.regions import DEFAULT_ZMAX
from stepsafe.exceptions import StepsafeError, positive_finite
from stepsafe.lazy import lazy_module
from stepsafe.methods.library import FAMILIES, _looks_like_path, builtin_dir, builtin_names, resolve
from stepsafe.methods.protocol import MethodKind
from stepsafe.methods.tableaux import validate_gradient_cost
from stepsafe.systems.scene import Scene, time_unit_in_force
from stepsafe.systems.scene import load_scene as _load
from stepsafe.units import duration, implied_time_unit, parse_quantity, quantity
from stepsafe.units import time_unit as known_time_unit

if TYPE_CHECKING:
    from stepsafe.core import resonances, tradeoff
    from stepsafe.systems import loader
else:
    # a scene's system: (matrices, a Hamiltonian, an MD engine's system) only
    loader = lazy_module("stepsafe.systems.loader")
    # a resonance order; a solver for tolerances
    resonances = lazy_module("stepsafe.core.resonances")
    tradeoff = lazy_module("stepsafe.core.tradeoff")

#: Models accepted by :func:`region` besides ``"all"`` (which means the main three).
REGION_MODELS = ("oscillator", "saddle", "inverted", "saddle-p")
ArrayLike = Sequence[float] | np.ndarray | float


@compared
@dataclass(frozen=True, eq=False)
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


@compared
@dataclass(frozen=True, eq=False)
class Integrator:
    """A method ready to analyse: its identity, and its coefficients as ``tableau``.

    ``tableau`` is the frozen coefficient object (:mod:`stepsafe.methods.tableaux`), typed
    by the method protocol every kind implements
    (:class:`~stepsafe.methods.protocol.MethodKind`); ``reference`` is how to rebuild it at
    high precision (name or path, stages, base).
    """

    name: str
    kind: str
    title: str
    order: int | None
    stages: int
    evaluations: int | None
    source: str
    explicit: bool
    tableau: MethodKind = field(repr=False, compare=False)
    entry: Any = field(repr=False, compare=False)
    reference: tuple[str, int | None, str | None] = field(repr=False, default=("", None, None))
    #: force-gradient terms (Hessian-vector products) per step, besides ``evaluations``
    gradient_evaluations: int = 0

    def cost_per_step(self, gradient_cost: float = 1.0) -> float | int | None:
        """Work per step in force evaluations: ``evaluations + gradient_cost *
        gradient_evaluations`` (see :data:`stepsafe.methods.tableaux.GRADIENT_COST`); the
        plain ``evaluations`` for methods without force-gradient terms.

        Parameters
        ----------
        gradient_cost : float
            The cost of one force-gradient term in force evaluations (> 0).

        Returns
        -------
        float or int or None
            Force evaluations per step (None: the method file states none).
        """
        if self.evaluations is None or not self.gradient_evaluations:
            return self.evaluations
        return self.evaluations + validate_gradient_cost(gradient_cost) * \
            self.gradient_evaluations

    def to_dict(self) -> dict[str, Any]:
        """What ``stepsafe show METHOD --json`` prints.

        Returns
        -------
        dict
            The record, with ``schema_version``.
        """
        return versioned({**method_data(self.tableau, self.entry),
                          "coefficients": coefficients(self.tableau)})

    @property
    def operations(self) -> tuple[tuple[str, float], ...] | None:
        """One step of a splitting method (or a composition of one) as its sequence of
        ``("drift", a)`` (q += a h dT/dp) and ``("kick", b)`` (p -= b h dV/dq), zero
        coefficients dropped and neighbours merged; None for Runge–Kutta methods. For a
        processed method ``P^-1 K P`` the kernel K's step (see :attr:`processor`).

        >>> method("verlet").operations
        (('kick', 0.5), ('drift', 1.0), ('kick', 0.5))
        """
        step = self.tableau.splitting()
        return None if step is None else tuple(step.operations)

    @property
    def processor(self) -> tuple[tuple[str, float], ...] | None:
        """A processed method's processor P as drift/kick operations (run once before the
        first step; ``P^-1``, the same reversed with negated coefficients, at each output);
        None for any other method.

        >>> method("bcr764").processor[-1]
        ('kick', -0.5)
        """
        ops = self.tableau.processor_operations
        return None if ops is None else tuple(ops)

    @property
    def partitioned_tableau(self) -> PartitionedTableau | None:
        """The coefficients of a Runge–Kutta or partitioned Runge–Kutta method (an RK method
        has both tableaux equal); None for splittings and compositions."""
        prk = self.tableau.rk_form()
        if prk is None:
            return None
        arrays = [np.array(a, dtype=float) for a in (prk.A_q, prk.b_q, prk.A_p, prk.b_p)]
        for a in arrays:
            a.flags.writeable = False
        return PartitionedTableau(*arrays)

    @contextmanager
    def naming_its_file(self) -> Iterator[None]:
        """An analysis error about a method read from a user's file names that file."""
        try:
            yield
        except StepsafeError as exc:
            path = self.entry.path
            if exc.where or not path or Path(path).parent == builtin_dir():
                raise
            raise StepsafeError(exc.message, path) from None


def as_text(value: Any, name: str, optional: bool = False) -> Any:
    """``value`` if it is a text (or None when ``optional``), else a StepsafeError."""
    if value is None and optional:
        return None
    if isinstance(value, Path):
        value = str(value)
    if not isinstance(value, str) or "\x00" in value:
        raise StepsafeError(f"{name} must be a text, got {type(value).__name__}"
                            if not isinstance(value, str) else f"{name} contains a NUL byte")
    return value


def as_flag(value: Any, name: str) -> bool:
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

    Parameters
    ----------
    name : str
        A built-in method's name or alias, a family's name (with ``stages``), or the path
        of a method file.
    stages : int, optional
        The member of a family: its number of stages.
    base : str, optional
        The base method of a composition, in place of its own.

    Returns
    -------
    Integrator
        The method, with its tableau and its library entry.

    Examples
    --------
    >>> method("gauss", stages=2).order
    4
    """
    name, base = as_text(name, "method"), as_text(base, "base", optional=True)
    stages = _stage_count(stages)
    tableau, entry = resolve(name, stages, base)
    return Integrator(entry.name, tableau.kind, entry.title, tableau.order, tableau.stages,
                      entry.evaluations, entry.source, bool(tableau.explicit), tableau, entry,
                      (name, stages, base), tableau.gradient_evaluations)


@public()
def method_from_file(path: str | Path, *, base: str | None = None) -> Integrator:
    """A method file (YAML, see ``stepsafe schema method``), read by path even when its
    name is also a built-in's.

    Parameters
    ----------
    path : str or Path
        The method file.
    base : str, optional
        The base method of a composition, in place of its own.

    Returns
    -------
    Integrator
        The method the file defines.
    """

    text = str(path)
    return method(text if _looks_like_path(text) else f"./{text}", base=base)


def as_integrator(value: Integrator | str) -> Integrator:
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


def frozen_record(data: dict[str, Any]) -> Mapping[str, Any]:
    return MappingProxyType(json_ready(data))


# --------------------------------------------------------------------------- inputs


@compared
@dataclass(frozen=True, eq=False)
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


def converted_betas(values: Mapping[str, UnitValues | None], time_unit: str | None
               ) -> list[np.ndarray]:
    """beta (rad per time unit) of each vibration given in another form (``CONVERTED``). A
    text must name its unit: a number is given as a number."""
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


def betas_by_model(beta: Any, saddle_beta: Any, inverted_beta: Any, modes: Any,
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


def step_in_unit(h: Any, time_unit: str | None) -> float:
    """A step ``h``: a number in ``time_unit``, or a text with a time unit (converted)."""
    return positive_finite(duration(h, "h", time_unit), "h")


@public()
@shared_keywords
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
            progress: Callable[[float], None] | None = None, budget: float | None = None,
            openmm_system: Any = None, positions: Any = None, constraints: str | None = None,
            hydrogen_mass: float | str | None = None, minimize: bool | None = None
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
    <keywords: frequencies>
    h : float or str, optional
        The step to check, in the time unit or as a text with a time unit (``"0.5 fs"``);
        default: the scene's ``h:``.
    <keywords: analysis>
    scene : str or Path, optional
        A scene file (see ``stepsafe schema scene``), or a :func:`load_scene` result.
    progress : callable, optional
        Called with the fraction done of a coupled analysis.
    <keywords: openmm>

    Returns
    -------
    Problem
    """
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
        loaded = _load(as_text(scene, "scene"), time_unit)
    else:
        loaded = Scene(time_unit=time_unit)
    margin = validate_margin(margin if margin is not None else
                             (loaded.margin if loaded.margin is not None else 1.0))
    zmax = zmax if zmax is not None else (
        loaded.zmax if loaded.zmax is not None else DEFAULT_ZMAX)
    step = loaded.h if h is None else step_in_unit(h, loaded.time_unit)
    integrator = _scene_method(method, loaded, stages, base)
    converted = converted_betas({"ordinary_frequency": ordinary_frequency, "wavenumber": wavenumber,
                            "period": period, "sigma": sigma}, loaded.time_unit)
    given = betas_by_model(beta, saddle_beta, inverted_beta, modes, converted)
    system, md_where = _md_system(system, loaded, openmm_system, positions, constraints,
                                  hydrogen_mass, minimize)
    if given and system is not None:
        raise StepsafeError("give either frequencies (or modes) or a system, not both (one "
                            "would be ignored)")
    report = None
    arrays: Mapping[str, Any]
    named: Mapping[str, tuple[str | None, ...]]  # the labels of the frequencies analysed
    if given:
        arrays, named = given, _labels(labels, given)
    elif loaded.modes and system is None:
        arrays, named = loaded.modes, loaded.labels
    elif system is not None or loaded.system is not None:
        deadline = None if budget is None else time.monotonic() + budget
        tree, where, folder = ((system, "system", Path(".")) if system is not None
                               else (loaded.system, loaded.where, loaded.folder))
        if md_where is not None:
            tree, where, folder = system, md_where, (loaded.folder if md_where == loaded.where
                                                     else Path("."))
        report = loader.analyse_system(tree, where, folder, integrator.tableau, zmax, progress,
                                deadline, loaded.time_unit)
        arrays = report.modes.betas if report.modes is not None else {"oscillator": [0.0]}
        named = {}
    else:
        raise StepsafeError("no frequencies: give --beta/--saddle-beta/--inverted-beta, "
                            "--modes FILE, or modes: or system: in a scene file (in Python: "
                            "beta=, saddle_beta=, inverted_beta=, modes=, system= or scene=)")
    return Problem(integrator, Modes.from_arrays(arrays), report, margin, zmax, step,
                   str(scene) if scene is not None else None, MappingProxyType(dict(named)),
                   loaded.time_unit)


def _md_system(system: Any, scene: Any, openmm_system: Any, positions: Any,
               constraints: str | None, hydrogen_mass: float | str | None,
               minimize: bool | None) -> tuple[Any, str | None]:
    """The ``system`` to analyse and the name its errors carry, with an OpenMM system given
    by keyword (``openmm_system=``, ``positions=``) and the keywords that modify one, which
    apply to it or to the scene's ``system: {openmm:}`` (they win over the scene's)."""
    md = {key: value for key, value in (("constraints", constraints),
                                          ("hydrogen_mass", hydrogen_mass),
                                          ("minimize", minimize)) if value is not None}
    if minimize is not None and not isinstance(minimize, (bool, np.bool_)):
        raise StepsafeError(f"minimize must be True or False, got {type(minimize).__name__}")
    if openmm_system is not None:
        if system is not None:
            raise StepsafeError("give either system= or openmm_system=, not both")
        if positions is None:
            raise StepsafeError("openmm_system= needs positions= (an (N, 3) array in nm, or "
                                "a .pdb, .cif or State .xml file)")
        return {"openmm": openmm_system, "positions": positions, **md}, "openmm_system"
    if positions is not None:
        raise StepsafeError("positions= goes with openmm_system=")
    if not md:
        return system, None
    target = system if system is not None else scene.system
    if not (isinstance(target, Mapping) and "openmm" in target):
        raise StepsafeError(f"{', '.join(f'{k}=' for k in md)}: only for an OpenMM system "
                            "(openmm_system=, or a scene's system: {openmm:, positions:})")
    if system is not None:
        return {**system, **md}, "system"
    return {**scene.system, **md}, scene.where


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


def problem_of(method: Integrator | str | None, beta: ArrayLike | None,
                inputs: dict[str, Any], times: Sequence[Any] = (), run: Any = None
                ) -> Problem:
    """A ``problem=`` given (it already holds the method, frequencies and options: any of
    them given beside it would be ignored, so that is refused), else :func:`problem` of
    the inputs (their names are checked by :func:`stepsafe.arguments.public`). ``times``
    are steps or durations of the caller (texts with a unit name the time unit when
    nothing else does). ``run`` is the length of a run at temperature (``length=``): its
    unit names the time unit only of frequencies that have a unit of their own (a
    wavenumber, a period); where nothing else names a time unit and the frequencies are
    plain numbers (a system in its own units), there is no unit to convert it into, and
    that is refused rather than the frequencies' unit taken from the length."""
    given = inputs.pop("problem", None)
    if given is None:
        if inputs.get("time_unit") is None and implied_time_unit(*times) is not None:
            inputs["time_unit"] = time_unit_in_force(None, inputs.get("scene"), *times,
                                                     inputs.get("h"), inputs.get("period"))
        if run is not None and inputs.get("time_unit") is None and time_unit_in_force(
                None, inputs.get("scene"), inputs.get("h"), inputs.get("period")) is None:
            return problem_for_run(lambda unit: problem(method, beta,
                                                        **{**inputs, "time_unit": unit}), run)
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


def problem_for_run(build: Callable[[str | None], Problem], run: Any) -> Problem:
    """The problem ``build(time_unit)`` of inputs in which nothing names a time unit, with
    the length of a run at temperature ``run`` (``--length``, ``length=``): when its text
    names a unit, that unit is the time unit only of frequencies that need one (a
    wavenumber, a frequency in THz: ``build(None)`` refuses them); frequencies that are
    plain numbers (a system in its own units) are per a time unit nobody stated, which the
    length cannot be converted into: refused, naming the length."""
    named = implied_time_unit(run)
    if named is None:
        return build(None)
    try:  # without a time unit: do the frequencies need one?
        found = build(None)
    except StepsafeError:
        return build(named)
    if found.time_unit is not None:  # (named by an input read, e.g. a --modes file)
        return found
    raise StepsafeError(f"--length, length=: {str(run)[:40]!r} is in {named}, but the system "
                        "states no time unit to convert it into (its frequencies are plain "
                        "numbers, per its own time unit): give the length as a number in "
                        "that unit, or the run's steps (--steps, steps=), or state the unit "
                        "(--time-unit, time_unit: in the scene)")


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


def valid_order(order: Any) -> int | None:
    """``resonance_order`` (``--resonance-order``): None, or a whole number from 3 to
    :data:`stepsafe.core.resonances.MAX_ORDER` (a numpy integer too; not a bool, a
    fraction or a text), else a StepsafeError naming the key."""
    if order is None:
        return None
    try:
        return resonances.validate_orders((order,))[0]
    except StepsafeError as exc:
        raise StepsafeError("--resonance-order, resonance_order=: " + exc.message.replace(
            "resonance orders must be integers", "must be an integer").replace(
            f"got {str((order,))[:40]}", f"got {str(order)[:40]}")) from None


def valid_stage_solver(value: Any) -> str:
    if not isinstance(value, str) or value not in ("fixed-point", "newton"):
        raise StepsafeError(f"solver must be fixed-point or newton, got {str(value)[:20]!r}")
    return value


def valid_solver(value: Any) -> str:
    if not isinstance(value, str) or value not in tradeoff.SOLVERS:
        raise StepsafeError(f"solver must be one of {', '.join(tradeoff.SOLVERS)}, got "
                            f"{str(value)[:20]!r}")
    return value


def valid_tolerance(kind: str, value: float) -> float:
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


def z_values(z: Any) -> np.ndarray:
    """z as a flat float array; complex, text or ragged input is a StepsafeError."""
    try:
        arr = np.asarray(z)
        if arr.dtype.kind not in "iuf":
            raise TypeError
        return np.atleast_1d(arr.astype(float)).ravel()
    except (TypeError, ValueError, OverflowError):
        raise StepsafeError("z must be a number or a list or array of real numbers") from None


def step_cost(integrator: Integrator, gradient_cost: float) -> float | int | None:
    """:meth:`Integrator.cost_per_step`, a bad ``gradient_cost`` as a StepsafeError."""
    try:
        validate_gradient_cost(gradient_cost)
    except StepsafeError as exc:
        raise StepsafeError(exc.message) from None
    return integrator.cost_per_step(gradient_cost)


# --------------------------------------------------------------------------- compare

#: What ``compare`` ranks when no methods are named.
COMPARE_DEFAULT = ("verlet", "yoshida4", "suzuki4", "pefrl", "blanes-moan6", "kahan-li8",
                   "gauss:2", "lobatto3ab:3")


def named_method(item: str) -> Integrator:
    """A method by name, path or ``family:N`` (``"gauss:2"``)."""
    name, _, stages = as_text(item, "method").strip().partition(":")
    if stages and not (stages.isascii() and stages.isdigit() and len(stages) <= 30):
        raise StepsafeError(f"bad stage count in {item!r} (use family:N)")
    return method(name, stages=int(stages) if stages else None)


def compared_methods(methods: Sequence[Integrator | str] | str | None) -> list[Integrator]:
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
            out.append(as_integrator(item))
            continue
        out.append(single_force(named_method(item)))
    if not out:
        raise StepsafeError("no methods to compare")
    return out


@public()
def load_scene(path: str | Path) -> Any:
    """A scene file (see ``stepsafe schema scene``) as a :class:`stepsafe.systems.scene.Scene`;
    pass its path as ``scene=`` to :func:`advise` or :func:`check`.

    Parameters
    ----------
    path : str or Path
        The scene file (YAML).

    Returns
    -------
    Scene
        The scene's method, frequencies or system, step and options, validated (bad input
        raises :class:`~stepsafe.exceptions.StepsafeError` naming the file and key).
    """

    return _load(as_text(path, "path"))

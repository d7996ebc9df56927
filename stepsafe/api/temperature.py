"""The request for an analysis at temperature: the keywords (the command line's options) and
the scene's keys ``temperature:``, ``kT:``, ``energy_unit:``, ``length:``, ``steps:``,
``max_drift:``, ``max_failure:`` and ``follow_steps:``, checked (a bad value is an error
naming its key).

Every ``advise`` and ``check`` reads them; the analysis itself (:mod:`stepsafe.api.thermal`)
is loaded only when a temperature is given.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from numbers import Integral, Real
from typing import Any

from stepsafe.comparison import compared
from stepsafe.exceptions import StepsafeError
from stepsafe.systems.scene import parse_real
from stepsafe.units import ENERGY_UNITS, duration, kelvin, thermal_energy

#: The energy unit of an MD engine's system (OpenMM's).
ENGINE_ENERGY = "kJ/mol"
#: The default largest acceptable failure probability of a run at temperature (as
#: :data:`stepsafe.systems.thermal.bands.MAX_FAILURE`).
MAX_FAILURE = 1e-3
#: The smallest accepted: ``ln(20) / MIN_FAILURE`` trajectories per probe.
MIN_FAILURE = 1e-5
#: The most steps the thermal trajectories follow by default (``follow_steps``; as
#: :data:`stepsafe.systems.thermal.limit.BAND_STEPS`).
FOLLOW_STEPS = 10_000
#: ... and at most, whatever is asked (the cost grows in proportion to the steps).
MAX_FOLLOW_STEPS = 10 ** 8


@compared
@dataclass(frozen=True, eq=False)
class Request:
    """A validated request for the analysis at temperature.

    Attributes
    ----------
    kT : float
        Thermal energy in the system's energy unit (> 0).
    temperature : float or None
        In kelvin, when given so.
    energy_unit : str or None
        The unit of kT (None: the system's own).
    length : float or None
        The run's simulated time, in the time unit.
    steps : float or None
        Or its number of steps.
    max_drift : float or None
        The largest acceptable energy drift, energy per time unit (the whole system).
    max_failure : float or None
        The largest acceptable failure probability of a run, when given (else
        :data:`MAX_FAILURE`, :attr:`failure`).
    key : str
        Where the temperature came from: the option and keyword (``--kT, kT=``) or the
        scene's key (``$.kT``), for errors of the analysis.
    follow_steps : int or None
        The most steps the thermal trajectories follow, when given (else
        :data:`FOLLOW_STEPS`, :attr:`follow`).
    run_key : str
        Where the run came from: the option and keyword (``--steps, steps=``) or the
        scene's key with its file (``scene.yaml::$.steps``), for a run longer than the
        trajectories follow.
    """

    kT: float
    temperature: float | None
    energy_unit: str | None
    length: float | None
    steps: float | None
    max_drift: float | None = None
    max_failure: float | None = None
    key: str = "--kT, kT="
    follow_steps: int | None = None
    run_key: str = "--steps, steps="

    def run(self) -> dict[str, Any]:
        return {"length": self.length, "steps": self.steps}

    @property
    def failure(self) -> float:
        """The largest acceptable failure probability: given, or :data:`MAX_FAILURE`."""
        return MAX_FAILURE if self.max_failure is None else self.max_failure

    @property
    def follow(self) -> int:
        """The most steps the thermal trajectories follow: given, or :data:`FOLLOW_STEPS`."""
        return FOLLOW_STEPS if self.follow_steps is None else self.follow_steps


def _number(value: Any, scene_text: bool) -> float:
    """A number given as one (an int, a float, a numpy scalar or 0-d array of one) as a
    float (an int beyond float64: inf), or a scene file's text of one (``scene_text``);
    nan for anything else (a bool, a keyword's text, an array of several values)."""
    if isinstance(value, str):
        number = parse_real(value) if scene_text else None
        return math.nan if number is None else float(number)
    if hasattr(value, "dtype") and getattr(value, "ndim", None) == 0 and \
            value.dtype.kind in "iuf":
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, Real):
        return math.nan
    if isinstance(value, Integral):
        whole = int(value)
        return float(whole) if abs(whole) < 2 ** 1023 else math.inf if whole > 0 else -math.inf
    return float(value)


def where_in_scene(scene: Any, key: str) -> str | None:
    """``FILE::$.key`` of the scene read (None: no scene file)."""
    return f"{scene.where}::$.{key}" if scene is not None and scene.where else None


def _fail(message: str, scene: Any, key: str, given: bool) -> StepsafeError:
    """An error naming the key: the keyword (option) when given, else the scene's key."""
    if given:
        return StepsafeError(message if message.startswith(key) else f"{key}: {message}")
    return StepsafeError(message, where_in_scene(scene, key))


def request(*, temperature: Any = None, kT: Any = None, length: Any = None,
            steps: Any = None, max_drift: Any = None, max_failure: Any = None,
            follow_steps: Any = None, scene: Any = None, system: Any = None,
            time_unit: str | None = None) -> Request | None:
    """The request of the keywords (the command line's options), else of the scene's
    ``temperature:``, ``kT:``, ``length:`` and ``steps:`` (each keyword wins over the
    scene's key; a temperature keyword also wins over the scene's ``kT:``, and kT over its
    ``temperature:``), checked: None without a temperature or at T = 0; a bad value is an
    error naming its key.

    Parameters
    ----------
    temperature : float or str, optional
        Kelvin (``300``, ``"300 K"``); needs the system's energy unit (the scene's
        ``energy_unit:``, or ``units: {energy:}`` of a stiffness).
    kT : float, optional
        Thermal energy in the system's energy unit (>= 0).
    length : float or str, optional
        The run's simulated time: in the time unit, or a text with a time unit
        (``"10 ps"``).
    steps : int, optional
        Or the run's number of steps.
    max_drift : float, optional
        The largest acceptable ``|drift| + 2 SE`` of the energy, in the system's energy
        unit per time unit: ``advise`` lowers the step until the measured drift meets it
        (``limited_by`` ``"drift"``), ``check`` fails a step whose drift does not.
    max_failure : float, optional
        The largest acceptable probability that a trajectory of the run fails, in (0, 0.1]
        (default :data:`MAX_FAILURE`): ``check`` needs none of
        ``ln(20) / max_failure`` thermal trajectories at the step to fail, ``advise``
        confirms its answer so on a fresh ensemble.
    follow_steps : int, optional
        The most steps the thermal trajectories follow (default :data:`FOLLOW_STEPS`, at
        most :data:`MAX_FOLLOW_STEPS`): a run of more steps is refused.
    scene : stepsafe.systems.scene.Scene, optional
        The scene file read (its keys and where they are).
    system : mapping, optional
        The ``system:`` mapping (for its energy unit).
    time_unit : str, optional
        The unit of ``length``.

    Returns
    -------
    Request or None
    """
    keys = dict(getattr(scene, "thermal", None) or {})
    given = {"temperature": temperature, "kT": kT, "length": length, "steps": steps,
             "max_drift": max_drift, "max_failure": max_failure, "follow_steps": follow_steps}

    def value(key: str) -> tuple[Any, bool]:
        if given.get(key) is not None:
            return given[key], True
        return keys.get(key), False

    t_value, t_given = value("temperature")
    k_value, k_given = value("kT")
    if t_value is not None and k_value is not None and t_given != k_given:
        # a keyword wins over the scene's key, as length over steps: the other is the scene's
        if t_given:
            k_value = None
        else:
            t_value = None
    if t_value is not None and k_value is not None:
        raise _fail("give temperature (kelvin) or kT (energy), not both", scene,
                    "temperature", t_given)
    unit = keys.get("energy_unit")
    if unit is not None and unit not in ENERGY_UNITS:
        raise StepsafeError(f"must be one of {', '.join(ENERGY_UNITS)}, got {str(unit)[:20]!r}",
                            where_in_scene(scene, "energy_unit"))
    units = system.get("units") if isinstance(system, Mapping) else None
    if unit is None and isinstance(units, Mapping) and units.get("energy") in ENERGY_UNITS:
        unit = units["energy"]
    if isinstance(system, Mapping) and "openmm" in system:  # the engine's energies
        if unit not in (None, ENGINE_ENERGY):
            raise StepsafeError(f"an OpenMM system's energies are in {ENGINE_ENERGY}, not "
                                f"{unit}", where_in_scene(scene, "energy_unit"))
        unit = ENGINE_ENERGY
    if t_value is not None:
        try:
            T = kelvin(t_value)
        except StepsafeError as exc:
            raise _fail(exc.message, scene, "temperature", t_given) from None
        if T == 0:
            return None
        if unit is None:
            raise _fail("the system's energy has no unit: give energy_unit: in the scene "
                        "(kcal/mol, kJ/mol, eV, hartree or J), or kT in its own energy unit",
                        scene, "temperature", t_given)
        kt = thermal_energy(T, unit)
        temperature_k: float | None = T
    elif k_value is not None:
        kt = _number(k_value, not k_given)
        if not math.isfinite(kt):
            raise _fail(f"kT must be a finite number >= 0 (energy), got {str(k_value)[:40]!r}",
                        scene, "kT", k_given)
        if kt < 0:
            raise _fail(f"kT must not be negative, got {kt:g}", scene, "kT", k_given)
        if kt == 0:
            return None
        temperature_k = None
        unit = unit if k_given is False else unit
    else:
        for key in ("length", "steps", "max_drift", "max_failure", "follow_steps"):
            v, g = value(key)
            if v is not None:
                raise _fail("applies to the analysis at temperature: give a temperature "
                            "(or kT) too", scene, key, g)
        return None
    if not math.isfinite(kt) or kt <= 0:
        raise _fail(f"kT = {kt!r} is not a positive finite energy", scene,
                    "temperature" if temperature_k is not None else "kT", True)
    l_value, l_given = value("length")
    s_value, s_given = value("steps")
    if l_given or s_given:  # the run given by keyword replaces the scene's
        l_value, s_value = given["length"], given["steps"]
    if l_value is not None and s_value is not None:
        raise _fail("give the run's length or its steps, not both", scene, "length",
                    l_given)
    run_length = run_steps = None
    if l_value is not None:
        try:
            run_length = duration(l_value, "length", time_unit, plain_text=not l_given)
        except StepsafeError as exc:
            raise _fail(exc.message, scene, "length", l_given) from None
        if not (math.isfinite(run_length) and run_length > 0):
            raise _fail(f"length must be a positive finite time, got {l_value!r}", scene,
                        "length", l_given)
    elif s_value is not None:
        number = _number(s_value, not s_given)
        if not (math.isfinite(number) and number >= 1 and number == int(number)):
            raise _fail(f"steps must be a whole number >= 1, got {str(s_value)[:40]!r}",
                        scene, "steps", s_given)
        run_steps = number
    else:
        raise _fail("give the run's length (simulated time, --length / length:) or its "
                    "number of steps (--steps / steps:): how far into the tails a run "
                    "reaches depends on it", scene, "length", t_given or k_given)
    tolerance, d_given = value("max_drift")
    if tolerance is not None:
        number = _number(tolerance, not d_given)
        if not (math.isfinite(number) and number > 0):
            raise _fail(f"max_drift must be a positive finite energy per time unit, got "
                        f"{str(tolerance)[:40]!r}", scene, "max_drift", d_given)
        tolerance = number
    p_value, p_given = value("max_failure")
    p_max = None
    if p_value is not None:
        p_max = _number(p_value, not p_given)
        if not MIN_FAILURE <= p_max <= 0.1:
            raise _fail(f"max_failure must be a probability in [{MIN_FAILURE:g}, 0.1], got "
                        f"{str(p_value)[:40]!r}", scene, "max_failure", p_given)
    f_value, f_given = value("follow_steps")
    follow = None
    if f_value is not None:
        real = _number(f_value, not f_given)
        number = int(real) if math.isfinite(real) and real == int(real) else 0
        if not 1 <= number <= MAX_FOLLOW_STEPS:
            raise _fail(f"follow_steps must be a whole number of steps in [1, "
                        f"{MAX_FOLLOW_STEPS:.0e}], got {str(f_value)[:40]!r}", scene,
                        "follow_steps", f_given)
        follow = number
    name = "temperature" if temperature_k is not None else "kT"
    key = f"--{name}, {name}=" if (t_given or k_given) else f"$.{name}"
    run_name = "length" if run_length is not None else "steps"
    run_key = (f"--{run_name}, {run_name}=" if (l_given or s_given)
               else (where_in_scene(scene, run_name) or f"$.{run_name}"))
    return Request(kt, temperature_k, unit, run_length, run_steps, tolerance, p_max, key,
                   follow, run_key)

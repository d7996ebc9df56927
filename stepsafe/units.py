"""Physical units: frequencies in the forms users have them, steps in a named time unit.

Every step h is in the *time unit* (``fs``, ``ps``, ...; without one, in the time unit of
1/beta), and every frequency becomes the angular frequency beta in radians per time unit,
so z = beta*h is unit-free and the analysis never sees a unit. The four forms:

==============  ==========================================  ===========================
form            beta (rad per time unit)                    unit of the value
==============  ==========================================  ===========================
``beta``        beta                                        rad per time unit
``frequency``   2 pi f                                      cycles per time unit, or a
                                                            unit: Hz ... PHz, ``ps-1``
``wavenumber``  2 pi c k,  c = 299 792 458 m/s              cm^-1 (needs a time unit)
``period``      2 pi / T                                    time unit, or ``fs``, ``ps``
``sigma``       1 / sigma (a Gaussian target, unit mass)    the units of q
==============  ==========================================  ===========================

The speed of light is exact in the SI (since 1983), and so are the decimal prefixes, so the
conversions carry no constant of limited precision: the scale factor is formed exactly as a
fraction, then rounded and multiplied by the value and pi (the result is within a few ulps
of the exact product). Example:
the O-H stretch of water at 3700 cm^-1 has beta = 2 pi c k = 0.69697... rad/fs.

A time (a step h, a period, a run time) may carry its unit: ``"0.5 fs"``, ``"0.5fs"``,
``"2e-15 s"`` (:func:`duration`). It is converted to the time unit in force (the ratio of
two time units is a power of ten, so the decimal digits and that ratio are combined exactly
and rounded once); where none is given, the unit the values name becomes it
(:func:`implied_time_unit`), and values in two different units with none given are refused.
The API's keyword for the ``frequency`` form is ``ordinary_frequency`` (cycles per time
unit), apart by name from ``beta`` (rad per time unit).
"""

from __future__ import annotations

import math
import re
from fractions import Fraction
from typing import Any

from stepsafe.exceptions import StepsafeError

#: The speed of light in vacuum, m/s (exact by the definition of the metre).
SPEED_OF_LIGHT = 299_792_458

#: Time units, in seconds (exact).
TIME_UNITS: dict[str, Fraction] = {
    "s": Fraction(1), "ms": Fraction(1, 10**3), "us": Fraction(1, 10**6),
    "ns": Fraction(1, 10**9), "ps": Fraction(1, 10**12), "fs": Fraction(1, 10**15),
    "as": Fraction(1, 10**18),
}

#: Frequency units, in hertz (exact); ``ps-1`` (also ``1/ps``, ``ps^-1``) is 1/ps = 1 THz.
FREQUENCY_UNITS: dict[str, Fraction] = {
    "Hz": Fraction(1), "kHz": Fraction(10**3), "MHz": Fraction(10**6), "GHz": Fraction(10**9),
    "THz": Fraction(10**12), "PHz": Fraction(10**15),
    **{f"{t}-1": 1 / s for t, s in TIME_UNITS.items()},
}

#: The forms a frequency can take (keys of a ``modes:`` item, options on the command line);
#: ``sigma`` is the standard deviation of a Gaussian target for HMC with unit mass
#: (``H = p^2/2 + q^2/(2 sigma^2)``: beta = 1/sigma, no unit).
FORMS = ("beta", "frequency", "wavenumber", "period", "sigma")

_QUANTITY = re.compile(r"\s*([+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)\s*([A-Za-z/^\-0-9]*)\s*")


def time_unit(name: str | None) -> str | None:
    """``name`` if it is a known time unit (None stays None)."""
    if name is None:
        return None
    if not isinstance(name, str) or name not in TIME_UNITS:
        raise StepsafeError(f"unknown time unit {str(name)[:20]!r}; choose one of "
                            f"{', '.join(TIME_UNITS)}")
    return name


def _unit_name(text: str) -> str:
    """Spellings of inverse time: ``1/ps`` and ``ps^-1`` are ``ps-1``; ``cm^-1`` is ``cm-1``."""
    if text.startswith("1/"):
        return text[2:] + "-1"
    return text.replace("^-1", "-1")


def parse_quantity(text: str) -> tuple[float, str | None]:
    """``"3700 cm-1"`` -> ``(3700.0, "cm-1")``; a plain number has unit None. No
    expressions: a decimal number and a unit name, nothing else."""
    match = _QUANTITY.fullmatch(text) if text.isascii() else None
    if match is None:
        raise StepsafeError(f"{text!r} is not a number with an optional unit "
                            "(e.g. 3700 cm-1, 100 THz, 9 fs)")
    value, unit = float(match.group(1)), match.group(2)
    return value, (_unit_name(unit) if unit else None)


#: What a standard deviation may be, as every refusal of one says (the option or key
#: named before it).
SIGMA_RULE = ("a standard deviation, a finite number > 0 (0, negative numbers, inf and nan "
              "are refused)")


def angular_frequency(form: str, value: float, unit: str | None = None,
                      time: str | None = None) -> float:
    """beta in radians per ``time`` unit of a frequency given as ``form`` (see the module
    table) with value ``value`` in ``unit`` (None: the form's default)."""
    if form == "sigma" and not (math.isfinite(value) and value > 0):
        raise StepsafeError(f"sigma must be {SIGMA_RULE}, got {value:g}")
    if not (math.isfinite(value) and value >= 0):
        raise StepsafeError(f"{form} must be a finite number >= 0, got {value}")
    seconds = None if time is None else TIME_UNITS[time]
    if form == "beta":
        if unit is not None:
            raise StepsafeError(f"beta takes no unit (rad per time unit), got {unit!r}: "
                                "use frequency, wavenumber or period for values with units")
        return value
    if form == "wavenumber":
        if unit not in (None, "cm-1"):
            raise StepsafeError(f"a wavenumber is in cm-1, got {unit!r}")
        factor = Fraction(SPEED_OF_LIGHT * 100) * _needs(seconds, form)
        return _scaled(value, 2 * factor)
    if form == "frequency":
        if unit is None:
            return _scaled(value, Fraction(2))
        if unit not in FREQUENCY_UNITS:
            raise StepsafeError(f"unknown frequency unit {unit!r}; choose one of "
                                f"{', '.join(FREQUENCY_UNITS)}")
        return _scaled(value, 2 * FREQUENCY_UNITS[unit] * _needs(seconds, form))
    if form == "sigma":
        if unit is not None:
            raise StepsafeError(f"a standard deviation takes no unit here, got {unit!r}")
        beta = 1.0 / value
        if not math.isfinite(beta):
            raise StepsafeError(f"1/sigma overflows: sigma = {value}")
        return beta
    if form == "period":
        if value == 0:
            raise StepsafeError("a period must be > 0")
        if unit is None:
            return _scaled(1 / value, Fraction(2))
        if unit not in TIME_UNITS:
            raise StepsafeError(f"unknown time unit {unit!r} for a period; choose one of "
                                f"{', '.join(TIME_UNITS)}")
        # beta = 2 pi / (T * unit / time unit)
        ratio = TIME_UNITS[unit] / _needs(seconds, form)
        return _scaled(1 / value, 2 / ratio)
    raise StepsafeError(f"unknown form {form!r}; choose one of {', '.join(FORMS)}")


def _needs(seconds: Fraction | None, form: str) -> Fraction:
    if seconds is None:
        what = "a wavenumber (cm-1)" if form == "wavenumber" else f"a {form} with a unit"
        raise StepsafeError(f"{what} needs a time unit for h: give --time-unit (e.g. fs) or "
                            "time_unit: in the scene file")
    return seconds


def _scaled(value: float, factor: Fraction) -> float:
    """``pi * factor * value``, with ``factor`` exact until the one rounding of its float."""
    result = value * float(factor) * math.pi
    if not math.isfinite(result):
        raise StepsafeError(f"the angular frequency overflows: {value} x {float(factor):g} "
                            "x pi")
    return result


def angular_frequencies(form: str, values: Any, time: str | None) -> Any:
    """:func:`angular_frequency` of an array of values in the form's default unit (the
    same roundings, element by element); entries that are not finite positive frequencies
    come out NaN or inf for the caller to name."""
    import numpy as np  # (only for arrays: the command line's import stays light)

    seconds = None if time is None else TIME_UNITS[time]
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        if form == "beta":
            return values
        if form == "sigma":
            return 1.0 / values
        if form == "wavenumber":
            factor = 2 * Fraction(SPEED_OF_LIGHT * 100) * _needs(seconds, form)
            return values * float(factor) * math.pi
        if form == "frequency":
            return values * float(Fraction(2)) * math.pi
        if form == "period":
            return (1 / values) * float(Fraction(2)) * math.pi
    raise ValueError(form)


#: inf and nan as a command line or YAML spells them (``inf``, ``-Infinity``, ``.nan``).
_NON_FINITE = re.compile(r"[+-]?\.?(inf|infinity|nan)", re.IGNORECASE)


def quantity(value: object, form: str, time: str | None) -> float:
    """beta of one value as read from a file or the command line: a number (in the form's
    default unit) or a text with a unit (``"3700 cm-1"``)."""
    if isinstance(value, bool):
        raise StepsafeError(f"{form} must be a number, got {value!r}")
    if isinstance(value, (int, float)):
        try:
            number = float(value)
        except OverflowError:
            raise StepsafeError(f"{form} must be a finite number, got {str(value)[:40]}"
                                ) from None
        return angular_frequency(form, number, None, time)
    if isinstance(value, str):
        if _NON_FINITE.fullmatch(value.strip()):  # inf or nan, refused by the form's rule
            return angular_frequency(form, float(value.strip().replace(".", "")), None, time)
        number, unit = parse_quantity(value)
        return angular_frequency(form, number, unit, time)
    raise StepsafeError(f"{form} must be a number or a text such as '3700 cm-1', got "
                        f"{type(value).__name__}")


def time_unit_of(value: object) -> str | None:
    """The time unit a text names (``"0.5 fs"`` -> ``"fs"``); None for a number, a plain
    number's text, a text naming another unit and one that does not parse (its error comes
    where the value is read)."""
    if not isinstance(value, str):
        return None
    try:
        _, unit = parse_quantity(value)
    except StepsafeError:
        return None
    return unit if unit in TIME_UNITS else None


def implied_time_unit(*values: object) -> str | None:
    """The time unit that values with a unit imply when none is given: the one time unit
    their texts name (a list is looked into), None when none names one; texts in two
    different units are a StepsafeError (which would the output be in?)."""
    named: set[str] = set()
    for value in values:
        items = value if isinstance(value, (list, tuple)) else [value]
        named.update(u for u in map(time_unit_of, items) if u is not None)
    if len(named) > 1:
        raise StepsafeError(f"values are given in {' and '.join(sorted(named))}: give the time "
                            "unit of h (--time-unit, time_unit: or time_unit=) to say which "
                            "unit the steps are in")
    return named.pop() if named else None


def duration(value: object, name: str, time: str | None, plain_text: bool = False) -> float:
    """A duration (a step h, a period, a run or trajectory time) in the ``time`` unit: a
    number is in it already; a text with a time unit (``"0.5 fs"``, ``"0.5fs"``,
    ``"2e-15 s"``) is converted to it exactly (the decimal digits and the ratio of the two
    units, a power of ten, are combined as fractions and rounded once). A text without a
    unit is a number only where every value is text (``plain_text``: the command line and
    files); a caller of the API gives numbers as numbers. A unit that is no time unit
    (``THz``, ``cm-1``) is refused, as is a unit where no time unit is known."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)) and not (
            hasattr(value, "dtype") and getattr(value, "ndim", 1) == 0
            and value.dtype.kind in "iuf"):
        raise StepsafeError(f"{name} must be a number or a text with a time unit such as "
                            f"'0.5 fs', got {type(value).__name__}")
    if not isinstance(value, str):
        try:
            return float(value)  # type: ignore[arg-type]  # (a 0-d array's item too)
        except OverflowError:
            raise StepsafeError(f"{name} must be a finite number, got {str(value)[:40]}"
                                ) from None
    number, unit = parse_quantity(value)
    if unit is None:
        if not plain_text:
            raise StepsafeError(f"{name} must be a number, or a text with a time unit such "
                                f"as '0.5 fs'; got the text {value[:40]!r} (give the number "
                                "itself)")
        return number
    if unit not in TIME_UNITS:
        kind = ("a wavenumber" if unit == "cm-1" else "a frequency"
                if unit in FREQUENCY_UNITS else "an unknown")
        raise StepsafeError(f"{name} is a time: {value[:40]!r} has {kind} unit ({unit}); give "
                            f"one of {', '.join(TIME_UNITS)}")
    if time is None:
        raise StepsafeError(f"{name} {value[:40]!r}: a value in {unit} needs the time unit of h "
                            "(--time-unit, time_unit: or time_unit=)")
    ratio = TIME_UNITS[unit] / TIME_UNITS[time]
    digits = _QUANTITY.fullmatch(value)
    text = digits.group(1) if digits is not None else ""
    if math.isfinite(number) and number != 0 and len(text) <= 60 and abs(
            int(text.lower().partition("e")[2] or 0)) <= 400:
        try:
            return float(Fraction(text) * ratio)  # exact until this one rounding
        except OverflowError:  # beyond float64: the caller says it is not finite
            return math.copysign(math.inf, number)
    return number * float(ratio)


def any_frequency(value: object, time: str | None) -> float:
    """beta (rad per ``time`` unit) of a frequency whose unit names its form: a plain
    number is an angular frequency (rad per time unit), ``"3700 cm-1"`` a wavenumber,
    ``"100 THz"`` or ``"3 ps-1"`` a frequency, ``"9 fs"`` a period."""
    if isinstance(value, str):
        number, unit = parse_quantity(value)
        form = ("beta" if unit is None else "wavenumber" if unit == "cm-1"
                else "period" if unit in TIME_UNITS else "frequency")
        return angular_frequency(form, number, unit, time)
    return quantity(value, "beta", time)


# ------------------------------------------------------------------ units of K and M

#: The Avogadro constant, 1/mol (exact in the SI since 2019).
AVOGADRO = Fraction(602_214_076) * 10**15
#: Energy units of a stiffness (per length squared), in joules: the calorie is 4.184 J and
#: the electronvolt 1.602176634e-19 J exactly; the hartree is CODATA 2022's.
ENERGY_UNITS: dict[str, Fraction] = {
    "J": Fraction(1), "kJ/mol": Fraction(1000) / AVOGADRO,
    "kcal/mol": Fraction(4184) / AVOGADRO, "eV": Fraction("1.602176634e-19"),
    "hartree": Fraction("4.3597447222060e-18"),
}
#: Length units, in metres (the bohr radius is CODATA 2022's).
LENGTH_UNITS: dict[str, Fraction] = {
    "m": Fraction(1), "nm": Fraction(1, 10**9), "angstrom": Fraction(1, 10**10),
    "pm": Fraction(1, 10**12), "bohr": Fraction("5.29177210544e-11"),
}
#: Mass units, in kilograms: the atomic mass constant (``amu``, also ``u``, ``Da``) and the
#: electron mass are CODATA 2022's; ``g/mol`` is 1e-3 kg over the Avogadro constant.
MASS_UNITS: dict[str, Fraction] = {
    "kg": Fraction(1), "amu": Fraction("1.66053906892e-27"),
    "u": Fraction("1.66053906892e-27"), "Da": Fraction("1.66053906892e-27"),
    "g/mol": Fraction(1, 1000) / AVOGADRO, "me": Fraction("9.1093837139e-31"),
}


def stiffness_scale(energy: str, length: str, mass: str, time: str) -> Fraction:
    """The factor that brings a stiffness in ``energy/length^2`` against a mass in
    ``mass`` to rad per ``time`` unit: ``K M^-1`` has the unit ``1 / t0^2`` with
    ``t0^2 = mass length^2 / energy``, so ``omega^2`` in rad^2 per ``time^2`` is the
    eigenvalue times ``(time / t0)^2 = time^2 energy / (mass length^2)`` (exact)."""
    return (TIME_UNITS[time] ** 2 * ENERGY_UNITS[energy]
            / (MASS_UNITS[mass] * LENGTH_UNITS[length] ** 2))


# ------------------------------------------------------------------ temperature

#: The Boltzmann constant, J/K (exact in the SI since 2019).
BOLTZMANN = Fraction("1.380649e-23")


def kelvin(value: object, name: str = "temperature") -> float:
    """A temperature in kelvin: a number (``300``) or a text with the unit K (``"300 K"``,
    ``"300K"``; a plain number as text too, as the command line and files give it);
    finite and >= 0."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise StepsafeError(f"{name} must be a number of kelvin or a text such as '300 K', "
                            f"got {type(value).__name__}")
    if isinstance(value, str):
        number, unit = parse_quantity(value)
        if unit not in (None, "K"):
            raise StepsafeError(f"{name} is in kelvin: {value[:40]!r} has the unit {unit} "
                                "(give 300, '300 K' or '300K')")
    else:
        try:
            number = float(value)
        except OverflowError:
            number = math.inf
    if not (math.isfinite(number) and number >= 0):
        raise StepsafeError(f"{name} must be a finite number of kelvin >= 0, got {value!r}")
    return number


def thermal_energy(temperature: float, energy: str) -> float:
    """``kT`` in the energy unit ``energy`` (one of :data:`ENERGY_UNITS`) at ``temperature``
    kelvin: ``k_B T / unit``, formed exactly as a fraction and rounded once (the Boltzmann
    constant, the Avogadro constant, the calorie and the electronvolt are exact)."""
    if energy not in ENERGY_UNITS:
        raise StepsafeError(f"unknown energy unit {str(energy)[:20]!r}; choose one of "
                            f"{', '.join(ENERGY_UNITS)}")
    return float(Fraction(temperature) * BOLTZMANN / ENERGY_UNITS[energy])

"""The arguments of the public API: each function takes the names it documents and no
others, and a name it does not take is a :class:`StepsafeError` listing every name it does.

Each frequency keyword has one meaning and one unit, and no two keywords differ by a letter
while their values differ by a factor (2 pi between an angular and an ordinary frequency):

======================  ==============================================================
keyword                 meaning and unit
======================  ==============================================================
``beta``                angular frequency of a vibration, rad per time unit
``saddle_beta``         rate of a saddle (H = beta p q), rad per time unit
``inverted_beta``       rate of a barrier top (p' = +beta^2 q), rad per time unit
``modes``               ``{model: betas}``, rad per time unit
``ordinary_frequency``  f = beta / (2 pi): cycles per time unit, or a text with a
                        frequency unit (``"100 THz"``, ``"3 ps-1"``)
``wavenumber``          cm^-1 (a number, or ``"3700 cm-1"``); needs a time unit
``period``              T = 2 pi / beta: in the time unit, or a text with a time unit
                        (``"9 fs"``)
``sigma``               standard deviation of a Gaussian target (unit mass), in the
                        units of q: beta = 1 / sigma
``fast_beta``,          the fast and the slow force's angular frequencies of an impulse
``slow_beta``           method, rad per time unit
``h``, ``step``         a step, in the time unit, or a text with a time unit (``"0.5 fs"``)
``time_unit``           the unit of every step in and out (``"fs"``, ...); without one,
                        the time unit of 1/beta
======================  ==============================================================

Words that name a frequency without saying which (``frequency``, ``frequencies``,
``omega``) are no keyword: given to a function, the error says what each reading is
called (:data:`READINGS`).
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable
from typing import Any, ParamSpec, TypeVar

from stepsafe.exceptions import StepsafeError

P = ParamSpec("P")
R = TypeVar("R")

_ANGULAR = ("beta", "angular frequencies, rad per time unit")
_ORDINARY = ("ordinary_frequency", "cycles per time unit or a text such as '100 THz'")

#: Names that are no keyword, and the keywords that say what each may mean (only those the
#: function takes are offered).
READINGS: dict[str, tuple[tuple[str, str], ...]] = {
    "frequencies": (_ANGULAR, _ORDINARY),
    "frequency": (_ANGULAR, _ORDINARY),
    "omega": (_ANGULAR,),
    "omegas": (_ANGULAR,),
    "angular_frequency": (_ANGULAR,),
    "betas": (_ANGULAR,),
    "saddle": (("saddle_beta", "rates of saddles, rad per time unit"),),
    "inverted": (("inverted_beta", "rates of barrier tops, rad per time unit"),),
    "fast": (("fast_beta", "the fast force's angular frequency, rad per time unit"),),
    "slow": (("slow_beta", "the slow force's angular frequency, rad per time unit"),),
    "step": (("h", "the step to check"),),
    "dt": (("h", "the step to check"), ("step", "a step to evaluate")),
    "h": (("step", "a step to evaluate"),),
}


def public(forwards: Callable[[], Callable[..., Any]] | None = None,
           drop: tuple[str, ...] = ()) -> Callable[[Callable[P, R]], Callable[P, R]]:
    """Decorate a public function: a positional argument beyond those it names before
    ``*``, a keyword it does not take, a missing or a repeated one, and a ``progress``
    that cannot be called are a StepsafeError.
    ``forwards`` returns the function its ``**inputs`` go to (:func:`stepsafe.problem`),
    whose keywords it takes too, less ``drop``, and ``problem`` (a problem built
    beforehand, given instead of them)."""
    def decorate(func: Callable[P, R]) -> Callable[P, R]:
        signature = inspect.signature(func)
        params = signature.parameters
        positional = [n for n, p in params.items()
                      if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
        own = [n for n, p in params.items() if p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL)]
        names: list[str] = []

        def accepted() -> list[str]:
            if not names:
                names.extend(own)
                if forwards is not None:
                    names.extend(n for n in inspect.signature(forwards()).parameters
                                 if n not in own and n not in drop)
                    names.append("problem")
            return names

        @functools.wraps(func)
        def call(*args: P.args, **kwargs: P.kwargs) -> R:
            takes = accepted()
            where = f"stepsafe.{func.__name__}"
            if len(args) > len(positional):
                keywords = [n for n in takes if n not in positional]
                raise StepsafeError(
                    f"{where} takes {len(positional)} positional argument(s) "
                    f"({', '.join(positional) or 'none'}), got {len(args)}: give the others "
                    f"by name ({', '.join(keywords)})")
            for key in kwargs:
                if key not in takes:
                    raise StepsafeError(unknown_argument(key, where, takes))
            try:
                signature.bind(*args, **kwargs)
            except TypeError as exc:  # a missing or a repeated argument
                raise StepsafeError(f"{where}: {exc}") from None
            progress = kwargs.get("progress")
            if progress is not None and not callable(progress):  # called late: check now
                raise StepsafeError(f"{where}: progress must be a function of the fraction "
                                    f"done, got {type(progress).__name__}")
            return func(*args, **kwargs)

        call.__signature__ = signature  # type: ignore[attr-defined]
        return call

    return decorate


def unknown_argument(key: str, where: str, takes: list[str]) -> str:
    """``unknown argument 'key'``, the keyword(s) it may have meant, and every name taken."""
    import difflib

    readings = [f"{name}= ({meaning})" for name, meaning in READINGS.get(key, ())
                if name in takes]
    close = difflib.get_close_matches(key, takes, n=1, cutoff=0.75)
    hint = (f": give {' or '.join(readings)}" if readings
            else f"; did you mean {close[0]!r}?" if close else "")
    return f"unknown argument {key!r} to {where}{hint} (it takes {', '.join(takes)})"

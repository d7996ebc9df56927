"""stepsafe: step sizes that keep the type of an equilibrium under a symplectic integrator.

The public API (see :mod:`stepsafe.api`)::

    method(name, stages=None, base=None)        a built-in method, family member or file
    method_from_file(path)                      a method file
    region(method, model="all", zmax=10)        every z = beta*h interval that keeps structure
    advise(method, beta, ...)                   the safe steps h for your frequencies
    check(method, h, beta, ...)                 whether step h is safe (``.safe``)
    check_scenes([scene, ...], ...)             check of several scene files, as the command
    errors(method, z, model="oscillator")       phase and energy errors of one step
    compare(methods, beta, ...)                 methods ranked by cost at the usable step
    transfer_matrices(method, z, model)         the one-step matrices M(z), shape (n, 2, 2)
    hmc(methods, sigma=..., ...)                HMC on a Gaussian target: acceptance, step, cost
    design(sigma=..., step=h, stages=2)         a 2- or 3-stage HMC splitting for your target
    impulse(outer, inner, substeps=, fast_beta=, slow_beta=)  safe outer steps of r-RESPA
    impulse_advice(method, pairs)               ... for several modes (fast, slow) together
    measure(method, steps, scene=...)           run the method on the scene's own system
    refine(method, "energy", tol, scene=...)    the largest h whose measured error meets tol
    problem(...), load_scene(path)              inputs merged from a scene file and arguments
    StepsafeError                               every error a caller can cause (bad input)

``beta`` is an angular frequency in rad per time unit; every keyword of a frequency in
another form says its unit (:mod:`stepsafe.arguments`). Arguments after the first one or two
are given by name, and one a function does not take is a StepsafeError listing those it
takes. Results are frozen objects whose ``to_dict()`` is the command line's ``--json``
output.
The folders follow the data: ``methods`` (method data and files), ``core`` (transfer
matrices, regions, advice, accuracy), ``systems`` (linear and nonlinear systems, scenes),
``reference`` (the independent mpmath path), ``cli`` (commands and reports). Importing this
package imports nothing heavy: the API is loaded on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from stepsafe.exceptions import MethodError, StepsafeError

__version__ = "0.1.0"

_API = ("Integrator", "PartitionedTableau", "RegionReport", "AdviceReport", "CheckReport",
        "CheckError", "SceneChecks", "ErrorTable", "CompareReport", "CompareRow", "Problem",
        "method", "method_from_file", "region", "advise", "check", "check_scenes", "errors",
        "compare", "transfer_matrices", "problem", "load_scene")
#: The HMC part of the API (stepsafe.hmc_advice), built on the same inputs.
_HMC = ("hmc", "design", "HmcReport", "HmcRow", "DesignReport")
#: Multiple time stepping (stepsafe.respa_advice).
_MTS = ("impulse", "impulse_advice", "ImpulseReport", "ImpulseModesReport")
#: Measurement on the user's own system (stepsafe.measurement).
_MEASURE = ("measure", "refine", "MeasureReport", "MeasureRow", "Refinement")
__all__ = [*_API, *_HMC, *_MTS, *_MEASURE, "StepsafeError", "MethodError", "__version__"]

if TYPE_CHECKING:  # pragma: no cover
    from stepsafe.api import (  # noqa: F401
        AdviceReport,
        CheckError,
        CheckReport,
        CompareReport,
        CompareRow,
        ErrorTable,
        Integrator,
        PartitionedTableau,
        Problem,
        RegionReport,
        SceneChecks,
        advise,
        check,
        check_scenes,
        compare,
        errors,
        load_scene,
        method,
        method_from_file,
        problem,
        region,
        transfer_matrices,
    )
    from stepsafe.hmc_advice import DesignReport, HmcReport, HmcRow, design, hmc  # noqa: F401
    from stepsafe.measurement import (  # noqa: F401
        MeasureReport,
        MeasureRow,
        Refinement,
        measure,
        refine,
    )
    from stepsafe.respa_advice import (  # noqa: F401
        ImpulseModesReport,
        ImpulseReport,
        impulse,
        impulse_advice,
    )


def __getattr__(name: str) -> Any:
    if name in _API:
        from stepsafe import api

        return getattr(api, name)
    if name in _HMC:
        from stepsafe import hmc_advice

        return getattr(hmc_advice, name)
    if name in _MTS:
        from stepsafe import respa_advice

        return getattr(respa_advice, name)
    if name in _MEASURE:
        from stepsafe import measurement

        return getattr(measurement, name)
    raise AttributeError(f"module 'stepsafe' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API) | set(_HMC) | set(_MTS) | set(_MEASURE))

"""stepsafe: step sizes that keep the type of an equilibrium under a symplectic integrator.

The public API (its modules: :mod:`stepsafe.api`)::

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
    hmc(methods, logdensity=f, gradient=g, start=q0, trajectory_steps=L)  ... on your own
                                                target: acceptance estimated on draws
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

from stepsafe._version import __version__
from stepsafe.exceptions import MethodError, StepsafeError

#: Each public name and the module of :mod:`stepsafe.api` that defines it (loaded on first
#: use, so that ``import stepsafe`` stays light).
_MODULES = {name: module for module, names in {
    "inputs": ("Integrator", "PartitionedTableau", "Problem", "method", "method_from_file",
               "problem", "load_scene"),
    "reports": ("RegionReport", "AdviceReport", "CheckReport", "CheckError", "SceneChecks",
                "ErrorTable", "CompareReport", "CompareRow"),
    "hmc_reports": ("HmcReport", "HmcRow", "DesignReport"),
    "md_reports": ("ImpulseReport", "ImpulseModesReport"),
    "measure_reports": ("MeasureReport", "MeasureRow", "Refinement", "EnsembleReport",
                        "EnsembleRow"),
    "linear": ("region", "advise", "check", "check_scenes", "errors", "compare",
               "transfer_matrices"),
    "hmc": ("hmc", "design"),
    "md": ("impulse", "impulse_advice"),
    "measure": ("measure", "refine"),
}.items() for name in names}
__all__ = [*_MODULES, "StepsafeError", "MethodError", "__version__"]

if TYPE_CHECKING:  # pragma: no cover
    from stepsafe.api.hmc import (  # noqa: F401
        design,
        hmc,
    )
    from stepsafe.api.hmc_reports import (  # noqa: F401
        DesignReport,
        HmcReport,
        HmcRow,
    )
    from stepsafe.api.inputs import (  # noqa: F401
        Integrator,
        PartitionedTableau,
        Problem,
        load_scene,
        method,
        method_from_file,
        problem,
    )
    from stepsafe.api.linear import (  # noqa: F401
        advise,
        check,
        check_scenes,
        compare,
        errors,
        region,
        transfer_matrices,
    )
    from stepsafe.api.md import (  # noqa: F401
        impulse,
        impulse_advice,
    )
    from stepsafe.api.md_reports import (  # noqa: F401
        ImpulseModesReport,
        ImpulseReport,
    )
    from stepsafe.api.measure import (  # noqa: F401
        measure,
        refine,
    )
    from stepsafe.api.measure_reports import (  # noqa: F401
        EnsembleReport,
        EnsembleRow,
        MeasureReport,
        MeasureRow,
        Refinement,
    )
    from stepsafe.api.reports import (  # noqa: F401
        AdviceReport,
        CheckError,
        CheckReport,
        CompareReport,
        CompareRow,
        ErrorTable,
        RegionReport,
        SceneChecks,
    )


def __getattr__(name: str) -> Any:
    module = _MODULES.get(name)
    if module is None:
        raise AttributeError(f"module 'stepsafe' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f"stepsafe.api.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_MODULES))

"""Safe at temperature: the numeric core of the thermal analysis.

A hot, anharmonic system meets more than the linearisation at its minimum: the curvature at
thermal configurations (instantaneous normal modes) and the resonance bands the method's
nonlinear map opens at finite amplitude. The modules, in the order the data flows:

* :mod:`.potential`: ``U(q)`` with diagonal masses (from a scene's separable system, plain
  functions or a stiffness matrix), difference Hessian-vector products with error
  estimates, 1-D profiles along modes and their tabulation;
* :mod:`.sampling`: configurations at ``kT`` (exact draws where possible, BAOAB Langevin
  otherwise);
* :mod:`.inm`: the extreme eigenvalues of the mass-weighted Hessian at configurations;
* :mod:`.extremes`: the largest value a run of a given length reaches, with an upper
  confidence bound;
* :mod:`.trajectories`, :mod:`.bands`, :mod:`.drift`: ensembles of the method's own map,
  the bands where they fail, the energy drift;
* :mod:`.limit`: :func:`thermal_limit` and :func:`thermal_check`.
"""

from stepsafe.systems.thermal.limit import ThermalCheck, ThermalLimit, thermal_check, thermal_limit
from stepsafe.systems.thermal.potential import Potential, from_callables, of_system, quadratic

__all__ = ["Potential", "ThermalCheck", "ThermalLimit", "from_callables", "of_system",
           "quadratic", "thermal_check", "thermal_limit"]

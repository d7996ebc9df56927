"""Molecular-dynamics systems read from an MD engine: forces, masses, constraints and virtual
sites through the narrow :class:`~stepsafe.systems.md.engine.ForceEngine` interface, the
Hessian by finite differences of the engine's forces (dense, or as Hessian-vector products
for Lanczos), the Hessian on the tangent space of holonomic constraints, hydrogen mass
repartitioning, trial runs of the engine's own integrators that validate a verdict, and
:mod:`~stepsafe.systems.md.system`, which turns a scene's ``system: {openmm:, positions:}``
into the modes the advice is about.

Units are the engine's (OpenMM's): nm, amu, ps, kJ/mol, K. This unit system is consistent,
1 kJ/mol = 1 amu nm^2/ps^2, so the eigenvalues of a mass-weighted Hessian are angular
frequencies squared in rad^2/ps^2 and Verlet's linear limit is h = 2/omega_max in ps.

Only :mod:`~stepsafe.systems.md.openmm_engine` imports OpenMM, and only inside its functions;
the other modules need numpy and scipy.
"""

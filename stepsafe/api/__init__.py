"""The public Python API, one module per kind of user; :mod:`stepsafe` re-exports every
public name (``stepsafe.check``, ...), and that is where to import them from.

==========================  ===========================================================
module                      contents
==========================  ===========================================================
:mod:`.inputs`              the method (:func:`method`, :class:`Integrator`), the problem
                            (:func:`problem`, :class:`Problem`) and the argument checks
:mod:`.reports`             the frozen result classes; ``to_dict()`` is the ``--json``
:mod:`.linear`              region, advise, check, check_scenes, errors, compare,
                            transfer_matrices (linear models, scenes, systems)
:mod:`.hmc`                 hmc, design (Hamiltonian Monte Carlo on Gaussian targets)
:mod:`.md`                  impulse, impulse_advice (multiple time stepping, r-RESPA)
:mod:`.measure`             measure, refine (runs on the user's own system)
==========================  ===========================================================

Every function takes numbers and arrays (or file paths for scenes and method files), never
prints and never exits; bad input raises :class:`~stepsafe.exceptions.StepsafeError` (exit
code 2 on the command line), whose ``where`` names the file and key at fault, and so does an
argument a function does not take (the error lists those it takes). Arguments after the
first one or two (the method, the frequencies, the step) are given by name.

This package imports nothing: each module imports what it uses.
"""

"""stepsafe: step sizes that keep the type of an equilibrium under a symplectic integrator.

The numeric core (``methods``, ``families``, ``models``, ``transfer``, ``regions``) knows
nothing of YAML or the terminal; ``methodfile``/``library`` read method files and ``cli``
is the command-line interface. Importing this package imports nothing heavy.
"""

__version__ = "0.1.0"

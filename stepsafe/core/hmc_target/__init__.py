"""HMC on the user's own target (not only Gaussians): a potential with its gradient, draws
from it, the acceptance of each method's own trajectories estimated on those draws with its
Monte Carlo error, the spread of local frequencies over the draws, and the advice built on
them beside the Gaussian (Laplace) figures at the mode.

Modules, in the direction the data moves: :mod:`~stepsafe.core.hmc_target.potential`
(the target), :mod:`~stepsafe.core.hmc_target.draws` (mode, Laplace approximation, the
warm-up sampler), :mod:`~stepsafe.core.hmc_target.trajectories` (proposals, vectorised),
:mod:`~stepsafe.core.hmc_target.statistics` (effective sample size),
:mod:`~stepsafe.core.hmc_target.estimate` (acceptance, step at target, divergence onset),
:mod:`~stepsafe.core.hmc_target.frequencies` (instantaneous frequencies) and
:mod:`~stepsafe.core.hmc_target.advice` (every method on the target, ranked).
"""

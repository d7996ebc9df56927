"""What every method kind implements, and the factors a step is made of.

A method kind (:mod:`stepsafe.methods.tableaux`: Runge–Kutta, partitioned RK, splitting with
or without force gradients, composition, processed, impulse; :mod:`stepsafe.methods.langevin`)
is a frozen dataclass holding its coefficients and implementing :class:`MethodKind`. The
analyses ask the method (its stages, symmetry, residuals, decomposition, ...) rather than
testing its class, so a new kind is one class, its method file and its tests.

The decomposition. One step of size h is a sequence of *blocks*, applied in order, each
run at ``weight * h``::

    step(h) = block_k(w_k h) o ... o block_2(w_2 h) o block_1(w_1 h)

    Shears(s, w)   a splitting s: drift(a_1 w h) kick(b_1 w h) drift(a_2 w h) ...
                   (force-gradient terms with their kicks); on an H that mixes q and p,
                   its symplectic Euler factors DK(c) / KD(d) (Splitting.euler_factors)
    Stages(m, w)   one step of the (partitioned) Runge–Kutta method m at w h: the stage
                   system (I - w h K) X = E with m's tableaux A_q, A_p, weights b_q, b_p
    Friction(w)    the Ornstein–Uhlenbeck step of Langevin dynamics over w h:
                   p <- c p + sqrt((1 - c^2) kT m) xi, c = exp(-gamma w h)

A composition ``Phi(g_k h) o ... o Phi(g_1 h)`` is its base's blocks once per weight, the
weights multiplied. The linear analyses (:mod:`stepsafe.core.transfer` on the 2x2 test
models, :mod:`stepsafe.systems.coupled` on 2n x 2n systems) read one description of these
blocks, :func:`~stepsafe.methods.tableaux.linear_blocks`: consecutive Shears merged into one
splitting where every block is one, otherwise the blocks with their weights. The poles of
the step (where a stage system is singular) are those of its blocks: a Stages block's stage
operator, a Shears block's symplectic Euler factors on the diagonal (saddle) models.

Nothing here computes a transfer matrix: the methods are data, the numerics live in
:mod:`stepsafe.core`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, NamedTuple

if TYPE_CHECKING:  # pragma: no cover
    from stepsafe.methods.residuals import Residuals
    from stepsafe.methods.tableaux import PartitionedRK, RungeKutta, Splitting

#: Test models on which every drift and kick is a diagonal matrix (H = +-beta p q).
DIAGONAL_MODELS = ("saddle", "saddle-p")
#: Every test model (:mod:`stepsafe.core.models`).
ALL_MODELS = ("oscillator", "saddle", "inverted", "saddle-p")
#: Digits of the high-precision transfer matrices of a method (its ``exact`` definition, or its
#: parts: :func:`stepsafe.methods.exact.high_precision`); :mod:`stepsafe.core.escalate` decides
#: at these.
HIGH_PRECISION_DIGITS = 40
#: The criteria of :mod:`stepsafe.core.regions` (``structure``: the flow's type and its
#: orientation; ``stability``: the type alone).
ALL_CRITERIA = ("structure", "stability")


class Exact(NamedTuple):
    """A method's exact definition, from which its high-precision transfer matrix is built
    (:func:`stepsafe.methods.exact.defined`): a Gauss or Lobatto IIIA-IIIB family member
    (``source="family"``, ``name`` ``gauss`` or ``lobatto3ab``, ``stages``), its tableau
    computed at raised precision; or a method file (``source="file"``, ``name`` a built-in
    name or a path, ``stages`` of a family base, ``base`` swapped in), read with its decimal
    literals exact."""

    source: str
    name: str
    stages: int | None
    base: str | None = None


@dataclass(frozen=True, eq=False)
class Shears:
    """A drift/kick sequence (a :class:`~stepsafe.methods.tableaux.Splitting`) run at
    ``weight * h``."""

    splitting: Splitting
    weight: float = 1.0


@dataclass(frozen=True, eq=False)
class Stages:
    """One step of a Runge–Kutta or partitioned RK method (the object as given, so that
    per-method caches of its stage operator hold) at ``weight * h``."""

    method: RungeKutta | PartitionedRK
    weight: float = 1.0


@dataclass(frozen=True, eq=False)
class Friction:
    """The Ornstein–Uhlenbeck step of Langevin dynamics over ``weight * h``: on the mean,
    ``p <- c p`` with ``c = exp(-gamma weight h)``; the noise adds ``(1 - c^2) kT m`` to
    the variance of p (``gamma``: friction, per time unit; ``kT``: thermal energy)."""

    weight: float
    gamma: float
    kT: float = 1.0


Block = Shears | Stages | Friction




class MethodKind(ABC):
    """The protocol of a one-step method (every kind is a frozen dataclass implementing it).

    Identity: ``kind`` (the method file's ``kind:``), ``name``, ``title``, ``order``,
    ``evaluations`` (force evaluations per step as the file states them) and ``exact``
    (optional high-precision definition, see :mod:`stepsafe.methods.tableaux`) are fields
    of each kind. The rest is asked of the method:

    * ``stages``, ``explicit``, :meth:`symmetric`, :meth:`residuals` (symplecticity and
      consistency), ``partitioned`` (q and p treated differently);
    * :meth:`decomposition`: the blocks of one step (see the module docstring) and
      :meth:`step_decomposition`, those run every step (a processed method's kernel);
    * what a splitting structure gives: :meth:`splitting` (the step as one drift/kick
      sequence), ``force_gradient``, ``forces_per_step``, ``gradient_evaluations``;
    * :meth:`rk_form` (the tableaux of a Runge–Kutta kind), ``single_tableau``;
    * a processor: ``processor_operations``, ``inverse_operations``,
      ``processor_evaluations`` (None without one), :meth:`one_step` (the map from one output
      to the next), :meth:`region_method` (the map whose region is the method's);
    * what the analyses accept: ``hamiltonian``, ``models``, ``criteria`` and, where those
      are restricted, ``analysis_note`` saying why;
    * the cost of analysing it: ``reach`` (how far the substeps reach, in h), ``sample_work``
      (relative cost of one transfer matrix);
    * :meth:`coefficients` (its arrays, as ``show --json`` prints them).

    Its transfer matrix in mpmath is built from ``exact`` or from these by
    :func:`stepsafe.methods.exact.high_precision`.
    """

    kind: ClassVar[str]
    name: str
    title: str
    order: int | None
    evaluations: int | None
    exact: Exact | None

    # ---------------------------------------------------------------- identity
    @property
    @abstractmethod
    def stages(self) -> int:
        """Stages (force evaluations before first-same-as-last merging) of one step."""

    @property
    @abstractmethod
    def explicit(self) -> bool:
        """Whether a step needs no stage solve."""

    @abstractmethod
    def symmetric(self, tol: float = 1e-12) -> bool:
        """Whether the method is its own adjoint (coefficients mirrored to ``tol``,
        relative to each pair's size)."""

    @abstractmethod
    def residuals(self) -> Residuals:
        """Its :class:`~stepsafe.methods.residuals.Residuals` (symplecticity, consistency)."""

    @property
    def partitioned(self) -> bool:
        """Whether the method treats q and p differently."""
        return True

    @abstractmethod
    def coefficients(self) -> dict[str, Any]:
        """Its coefficient arrays as lists (``show --json``)."""

    # ---------------------------------------------------------------- decomposition
    @abstractmethod
    def decomposition(self, model: str | None = None) -> tuple[Block, ...]:
        """The blocks of one step on ``model`` (None: any H). A method whose step has no
        form there raises :class:`~stepsafe.exceptions.MethodError`."""

    def step_decomposition(self) -> tuple[Block, ...]:
        """The blocks run every step (a processed method runs its processor once at the
        start and its inverse at each output)."""
        return self.decomposition()

    def splitting(self) -> Splitting | None:
        """The step run every step as one drift/kick sequence, None if it is not one."""
        return None

    @property
    def force_gradient(self) -> bool:
        """Whether some kick carries a force-gradient term (then H must be separable
        with a quadratic kinetic energy)."""
        return False

    @property
    def forces_per_step(self) -> int | None:
        """Force evaluations per step as run (splittings: kicks, first same as last);
        None where the kind does not count them."""
        return None

    @property
    def gradient_evaluations(self) -> int:
        """Force-gradient terms (Hessian-vector products) per step as run."""
        return 0

    def rk_form(self) -> PartitionedRK | None:
        """The tableaux of a Runge–Kutta or partitioned RK method, None for other kinds."""
        return None

    @property
    def single_tableau(self) -> bool:
        """Whether the method is a Runge–Kutta method given by one tableau ``(A, b, c)``:
        on the oscillator its transfer matrix is its stability function ``R(iz)``."""
        return False

    # ---------------------------------------------------------------- processing
    @property
    def processor_operations(self) -> list[tuple[str, float]] | None:
        """The processor P as drift/kick operations, None without a processor."""
        return None

    @property
    def inverse_operations(self) -> list[tuple[str, float]] | None:
        """``P^-1`` as drift/kick operations, None without a processor."""
        return None

    @property
    def processor_evaluations(self) -> int | None:
        """Force evaluations of P (and of ``P^-1``), None without a processor."""
        return None

    def one_step(self) -> MethodKind:
        """The map from one output to the next as a method (``P^-1 K P`` as one splitting
        for a processed method; the method itself otherwise)."""
        return self

    def region_method(self, model: str = "oscillator") -> MethodKind:
        """The method whose M(z) the region finder analyses on ``model`` (the method
        itself but where a similar map has the same region)."""
        return self

    # ---------------------------------------------------------------- analyses
    @property
    def hamiltonian(self) -> bool:
        """Whether a step is the map of a Hamiltonian flow's approximation (phase and
        energy errors, HMC, orientation apply); a Langevin splitting's mean map is not."""
        return True

    @property
    def models(self) -> tuple[str, ...]:
        """The test models the method is analysed on."""
        return ALL_MODELS

    @property
    def criteria(self) -> tuple[str, ...]:
        """The region criteria that apply to the method."""
        return ALL_CRITERIA

    @property
    def analysis_note(self) -> str | None:
        """What the analyses of a method that is not Hamiltonian mean (the message where
        one asks for what does not apply); None for Hamiltonian methods."""
        return None

    @property
    def reach(self) -> float:
        """How far the substeps of one step reach, in units of h (at least 1)."""
        return 1.0

    @property
    def sample_work(self) -> float:
        """Relative cost of one evaluation of M(z) (see :mod:`stepsafe.core.grid`)."""
        return 1.0

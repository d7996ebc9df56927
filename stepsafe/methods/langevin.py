"""Langevin splittings: drift (A), kick (B) and the exact Ornstein–Uhlenbeck step (O).

Langevin dynamics ``dq = M^-1 p dt``, ``dp = -V'(q) dt - gamma p dt + sqrt(2 gamma kT) M^1/2
dW`` split into three exactly solvable parts, applied in the order of a word in the
letters A, B, O (Leimkuhler & Matthews, "Rational construction of stochastic numerical
methods for molecular sampling", Appl. Math. Res. Express 2013(1) 34–56)::

    A_t:  q <- q + t M^-1 p                          (drift)
    B_t:  p <- p - t V'(q)                            (kick)
    O_t:  p <- c p + sqrt((1 - c^2) kT) M^1/2 xi,     c = exp(-gamma t), xi ~ N(0, I)

Each letter's substep is ``h`` divided by how often the letter occurs (the convention of
openmmtools' ``LangevinIntegrator(splitting=...)``): ``BAOAB`` is ``B_{h/2} A_{h/2} O_h
A_{h/2} B_{h/2}``, ``OBABO`` is ``O_{h/2} B_{h/2} A_h B_{h/2} O_{h/2}``, and ``BAOA`` is
OpenMM's ``LangevinMiddleIntegrator`` (a full kick, a half drift, the O step, a half drift:
its state is the position at the step and the velocity half a step before it).

On the harmonic oscillator every substep is linear: one step is ``x' = M x + N xi`` with
``M`` the map of the mean (drifts and kicks are shears, O is ``diag(1, c)``), and the
covariance follows ``Sigma' = M Sigma M^T + N N^T`` (:mod:`stepsafe.core.langevin`).

The stability of the mean map for every friction. The O letters must form one run (up to a
rotation of the word: ``OBABO`` has one, cyclically). Then ``M = L O R`` with ``R`` the
letters before the run, ``L`` those after, and ``tr M = tr(O X)``, ``X = R L`` the drifts and
kicks in cyclic order from the run (``det M = c``, c the run's total factor). For a real 2x2
matrix of determinant c in [0, 1) both eigenvalues lie inside the unit circle iff
``|tr M| < 1 + c``; ``tr(O X) = X_11 + c X_22`` is affine in c, so the condition holds for
every ``c`` in (0, 1) iff it holds at both ends: ``|tr X| <= 2`` (c = 1) and ``|X_11| <= 1``
(c = 0), not both with equality. When X is a palindrome (the word is symmetric about its O
run, as BAOAB, ABOBA, OBABO and BAOA are), ``X_11 = X_22 = tr X / 2`` and the second condition
is the first: the mean map is stable for every friction exactly where X, a symplectic
splitting, is elliptic, ``|tr X| < 2`` (excluding ``tr X = +-2``). That is the region the
analyses report (:meth:`Langevin.region_method`); for these four it is ``omega h < 2`` at
every friction, Verlet's limit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

from stepsafe.exceptions import MethodError
from stepsafe.methods.protocol import Block, Exact, Friction, MethodKind, Shears
from stepsafe.methods.residuals import Residuals
from stepsafe.methods.tableaux import Splitting, splitting_from_operations

#: Letters a word may have at most (each is a substep of every analysis).
MAX_LETTERS = 64
#: What a letter does: ``drift`` (A), ``kick`` (B) or the friction step (O).
LETTERS = {"A": "drift", "B": "kick", "O": "friction"}

#: What a word samples on the harmonic oscillator, in closed form, as text (``show``), z =
#: omega h, for every friction gamma > 0 and z < 2 (the closed forms themselves:
#: :data:`stepsafe.core.langevin.CLOSED_FORMS`).
CLOSED_FORM_TEXT: dict[str, str] = {
    "BAOAB": "<q^2> m omega^2/kT = 1 (exact), <p^2>/(m kT) = 1 - z^2/4",
    "ABOBA": "<q^2> m omega^2/kT = 1 (exact), <p^2>/(m kT) = 1/(1 - z^2/4)",
    "OBABO": "<q^2> m omega^2/kT = 1/(1 - z^2/4), <p^2>/(m kT) = 1 (exact)",
    "BAOA": "<q^2> m omega^2/kT = 1, <p^2>/(m kT) = 1 (both exact; the velocity half a "
            "step behind the position), <q p> omega/kT = z/2",
}


@dataclass(frozen=True, eq=False)
class Langevin(MethodKind):
    """A Langevin splitting: a word in A, B, O (see the module docstring), the friction
    ``gamma`` (per time unit; in the dimensionless analyses of a test model, per unit of its
    frequency: ``c = exp(-gamma w z)``) and the thermal energy ``kT``."""

    letters: str
    friction: float = 1.0
    kT: float = 1.0
    name: str = "langevin"
    order: int | None = None
    evaluations: int | None = None
    title: str = ""
    exact: Exact | None = field(default=None, compare=False, repr=False)

    kind = "langevin"

    def __post_init__(self) -> None:
        word = self.letters
        if not isinstance(word, str) or not word or len(word) > MAX_LETTERS \
                or any(ch not in LETTERS for ch in word):
            shown = repr(word)[:40]
            raise MethodError(f"{self.name}: letters must be a word of at most {MAX_LETTERS} "
                              f"of A (drift), B (kick) and O (friction), got {shown}")
        missing = [ch for ch in "ABO" if ch not in word]
        if missing:
            raise MethodError(f"{self.name}: the word {word} has no {missing[0]} "
                              f"({LETTERS[missing[0]]} step): a Langevin splitting needs all "
                              "three")
        if _runs(word) != 1:
            raise MethodError(f"{self.name}: the O steps of {word} must be one run (up to a "
                              "rotation of the word, as in OBABO): the stability of the mean "
                              "map for every friction is decided for such words")
        for key in ("friction", "kT"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not math.isfinite(value) or value < 0 or (key == "kT" and value == 0):
                raise MethodError(f"{self.name}: {key} must be a finite number "
                                  f"{'> 0' if key == 'kT' else '>= 0'}, got {value!r}")
            object.__setattr__(self, key, float(value))

    # ---------------------------------------------------------------- the word
    def substeps(self) -> list[tuple[str, float]]:
        """The word as ``(letter, fraction of h)``: each letter's count divides h."""
        counts = {ch: self.letters.count(ch) for ch in LETTERS}
        return [(ch, 1.0 / counts[ch]) for ch in self.letters]

    def _splitting(self, letters: list[tuple[str, float]], role: str) -> Splitting:
        ops = [(LETTERS[ch], t) for ch, t in letters]
        return splitting_from_operations(ops, name=f"{self.name} {role}")

    def hamiltonian_part(self) -> Splitting:
        """``X``: the drifts and kicks in cyclic order from the end of the O run (the
        module docstring: ``tr M = tr(O X)``)."""
        steps = self.substeps()
        n = len(steps)
        end = next(i for i in range(n) if steps[i][0] == "O" and steps[(i + 1) % n][0] != "O")
        cyclic = [steps[(end + 1 + k) % n] for k in range(n)]
        return self._splitting([s for s in cyclic if s[0] != "O"], "X")

    def without_friction(self) -> Splitting:
        """The drifts and kicks in the word's order (``gamma = 0``: the O steps are the
        identity on the mean)."""
        return self._splitting([s for s in self.substeps() if s[0] != "O"], "at gamma 0")

    def with_friction(self, friction: float) -> Langevin:
        """The same word at another friction."""
        return replace(self, friction=friction)

    # ---------------------------------------------------------------- the protocol
    @property
    def stages(self) -> int:
        """Kicks per step (before first-same-as-last merging)."""
        return self.letters.count("B")

    @property
    def explicit(self) -> bool:
        return True

    @property
    def forces_per_step(self) -> int | None:
        """Forces per step as run: the kicks with the O steps (which leave q alone) taken
        out, the step's last and the next step's first merged when no drift separates them."""
        return self.without_friction().forces_per_step

    def symmetric(self, tol: float = 1e-12) -> bool:
        """Whether the word is a palindrome."""
        return self.letters == self.letters[::-1]

    def residuals(self) -> Residuals:
        """Not symplectic (the mean map contracts: ``det M = exp(-gamma h)``); consistent
        when each letter's substeps sum to h (they do, by construction)."""
        sums: dict[str, float] = {}
        for ch, t in self.substeps():
            sums[ch] = sums.get(ch, 0.0) + t
        cons = max(abs(s - 1.0) for s in sums.values())
        return Residuals(math.nan, math.nan, cons, None, 1.0)

    def coefficients(self) -> dict[str, Any]:
        return {"letters": self.letters, "friction": self.friction, "kT": self.kT,
                "substeps": [[ch, t] for ch, t in self.substeps()]}

    def decomposition(self, model: str | None = None) -> tuple[Block, ...]:
        """Runs of A and B letters as splittings, each O letter as a friction step."""
        blocks: list[Block] = []
        run: list[tuple[str, float]] = []
        for ch, t in self.substeps():
            if ch == "O":
                if run:
                    blocks.append(Shears(self._splitting(run, f"part {len(blocks) + 1}")))
                    run = []
                blocks.append(Friction(t, self.friction, self.kT))
            else:
                run.append((ch, t))
        if run:
            blocks.append(Shears(self._splitting(run, f"part {len(blocks) + 1}")))
        return tuple(blocks)

    @property
    def hamiltonian(self) -> bool:
        return False

    @property
    def models(self) -> tuple[str, ...]:
        return ("oscillator",)

    @property
    def criteria(self) -> tuple[str, ...]:
        return ("stability",)

    @property
    def analysis_note(self) -> str:
        return (f"{self.name} is a Langevin splitting ({self.letters}): friction contracts its "
                "mean map (det M = exp(-gamma h)), so the structure criterion does not apply; "
                "its region is where the mean map is stable for every friction, i.e. where X, "
                "its drifts and kicks taken from the O step, is elliptic (|tr X| < 2; the "
                "stability criterion, on vibrations)")

    def region_method(self, model: str = "oscillator") -> Splitting:
        """``X`` (:meth:`hamiltonian_part`): where it is elliptic the mean map is stable for
        every friction, when X is a palindrome (see the module docstring); a word whose X is
        not is refused."""
        part = self.hamiltonian_part()
        if not part.symmetric():
            raise MethodError(f"{self.name}: the drifts and kicks of {self.letters} taken from "
                              "its O steps are not symmetric, so where its mean map is stable "
                              "for every friction is not the region of its Hamiltonian part "
                              "(use a word symmetric about its O steps, as BAOAB or OBABO)")
        return part

def _runs(word: str) -> int:
    """Runs of O in the word, counted cyclically (a run across its end counts once)."""
    n = len(word)
    return sum(1 for i in range(n) if word[i] == "O" and word[i - 1] != "O") or \
        (1 if "O" in word else 0)

"""Method families for any stage count, and composition recipes.

Tableaux are built without Vandermonde solves (which lose about ``s`` digits for ``s``
stages). Nodes come from the symmetric tridiagonal Jacobi matrix (Golub–Welsch) polished by
Newton steps on the Legendre three-term recurrence; ``A`` comes from the W-transformation
(Hairer–Wanner II, §IV.5): with ``W[i, k] = P~_k(c_i)`` the normalised shifted Legendre
polynomials ``P~_k(x) = sqrt(2k+1) P_k(2x-1)``, collocation means ``A W = W X`` where
``X`` holds the exact integrals ``int_0^x P~_k = xi_{k+1} P~_{k+1} - xi_k P~_{k-1}``
(``xi_k = 1 / (2 sqrt(4k^2 - 1))``, ``int_0^x P~_0 = P~_0/2 + xi_1 P~_1``). The
quadrature makes ``W^T B W`` the identity (Gauss) or the identity but for its last
diagonal entry (Lobatto), so ``W^-1`` is explicit and well conditioned.

* ``gauss(s)``: Gauss–Legendre collocation, order 2s, symplectic and symmetric.
* ``lobatto3ab(s)``: Lobatto IIIA for q, IIIB for p (s >= 2), order 2s-2. IIIB is built as
  the symplectic partner of IIIA, ``A_B[i, j] = b_j (1 - A_A[j, i] / b_i)``.
* ``triple_jump(base)``, ``suzuki_fractal(base)``: order ``2k -> 2k+2`` for a symmetric base
  of even order 2k (Yoshida 1990, Suzuki 1990).
"""

from __future__ import annotations

import numpy as np

from stepsafe.exceptions import MethodError
from stepsafe.methods.protocol import Exact
from stepsafe.methods.tableaux import Composition, Method, PartitionedRK, RungeKutta

#: Largest stage count accepted for the families (accuracy verified up to here by tests).
MAX_STAGES = 40


def _check_stages(s: int, smallest: int, family: str) -> None:
    if not isinstance(s, (int, np.integer)) or isinstance(s, bool):
        raise MethodError(f"{family}: the stage count must be an integer, got {s!r}")
    if s < smallest or s > MAX_STAGES:
        raise MethodError(f"{family}: -s must be between {smallest} and {MAX_STAGES}, got {s}")


def _legendre(n: int, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``P_n(x)`` and ``P_n'(x)`` on [-1, 1] by the three-term recurrence."""
    p0, p1 = np.ones_like(x), x.copy()
    if n == 0:
        return p0, np.zeros_like(x)
    for k in range(2, n + 1):
        p0, p1 = p1, ((2 * k - 1) * x * p1 - (k - 1) * p0) / k
    with np.errstate(divide="ignore", invalid="ignore"):
        dp = n * (x * p1 - p0) / (x * x - 1.0)
    return p1, dp


def _normalised_legendre_table(c: np.ndarray, s: int) -> np.ndarray:
    """``W[i, k] = sqrt(2k+1) P_k(2 c_i - 1)`` for ``k < s``."""
    x = 2.0 * c - 1.0
    W = np.empty((c.size, s))
    p_prev, p = np.zeros_like(x), np.ones_like(x)
    for k in range(s):
        W[:, k] = np.sqrt(2 * k + 1) * p
        p_prev, p = p, ((2 * k + 1) * x * p - k * p_prev) / (k + 1)
    return W


def _integration_matrix(s: int) -> np.ndarray:
    """``X`` with ``int_0^x P~_k = sum_j X[j, k] P~_j`` truncated to degree < s."""
    X = np.zeros((s, s))
    X[0, 0] = 0.5
    for k in range(1, s):
        xi = 0.5 / np.sqrt(4.0 * k * k - 1.0)
        X[k, k - 1] = xi
        X[k - 1, k] = -xi
    return X


def gauss_nodes(s: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Legendre nodes ``c`` and weights ``b`` on [0, 1]."""
    k = np.arange(1, s)
    offdiag = k / np.sqrt(4.0 * k * k - 1.0)
    x = np.linalg.eigvalsh(np.diag(offdiag, 1) + np.diag(offdiag, -1)) if s > 1 else np.zeros(1)
    for _ in range(3):
        p, dp = _legendre(s, x)
        x = x - p / dp
    x = 0.5 * (x - x[::-1])  # exact symmetry
    _, dp = _legendre(s, x)
    w = 2.0 / ((1.0 - x * x) * dp * dp)
    return 0.5 * (1.0 + x), 0.5 * w


def lobatto_nodes(s: int) -> tuple[np.ndarray, np.ndarray]:
    """Lobatto nodes (0, 1 and the zeros of ``P'_{s-1}``) and weights on [0, 1]."""
    n = s - 2
    if n > 0:
        k = np.arange(1, n)
        offdiag = np.sqrt(k * (k + 2.0) / ((2 * k + 1.0) * (2 * k + 3.0)))
        x = np.linalg.eigvalsh(np.diag(offdiag, 1) + np.diag(offdiag, -1)) if n > 1 else np.zeros(1)
        for _ in range(3):
            # Newton on P'_{s-1}: (1-x^2) P'' = 2x P' - n(n+1) P with n = s-1
            p, dp = _legendre(s - 1, x)
            d2p = (2.0 * x * dp - (s - 1) * s * p) / (1.0 - x * x)
            x = x - dp / d2p
        x = 0.5 * (x - x[::-1])
        x = np.concatenate([[-1.0], x, [1.0]])
    else:
        x = np.array([-1.0, 1.0])
    p, _ = _legendre(s - 1, x)
    w = 2.0 / (s * (s - 1) * p * p)
    return 0.5 * (1.0 + x), 0.5 * w


def gauss(s: int) -> RungeKutta:
    """s-stage Gauss–Legendre collocation method (order 2s)."""
    _check_stages(s, 1, "gauss")
    c, b = gauss_nodes(s)
    W = _normalised_legendre_table(c, s)
    A = W @ _integration_matrix(s) @ W.T @ np.diag(b)
    return RungeKutta(A, b, c, name=f"gauss-s{s}", order=2 * s, evaluations=s,
                      title=f"{s}-stage Gauss–Legendre collocation",
                      exact=Exact("family", "gauss", s))


def lobatto3a(s: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lobatto IIIA tableau ``(A, b, c)`` (collocation at the Lobatto nodes)."""
    c, b = lobatto_nodes(s)
    W = _normalised_legendre_table(c, s)
    X = _integration_matrix(s)
    X[s - 2, s - 1] = 0.0  # int_0^x P~_{s-1} vanishes at every Lobatto node
    gamma = float(np.sum(b * W[:, s - 1] ** 2))  # (W^T B W)[s-1, s-1]; the rest is I
    W_inv = W.T @ np.diag(b)
    W_inv[s - 1] /= gamma
    A = W @ X @ W_inv
    A[0] = 0.0  # first stage is exactly q0
    A[s - 1] = b  # last stage is exactly q1 (collocation at c = 1: int_0^1 l_j = b_j)
    return A, b, c


def lobatto3ab(s: int) -> PartitionedRK:
    """s-stage Lobatto IIIA (q) – IIIB (p) pair (order 2s-2); s = 2 is Störmer–Verlet."""
    _check_stages(s, 2, "lobatto3ab")
    A_a, b, _ = lobatto3a(s)
    A_b = b[None, :] * (1.0 - A_a.T / b[:, None])
    A_b[:, s - 1] = 0.0  # IIIB's last column vanishes
    return PartitionedRK(A_a, b, A_b, b.copy(), name=f"lobatto3ab-s{s}", order=2 * s - 2,
                         evaluations=s - 1,
                         title=f"{s}-stage Lobatto IIIA–IIIB pair",
                         exact=Exact("family", "lobatto3ab", s))


def _recipe_order(base: Method, recipe: str) -> int:
    order = getattr(base, "order", None)
    if order is None or order % 2:
        raise MethodError(f"{recipe} needs a symmetric base of even order; "
                          f"{base.name} has order {order}")
    if not is_symmetric(base):
        raise MethodError(f"{recipe} needs a symmetric base method; {base.name} is not symmetric")
    return int(order)


def triple_jump(base: Method, name: str | None = None) -> Composition:
    """Yoshida's triple jump ``g1, g0, g1`` with ``g1 = 1/(2 - 2^(1/(2k+1)))``."""
    k2 = _recipe_order(base, "triple jump")
    root = 2.0 ** (1.0 / (k2 + 1))
    g1 = 1.0 / (2.0 - root)
    weights = np.array([g1, -root * g1, g1])
    return Composition(base, weights, name=name or f"triple-jump({base.name})", order=k2 + 2,
                       title=f"triple jump of {base.name}", base_order=k2)


def suzuki_fractal(base: Method, name: str | None = None) -> Composition:
    """Suzuki's 5-stage fractal ``p, p, 1-4p, p, p`` with ``p = 1/(4 - 4^(1/(2k+1)))``."""
    k2 = _recipe_order(base, "Suzuki's fractal")
    p = 1.0 / (4.0 - 4.0 ** (1.0 / (k2 + 1)))
    weights = np.array([p, p, 1.0 - 4.0 * p, p, p])
    return Composition(base, weights, name=name or f"suzuki({base.name})", order=k2 + 2,
                       title=f"Suzuki 5-stage fractal of {base.name}", base_order=k2)


RECIPES = {"triple-jump": triple_jump, "suzuki": suzuki_fractal}


def is_symmetric(method: Method, tol: float = 1e-12) -> bool:
    """Whether the method is its own adjoint (checked on the coefficients, each mirrored
    pair to ``tol`` relative to its own size, so that the same method at another step,
    every coefficient scaled, is judged the same).

    RK: ``a_ij + a_{s+1-i, s+1-j} = b_j`` and ``b`` palindromic (after the standard
    stage reversal). Splitting: the merged drift/kick sequence is a palindrome.
    Composition: palindromic weights over a symmetric base. Impulse: symmetric outer and
    inner splittings (each outer drift is then K steps of a symmetric map). Each kind
    decides (:meth:`~stepsafe.methods.protocol.MethodKind.symmetric`).
    """
    return method.symmetric(tol)

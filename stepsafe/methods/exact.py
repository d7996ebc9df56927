"""The methods' transfer matrices in mpmath, from their exact definitions.

What the core decides at high precision where float64 cannot (:mod:`stepsafe.core.escalate`,
:mod:`stepsafe.core.accuracy`) and what the reference recomputes (:mod:`stepsafe.reference`):
a method's one-step map ``M(z)`` on a test model, in mpmath numbers at the caller's precision
(``with mp.workdps(d): ...``). Its definition is the method's own where it carries one
(:class:`~stepsafe.methods.protocol.Exact`: a Gauss or Lobatto family member's tableau with
its nodes and weights computed at raised precision, a method file's decimal literals read
exactly by the mpmath backend of the expression evaluator, recipes from their formulas), else
its float coefficients taken as exact. Stage equations are solved in mpmath; nothing here
shares code with the float64 path. mpmath is imported inside the functions, so importing
this module loads nothing heavy.

Conventions: phase space x = (q, p); a method applied to x' = L x with step z (z = beta*h)
is the linear map x1 = M(z) x0; the models L are :data:`MODELS`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import lru_cache
from itertools import zip_longest
from pathlib import Path
from typing import Any, NamedTuple

from stepsafe.files.expressions import mpmath_backend
from stepsafe.methods.langevin import Langevin
from stepsafe.methods.library import FAMILIES, _find_file, _looks_like_path, load_file
from stepsafe.methods.protocol import HIGH_PRECISION_DIGITS, Exact, Friction, MethodKind, Shears
from stepsafe.methods.tableaux import (
    Composition,
    Impulse,
    PartitionedRK,
    Processed,
    RungeKutta,
    Splitting,
)

MODELS = {
    "oscillator": ((0, 1), (-1, 0)),
    "saddle": ((1, 0), (0, -1)),
    "inverted": ((0, 1), (1, 0)),
    "saddle-p": ((-1, 0), (0, 1)),
}


MFun = Callable[[object], object]


def _shifted_legendre(n: int) -> list:
    """Ascending coefficients of P_n(2x - 1) (exact integers)."""
    from mpmath import mp

    return [(-1) ** (n + k) * mp.binomial(n, k) * mp.binomial(n + k, k)
            for k in range(n + 1)]


def _real_roots(coeffs: list, n: int) -> list:
    """Sorted real roots of sum coeffs[k] x^k (all roots real and simple)."""
    from mpmath import mp

    if len(coeffs) < 2:
        return []
    import inspect

    kwargs = dict(maxsteps=200 + 20 * n, extraprec=mp.prec + 20 * n)
    if "asc" in inspect.signature(mp.polyroots).parameters:  # mpmath >= 1.4
        roots = mp.polyroots(coeffs, asc=True, **kwargs)
    else:
        roots = mp.polyroots(coeffs[::-1], **kwargs)
    return sorted(mp.re(r) for r in roots)


def _legendre(n: int, x) -> tuple:
    """``(P_n(x), P_n'(x))`` on [-1, 1] by the three-term recurrence
    ``(k+1) P_{k+1} = (2k+1) x P_k - k P_{k-1}`` and ``(1 - x^2) P_n' = n (P_{n-1} - x P_n)``
    (``P_n'(+-1) = (+-1)^{n-1} n(n+1)/2``)."""
    from mpmath import mp

    p0, p1 = mp.one, x
    if n == 0:
        return p0, mp.zero
    for k in range(1, n):
        p0, p1 = p1, ((2 * k + 1) * x * p1 - k * p0) / (k + 1)
    if abs(x) == 1:
        return p1, x ** (n - 1) * n * (n + 1) / 2
    return p1, n * (p0 - x * p1) / (1 - x * x)


def _certified(f: Callable, roots: list, count: int) -> bool:
    """Whether ``roots`` (sorted) are ``count`` distinct roots of ``f`` in (-1, 1), each
    certified by a sign change of ``f`` over ``r -+ d`` (``d`` half the working digits) on
    disjoint intervals: ``f`` has exactly ``count`` roots there, so these are all of them."""
    from mpmath import mp

    if len(roots) != count:
        return False
    d = mp.mpf(2) ** (-mp.prec // 2)
    edges = [-mp.one] + [x for r in roots for x in (r - d, r + d)] + [mp.one]
    if any(a >= b for a, b in zip(edges, edges[1:])):
        return False
    return all((f(r - d) > 0) != (f(r + d) > 0) for r in roots)


def _newton(f_df: Callable, x, lo=None, hi=None):
    """Newton's method on ``f_df(x) = (f, f')`` from ``x`` to the working precision; with a
    bracket ``(lo, hi)`` whose ends ``f`` takes with opposite signs, a step that leaves it
    bisects instead and the bracket follows the signs (so it converges to the root inside)."""
    from mpmath import mp

    f_lo = None if lo is None else f_df(lo)[0]
    tol = mp.eps * 4
    settled = 0
    for _ in range(4 * mp.prec):
        f, df = f_df(x)
        if f == 0:
            return x
        if lo is not None and f_lo is not None:  # (both or neither)
            if (f > 0) == (f_lo > 0):
                lo, f_lo = x, f
            else:
                hi = x
        step = f / df if df else mp.inf
        new = x - step
        if lo is not None and hi is not None and not lo <= new <= hi:
            new = (lo + hi) / 2
        settled = settled + 1 if abs(new - x) <= tol * max(1, abs(x)) else 0
        x = new
        if settled >= 2:
            break
    return x


def _gauss_nodes(n: int) -> list:
    """The roots of ``P_n`` on [-1, 1], ascending: Newton's method from Tricomi's
    ``cos(pi (k - 1/4) / (n + 1/2))``, certified by :func:`_certified` (else the roots of
    the polynomial's coefficients, :func:`_real_roots`)."""
    from mpmath import mp

    def f_df(x):
        return _legendre(n, x)

    roots = sorted(_newton(f_df, mp.cos(mp.pi * (k - mp.mpf(1) / 4) / (n + mp.mpf(1) / 2)))
                   for k in range(1, n + 1))
    if _certified(lambda x: _legendre(n, x)[0], roots, n):
        return roots
    return [2 * r - 1 for r in _real_roots(_shifted_legendre(n), n)]


def _lobatto_interior(n: int) -> list:
    """The roots of ``P_n'`` on (-1, 1), ascending: one between each two consecutive roots
    of ``P_n`` (they interlace), by Newton's method kept inside that bracket
    (``(1 - x^2) P_n'' = 2 x P_n' - n (n+1) P_n``), certified by :func:`_certified`."""
    def f_df(x):
        p, dp = _legendre(n, x)
        return dp, (2 * x * dp - n * (n + 1) * p) / (1 - x * x)

    nodes = _gauss_nodes(n)
    roots = [_newton(f_df, (a + b) / 2, a, b) for a, b in zip(nodes, nodes[1:])]
    if _certified(lambda x: _legendre(n, x)[1], roots, n - 1):
        return roots
    leg = _shifted_legendre(n)
    return [2 * r - 1 for r in _real_roots([k * leg[k] for k in range(1, len(leg))], n)]


def _collocation(c: list) -> tuple:
    """Moment (Vandermonde) solve: b_j with sum_j b_j c_j^k = 1/(k+1) and
    A[i,j] = int_0^{c_i} l_j(t) dt, i.e. sum_j A[i,j] c_j^k = c_i^{k+1}/(k+1),
    k = 0..s-1 (simplifying conditions B(s), C(s))."""
    from mpmath import mp

    s = len(c)
    powers = [[mp.one] for _ in c]  # powers[i][k] = c_i^k, k = 0..s
    for i, ci in enumerate(c):
        for _ in range(s):
            powers[i].append(powers[i][-1] * ci)
    vinv = mp.inverse(mp.matrix([[powers[j][k] for j in range(s)] for k in range(s)]))
    b = [mp.fsum(vinv[j, k] / (k + 1) for k in range(s)) for j in range(s)]
    A = mp.matrix(s, s)
    for j in range(s):
        scaled = [vinv[j, k] / (k + 1) for k in range(s)]
        for i in range(s):
            A[i, j] = mp.fsum(scaled[k] * powers[i][k + 1] for k in range(s))
    return A, b


def _round(A, b: list, c: list) -> tuple:  # to the caller's precision
    return +A, [+x for x in b], [+x for x in c]


#: Tableaux computed so far, by (family, s): (the caller's precision in bits, A, b, c) at
#: the highest precision asked for; a request at that precision or less is rounded from it.
_TABLEAUX: dict[tuple[str, int], tuple] = {}


def _tableau(family: str, s: int, build: Callable) -> tuple:
    """``build()`` at the raised precision, rounded to the caller's (cached, see
    :data:`_TABLEAUX`); a fresh copy each call."""
    from mpmath import mp

    known = _TABLEAUX.get((family, s))
    if known is None or known[0] < mp.prec:
        with mp.workdps(mp.dps + 3 * s + 10):
            A, b, c = build()
        known = (mp.prec, A, b, c)
        _TABLEAUX[(family, s)] = known
    return _round(*known[1:])


def gauss_tableau(s: int) -> tuple:
    """Gauss-Legendre (A, b, c): c = roots of P_s(2x-1), A by collocation."""
    def build():
        c = [(1 + x) / 2 for x in _gauss_nodes(s)]
        A, b = _collocation(c)
        return A, b, c

    return _tableau("gauss", s, build)


_LOBATTO: dict[tuple[int, int], tuple] = {}


def _lobatto_iiia(s: int) -> tuple:
    """Lobatto IIIA ``(A, b, c)`` at the working precision (kept for IIIB, which is
    built from it at the same precision)."""
    from mpmath import mp

    if s < 2:
        raise ValueError("Lobatto needs s >= 2")
    if (s, mp.prec) not in _LOBATTO:
        c = [mp.zero] + [(1 + x) / 2 for x in _lobatto_interior(s - 1)] + [mp.one]
        A, b = _collocation(c)
        _LOBATTO[(s, mp.prec)] = (A, b, c)
    return _LOBATTO[(s, mp.prec)]


def lobatto_IIIA_tableau(s: int) -> tuple:
    """Lobatto IIIA (A, b, c): nodes 0, 1 and the roots of P'_{s-1}(2x-1);
    collocation A[i,j] = int_0^{c_i} l_j(t) dt; b the Lobatto weights."""
    return _tableau("lobatto3a", s, lambda: _lobatto_iiia(s))


def lobatto_IIIB_tableau(s: int) -> tuple:
    """Lobatto IIIB: the symplectic partner of IIIA, defined by
    b_i B[i,j] + b_j A[j,i] - b_i b_j = 0, i.e. B[i,j] = b_j (1 - A[j,i]/b_i).
    (s=2: [[1/2,0],[1/2,0]]; s=3: [[1/6,-1/6,0],[1/6,1/3,0],[1/6,5/6,0]].)"""
    from mpmath import mp

    def build():
        A, b, c = _lobatto_iiia(s)
        B = mp.matrix([[b[j] * (1 - A[j, i] / b[i]) for j in range(s)]
                       for i in range(s)])
        return B, b, c

    return _tableau("lobatto3b", s, build)


def splitting_to_prk(drift: Sequence, kick: Sequence) -> tuple:
    """PRK (A_q, b, A_p, b) of the splitting drift(a1) kick(b1) drift(a2)...

    The sequence x = (a1, b1, a2, b2, ...) is rewritten as the composition
    Phi_{c1} Phi*_{c2} Phi_{c3} ... (applied left to right) of symplectic
    Euler Phi_c (drift then kick: 1-stage PRK A_q = 1, A_p = 0) and its
    adjoint Phi*_c (kick then drift: A_q = 0, A_p = 1), with c1 = x1,
    c_k = x_k - c_{k-1}.  Stacking the stages gives a PRK with b_q = b_p = c,
    A_q[k,l] = A_p[k,l] = c_l (l < k), and c_k on the diagonal of A_q (Phi)
    or A_p (Phi*).  It is symplectic for every H and equals the splitting
    for separable H; velocity Verlet (0, 1/2, 1, 1/2) gives exactly 2-stage
    Lobatto IIIA (q) - IIIB (p).  Zero-weight pieces are dropped.
    """
    from mpmath import mp

    pieces = _euler_pieces(drift, kick)
    s = len(pieces)
    A_q, A_p = mp.matrix(s, s), mp.matrix(s, s)
    for k, (ck, is_phi) in enumerate(pieces):
        for m in range(k):
            A_q[k, m] = A_p[k, m] = pieces[m][0]
        (A_q if is_phi else A_p)[k, k] = ck
    b = [pc[0] for pc in pieces]
    return A_q, b, A_p, list(b)


#: Relative tolerance of ``sum(drift) = sum(kick)`` for a splitting's PRK form: the float
#: path's (``RESIDUAL_TOL`` in :mod:`stepsafe.methods.tableaux`, kept equal by the tests).
#: The coefficients are float64 values or decimals computed at some precision, so their
#: sums agree only to that rounding, whatever the precision the reference works at.
SUM_TOL = 1e-12


def _euler_pieces(drift: Sequence, kick: Sequence) -> list[tuple]:
    """The pieces (c_k, is_phi) of :func:`splitting_to_prk`, zero weights dropped.

    The sums must agree to :data:`SUM_TOL` relative to the size of the coefficients (else
    ValueError: no PRK form); a difference within it is taken as the float path takes it
    (:meth:`stepsafe.methods.tableaux.Splitting.euler_factors`): the last drift becomes
    ``sum(kick)`` minus the other drifts. (The pieces after the last kick, Phi_e then
    Phi*_-e = Phi_e^-1 with e the difference, are the identity and are dropped; a splitting
    that ends with a kick keeps a trailing drift of the difference, as the float path.)"""
    from mpmath import mp

    x = [mp.mpf(v) for pair in zip_longest(drift, kick, fillvalue=0) for v in pair]
    size = max(mp.fsum(abs(v) for v in x[0::2]), mp.fsum(abs(v) for v in x[1::2]))
    mismatch = abs(mp.fsum(x[0::2]) - mp.fsum(x[1::2]))
    if not mismatch <= SUM_TOL * size:
        raise ValueError(f"inconsistent splitting: sum(drift) - sum(kick) = "
                         f"{mp.nstr(mismatch, 3)}: no PRK form")
    pieces, prev = [], mp.zero
    for k, xk in enumerate(x):
        ck = xk - prev
        pieces.append((ck, k % 2 == 0))  # True: Phi (drift-kick)
        prev = ck
    if x and x[-1] == 0:  # Phi_e Phi*_-e: the identity (see above)
        pieces = pieces[:-2]
    return [pc for pc in pieces if pc[0] != 0]


def _solve(A: list, rhs: list) -> list:
    """Solve A X = rhs (lists of rows) by Gaussian elimination with partial pivoting at
    the working precision (forward substitution when A is lower triangular, as the stage
    systems of splittings are); raises ZeroDivisionError if A is singular."""
    from mpmath import mp

    n, m = len(A), len(rhs[0])
    if all(A[i][j] == 0 for i in range(n) for j in range(i + 1, n)):
        return _forward_substitution(A, rhs)
    W = [list(A[i]) + list(rhs[i]) for i in range(n)]
    for k in range(n):
        piv = max(range(k, n), key=lambda i: abs(W[i][k]))
        if W[piv][k] == 0:
            raise ZeroDivisionError("singular stage system")
        W[k], W[piv] = W[piv], W[k]
        row = W[k]
        inv = 1 / row[k]
        for i in range(k + 1, n):
            f = W[i][k] * inv
            if f:
                Wi = W[i]
                for j in range(k + 1, n + m):
                    Wi[j] -= f * row[j]
    X = [[mp.zero] * m for _ in range(n)]
    for i in range(n - 1, -1, -1):
        for c in range(m):
            acc = W[i][n + c] - mp.fsum(W[i][j] * X[j][c] for j in range(i + 1, n))
            X[i][c] = acc / W[i][i]
    return X


def _forward_substitution(L: list, rhs: list) -> list:
    """Solve L X = rhs for lower-triangular L (lists of rows)."""
    from mpmath import mp

    n, m = len(L), len(rhs[0])
    X: list = []
    for i in range(n):
        if L[i][i] == 0:
            raise ZeroDivisionError("singular stage system")
        X.append([(rhs[i][c] - mp.fsum(L[i][j] * X[j][c] for j in range(i))) / L[i][i]
                  for c in range(m)])
    return X


def _rows_of(A) -> list:
    from mpmath import mp

    A = mp.matrix(A)
    return [[A[i, j] for j in range(A.cols)] for i in range(A.rows)]


def transfer_matrix_prk(A_q, b_q, A_p, b_p, z, model: str):
    """M(z) of the PRK (A_q,b_q)-(A_p,b_p) on ``model`` (see :func:`prk_transfer`)."""
    return prk_transfer(A_q, b_q, A_p, b_p)(z, model)


def _hessenberg(K: list, vectors: list) -> tuple:
    """Householder reduction ``K = Q H Q^T`` (``Q`` orthogonal, ``H`` upper Hessenberg,
    exact zeros below its subdiagonal), once per matrix: returns ``H`` (rows) and
    ``Q^T v`` for each of ``vectors`` (``Q`` itself is never formed)."""
    from mpmath import mp

    n = len(K)
    H = [list(row) for row in K]
    out = [list(v) for v in vectors]
    for k in range(n - 2):
        x = [H[i][k] for i in range(k + 1, n)]
        norm = mp.sqrt(mp.fsum(t * t for t in x))
        if norm == 0:
            continue
        v = list(x)
        v[0] += norm if x[0] >= 0 else -norm  # v = x + sign(x_0) |x| e_1: no cancellation
        scale = 2 / mp.fsum(t * t for t in v)
        rows = range(k + 1, n)
        for j in range(n):  # H <- P H (rows k+1..n-1)
            f = scale * mp.fsum(v[i] * H[r][j] for i, r in enumerate(rows))
            if f:
                for i, r in enumerate(rows):
                    H[r][j] -= f * v[i]
        for row in H:  # H <- H P (columns k+1..n-1)
            f = scale * mp.fsum(v[i] * row[r] for i, r in enumerate(rows))
            if f:
                for i, r in enumerate(rows):
                    row[r] -= f * v[i]
        for w in out:  # w <- P w, so that w ends as Q^T w (Q = P_0 P_1 ...)
            f = scale * mp.fsum(v[i] * w[r] for i, r in enumerate(rows))
            for i, r in enumerate(rows):
                w[r] -= f * v[i]
        for r in range(k + 2, n):
            H[r][k] = mp.zero
    return H, out


def _hessenberg_solve(c, H: list, rhs: list) -> list:
    """``y`` with ``(I - c H) y = r`` for each ``r`` in ``rhs``, ``H`` upper Hessenberg:
    Gaussian elimination with partial pivoting between neighbouring rows (the only
    candidates), O(s^2); ZeroDivisionError if the matrix is singular."""
    from mpmath import mp

    n = len(H)
    T = [[(1 if i == j else 0) - c * H[i][j] if j >= i - 1 else mp.zero for j in range(n)]
         for i in range(n)]
    R = [[r[i] for r in rhs] for i in range(n)]
    for k in range(n - 1):
        if abs(T[k + 1][k]) > abs(T[k][k]):
            T[k], T[k + 1] = T[k + 1], T[k]
            R[k], R[k + 1] = R[k + 1], R[k]
        if T[k][k] == 0:
            raise ZeroDivisionError("singular stage system")
        f = T[k + 1][k] / T[k][k]
        if f:
            row, below = T[k], T[k + 1]
            for j in range(k + 1, n):
                below[j] -= f * row[j]
            R[k + 1] = [a - f * b for a, b in zip(R[k + 1], R[k])]
        T[k + 1][k] = mp.zero
    if T[n - 1][n - 1] == 0:
        raise ZeroDivisionError("singular stage system")
    Y = [[mp.zero] * len(rhs) for _ in range(n)]
    for i in range(n - 1, -1, -1):
        for col in range(len(rhs)):
            acc = R[i][col] - mp.fsum(T[i][j] * Y[j][col] for j in range(i + 1, n))
            Y[i][col] = acc / T[i][i]
    return [[Y[i][col] for i in range(n)] for col in range(len(rhs))]


def _lower_triangular(K: list) -> bool:
    return all(K[i][j] == 0 for i in range(len(K)) for j in range(i + 1, len(K)))


def prk_transfer(A_q, b_q, A_p, b_p) -> Callable:
    """``Mfun(z, model)`` of the PRK (A_q,b_q)-(A_p,b_p): the stage system
    Q = q0 e + z A_q (Lqq Q + Lqp P), P = p0 e + z A_p (Lpq Q + Lpp P), solved for
    (q0, p0) = (1, 0) and (0, 1); then q1 = q0 + z b_q.(Lqq Q + Lqp P),
    p1 = p0 + z b_p.(Lpq Q + Lpp P). Every model here has Lqq = Lpp = 0 or
    Lqp = Lpq = 0, so only s x s systems are solved:

    * Lqq = Lpp = 0: with ``K = A_q A_p``, ``c = z^2 Lqp Lpq`` and ``S = I - c K``,
      ``Q = S^-1 (q0 e + z Lqp p0 A_q e)``, ``P = p0 e + z Lpq A_p Q``, so
      ``M = [[1 + c g(A_p^T b_q, e), z Lqp (sum b_q + c g(A_p^T b_q, A_q e))],
      [z Lpq g(b_p, e), 1 + c g(b_p, A_q e)]]`` with ``g(u, v) = u^T S^-1 v``;
    * Lqp = Lpq = 0: ``M = diag(1 + z Lqq g_q(b_q, e), 1 + z Lpp g_p(b_p, e))``,
      ``g_q(u, v) = u^T (I - z Lqq A_q)^-1 v`` and ``g_p`` alike with ``A_p``.

    Each ``g`` is ``(Q^T u)^T (I - c H)^-1 (Q^T v)`` for the Householder form ``K = Q H
    Q^T`` (H upper Hessenberg), computed once per working precision, so that each z costs
    O(s^2) instead of a dense O(s^3) solve; a lower-triangular K (explicit methods) is
    solved by forward substitution. ``Mfun`` raises ZeroDivisionError where the stage
    system is singular (a pole)."""
    from mpmath import mp

    Aq, Ap = _rows_of(A_q), _rows_of(A_p)
    s = len(Aq)
    b_q, b_p = list(b_q), list(b_p)
    eye = [[mp.one if i == j else mp.zero for j in range(s)] for i in range(s)]
    ones = [mp.one] * s
    forms: dict[tuple[int, str], Any] = {}

    def form(key: str):
        """Per working precision: ``("triangular", K, ...)`` or ``("hessenberg", H, the
        vectors Q^T u, Q^T v)`` for K = A_q A_p (``off``), A_q or A_p (``q``, ``p``)."""
        if (mp.prec, key) in forms:
            return forms[(mp.prec, key)]
        rq = [mp.fsum(row) for row in Aq]  # A_q e
        if key == "off":
            K = [[mp.fsum(Aq[i][k] * Ap[k][j] for k in range(s)) for j in range(s)]
                 for i in range(s)]
            left = [mp.fsum(Ap[k][j] * b_q[k] for k in range(s)) for j in range(s)]
            vectors = [left, b_p, ones, rq]  # u: A_p^T b_q, b_p; v: e, A_q e
        else:
            K = Aq if key == "q" else Ap
            vectors = [b_q if key == "q" else b_p, ones]
        if _lower_triangular(K):
            out = ("triangular", K, vectors)
        else:
            out = ("hessenberg", *_hessenberg(K, vectors))
        forms[(mp.prec, key)] = out
        return out

    def g(key: str, c, pairs: list) -> list:
        """``u^T (I - c K)^-1 v`` for each ``(u, v)`` index pair into the form's vectors."""
        how, K, vectors = form(key)
        rhs = sorted({v for _, v in pairs})
        if how == "triangular":
            Y = _forward_substitution([[eye[i][j] - c * K[i][j] for j in range(s)]
                                       for i in range(s)],
                                      [[vectors[v][i] for v in rhs] for i in range(s)])
            Y = [[Y[i][col] for i in range(s)] for col in range(len(rhs))]
        else:
            Y = _hessenberg_solve(c, K, [vectors[v] for v in rhs])
        return [mp.fsum(a * b for a, b in zip(vectors[u], Y[rhs.index(v)])) for u, v in pairs]

    def Mfun(z, model: str):
        (lqq, lqp), (lpq, lpp) = MODELS[model]
        z = mp.mpf(z)
        M = mp.matrix(2, 2)
        if lqq == 0 and lpp == 0:
            c = z * z * lqp * lpq
            qe, qr, pe, pr = g("off", c, [(0, 2), (0, 3), (1, 2), (1, 3)])
            M[0, 0] = 1 + c * qe
            M[0, 1] = z * lqp * (mp.fsum(b_q) + c * qr)
            M[1, 0] = z * lpq * pe
            M[1, 1] = 1 + c * pr
        else:
            M[0, 0] = 1 + z * lqq * g("q", z * lqq, [(0, 1)])[0]
            M[1, 1] = 1 + z * lpp * g("p", z * lpp, [(0, 1)])[0]
        return M

    return Mfun


def transfer_matrix_rk(A, b, z, model: str):
    """RK method = PRK with both tableaux equal."""
    return transfer_matrix_prk(A, b, A, b, z, model)


def transfer_matrix_splitting(drift: Sequence, kick: Sequence, z,
                              model: str, gradient: Sequence | None = None):
    """Splitting drift(a1 z) kick(b1 z) drift(a2 z) ... : product of
    [[1, a z],[0, 1]] and [[1, 0],[-+b z, 1]] (oscillator -, inverted +), applied to the
    rows of M as scalars; on the saddle through the equivalent PRK (see splitting_to_prk).

    ``gradient`` (force-gradient methods, one c_i per kick): kick i is
    p -= b_i h V'(q) - c_i h^3 d/dq (V'(q)^2); with V = +-q^2/2 (scaled) that adds
    +2 c_i z^3 q to p on either model. Force-gradient methods have no saddle form."""
    from mpmath import mp

    if model in ("saddle", "saddle-p"):
        if gradient is not None and any(gradient):
            raise ValueError("a force-gradient splitting has no form for the saddle")
        return _diagonal_splitting(drift, kick, z, model)
    sign = -1 if model == "oscillator" else 1
    z = mp.mpf(z)
    grads = list(gradient) if gradient is not None else [0] * len(kick)
    z3 = z ** 3 if any(grads) else mp.zero
    a, b, c, d = mp.one, mp.zero, mp.zero, mp.one  # rows (a, b) for q and (c, d) for p
    for x, y, w in zip_longest(drift, kick, grads, fillvalue=0):
        if x:
            t = x * z
            a, b = a + t * c, b + t * d
        if y or w:
            t = sign * y * z + 2 * w * z3 if w else sign * y * z
            c, d = c + t * a, d + t * b
    return mp.matrix([[a, b], [c, d]])


def _diagonal_splitting(drift: Sequence, kick: Sequence, z, model: str):
    """The PRK of :func:`splitting_to_prk` on a diagonal model (q' = lqq q, p' = lpp p):
    q and p decouple, and each symplectic Euler piece Phi_c is implicit Euler in q and
    explicit Euler in p (Phi*_c the reverse), so M = diag(prod r_q, prod r_p) with
    r = 1/(1 - z l c) (implicit) or 1 + z l c (explicit).  Raises ZeroDivisionError at a
    pole (1 - z l c = 0)."""
    from mpmath import mp

    (lqq, _), (_, lpp) = MODELS[model]
    z = mp.mpf(z)
    rq = rp = mp.one
    for c, is_phi in _euler_pieces(drift, kick):
        implicit, explicit = (lqq, lpp) if is_phi else (lpp, lqq)
        den = 1 - z * implicit * c
        if den == 0:
            raise ZeroDivisionError("singular stage system")
        r_impl, r_expl = 1 / den, 1 + z * explicit * c
        if is_phi:
            rq, rp = rq * r_impl, rp * r_expl
        else:
            rq, rp = rq * r_expl, rp * r_impl
    return mp.matrix([[rq, mp.zero], [mp.zero, rp]])


def langevin_substeps(letters: str) -> list[tuple[str, Any]]:
    """A Langevin splitting's word as ``(letter, fraction of the step)``: each letter's
    substep is the step over the number of times the letter occurs."""
    from mpmath import mp

    return [(ch, mp.one / letters.count(ch)) for ch in letters]


def transfer_matrix_langevin(letters: str, friction, z, model: str = "oscillator"):
    """The map of the mean of a Langevin splitting on the oscillator (z = omega h, friction
    per unit of frequency): ``A_t = [[1, t z], [0, 1]]``, ``B_t = [[1, 0], [-t z, 1]]``,
    ``O_t = diag(1, exp(-friction t z))``, multiplied in the word's order."""
    from mpmath import mp

    if model != "oscillator":
        raise ValueError("a Langevin splitting's mean map is analysed on the oscillator only")
    z = mp.mpf(z)
    M = mp.eye(2)
    for ch, t in langevin_substeps(letters):
        if ch == "A":
            F = mp.matrix([[1, t * z], [0, 1]])
        elif ch == "B":
            F = mp.matrix([[1, 0], [-t * z, 1]])
        else:
            F = mp.matrix([[1, 0], [0, mp.exp(-mp.mpf(friction) * t * z)]])
        M = F * M
    return M


def langevin_hamiltonian_part(letters: str) -> tuple[list, list]:
    """``(drift, kick)`` of the drifts and kicks of a Langevin splitting's word taken in
    cyclic order from the end of its run of O letters (the O letters dropped): the
    symplectic map X with ``tr M = tr(diag(1, c) X)``."""
    from mpmath import mp

    n = len(letters)
    end = next(i for i in range(n) if letters[i] == "O" and letters[(i + 1) % n] != "O")
    steps = langevin_substeps(letters)
    ops = [steps[(end + 1 + k) % n] for k in range(n)]
    drift: list = [mp.zero]  # drift(a_1) kick(b_1) drift(a_2) ...: one more drift than kicks
    kick: list = []
    for ch, t in ops:
        if ch == "A":
            drift[-1] += t
        elif ch == "B":
            kick.append(t)
            drift.append(mp.zero)
    return drift, kick


def transfer_matrix_composition(base_fn: MFun, weights: Sequence, z):
    """Phi_{g_k h} o ... o Phi_{g_1 h}: M = M_base(g_k z) ... M_base(g_1 z)."""
    from mpmath import mp

    M = mp.eye(2)
    for g in weights:
        M = base_fn(g * z) * M
    return M


def triple_jump(order: int) -> list:
    """Weights (g1, g2, g1) raising a symmetric method of even ``order`` to
    order+2: g1 = 1/(2 - 2^(1/(order+1))), g2 = -2^(1/(order+1)) g1
    (so 2 g1 + g2 = 1; g2 < 0)."""
    from mpmath import mp

    r = mp.root(2, order + 1)
    g1 = 1 / (2 - r)
    return [g1, -r * g1, g1]


# ------------------------------------------------------------ method files at high precision


class MPMethod(NamedTuple):
    kind: str  # "prk", "splitting", "composition", "processed", "langevin"
    order: int | None
    data: dict[str, Any]


def _rows(A) -> list[list]:
    from mpmath import mp

    if isinstance(A, mp.matrix):
        return [[A[i, j] for j in range(A.cols)] for i in range(A.rows)]
    return [list(r) for r in A]


@lru_cache(maxsize=64)
def mp_method(name: str, stages: int | None = None, base: str | None = None,
              dps: int = HIGH_PRECISION_DIGITS) -> MPMethod:
    """The method at ``dps`` digits (resolved as by
    :func:`stepsafe.methods.library.resolve`)."""
    from mpmath import mp

    with mp.workdps(dps):
        if name in FAMILIES:
            assert stages is not None  # (a family is resolved with its stages)
            if name == "gauss":
                A, b, _ = gauss_tableau(stages)
                A, b = _rows(A), list(b)
                out = MPMethod("prk", 2 * stages, {"A_q": A, "b_q": b, "A_p": A, "b_p": b})
            else:
                A, b, _ = lobatto_IIIA_tableau(stages)
                B, _, _ = lobatto_IIIB_tableau(stages)
                out = MPMethod("prk", 2 * stages - 2, {"A_q": _rows(A), "b_q": list(b),
                                                       "A_p": _rows(B), "b_p": list(b)})
        else:
            data = load_file(_find_file(name), backend=mpmath_backend())
            co = dict(data.coefficients)
            if data.kind == "composition":
                ref = data.base
                folder = Path(data.where).parent
                ref_name = ref if isinstance(ref, str) else ref["name"]
                if _looks_like_path(ref_name) and not Path(ref_name).is_absolute():
                    ref_name = str(folder / ref_name)
                inner = mp_method(ref_name, None if isinstance(ref, str) else ref.get("stages"),
                                  dps=dps)
                if data.recipe:
                    assert inner.order is not None  # (a recipe's base states its order)
                    co["weights"] = _recipe_weights(data.recipe, inner.order)
                out = MPMethod("composition", data.order, {"base": inner,
                                                           "weights": co["weights"]})
            elif data.kind == "processed":
                folder = Path(data.where).parent

                def part(ref):
                    if isinstance(ref, dict) and "drift" in ref:
                        return MPMethod("splitting", None, dict(ref))
                    ref_name = ref if isinstance(ref, str) else ref["name"]
                    if _looks_like_path(ref_name) and not Path(ref_name).is_absolute():
                        ref_name = str(folder / ref_name)
                    return mp_method(ref_name, None if isinstance(ref, str)
                                     else ref.get("stages"), dps=dps)

                out = MPMethod("processed", data.order,
                               {"kernel": part(data.extras["kernel"]),
                                "processor": part(data.extras["processor"])})
            elif data.kind == "langevin":
                out = MPMethod("langevin", data.order, dict(data.extras))
            elif data.kind in ("rk", "prk"):
                if data.kind == "rk":
                    co = {"A_q": co["A"], "b_q": co["b"], "A_p": co["A"], "b_p": co["b"]}
                out = MPMethod("prk", data.order, co)
            else:
                if "gradient" in co:  # how integrations evaluate the force-gradient kick
                    co["displaced"] = data.extras.get("gradient_form") == "displaced-force"
                out = MPMethod("splitting", data.order, co)
        if base is not None:
            if out.kind != "composition":
                raise ValueError("--base applies to compositions")
            bname, _, bstages = base.partition(":")
            out = MPMethod("composition", None, {
                "base": mp_method(bname, int(bstages) if bstages else None, dps=dps),
                "weights": out.data["weights"]})
    return out


def _recipe_weights(recipe: str, base_order: int) -> list:
    from mpmath import mp

    k = base_order + 1
    if recipe == "triple-jump":
        g1 = 1 / (2 - mp.root(2, k))
        return [g1, -mp.root(2, k) * g1, g1]
    p = 1 / (4 - mp.root(4, k))
    return [p, p, 1 - 4 * p, p, p]


def mp_transfer(m: MPMethod) -> Callable:
    """``Mfun(z, model)``: the mpmath transfer matrix of ``m``."""
    from mpmath import mp

    if m.kind == "langevin":  # the map of the mean
        letters, friction = m.data["letters"], m.data["friction"]
        return lambda z, model: transfer_matrix_langevin(letters, friction, z, model)
    if m.kind == "processed":  # the full one-step map P^-1 K P (the kernel's trace)
        drift, kick = mp_processed_splitting(m)
        kernel = mp_transfer(m.data["kernel"])
        # on the diagonal models every drift and kick is a diagonal matrix, so P commutes
        # with K and P^-1 K P = K exactly (as the float analysis takes it); merging P's
        # factors into the kernel's, as for the other models, would change the implicit
        # Euler factors there
        return lambda z, model: (kernel(z, model) if model in ("saddle", "saddle-p") else
                                 transfer_matrix_splitting(drift, kick, z, model))
    if m.kind == "composition" and m.data["base"].kind == "splitting" \
            and "gradient" not in m.data["base"].data:
        # a composition of a splitting is a splitting: one pass of scalar updates (its
        # coefficients multiplied out once per working precision)
        flat: dict[int, tuple[list, list]] = {}

        def composed(z, model: str):
            if mp.prec not in flat:
                flat[mp.prec] = _flat_splitting(m.data["weights"],
                                                m.data["base"].data["drift"],
                                                m.data["base"].data["kick"])
            return transfer_matrix_splitting(*flat[mp.prec], z, model)

        return composed
    if m.kind == "composition":
        inner = mp_transfer(m.data["base"])
        weights = m.data["weights"]
        return lambda z, model: transfer_matrix_composition(
            lambda x: inner(x, model), weights, z)
    if m.kind == "splitting":
        d, k, g = m.data["drift"], m.data["kick"], m.data.get("gradient")
        return lambda z, model: transfer_matrix_splitting(d, k, z, model, g)
    return prk_transfer(*(m.data[key] for key in ("A_q", "b_q", "A_p", "b_p")))


def _operations(m: MPMethod, scale=1) -> list[list]:
    """``[kind, coefficient]`` of a splitting or of a composition of one, in order."""
    if m.kind == "composition":
        return [op for g in m.data["weights"] for op in _operations(m.data["base"], g * scale)]
    if m.kind != "splitting":
        raise ValueError("a processed method's kernel and processor are splittings")
    out = []
    for i, a in enumerate(m.data["drift"]):
        out.append(["drift", scale * a])
        if i < len(m.data["kick"]):
            out.append(["kick", scale * m.data["kick"][i]])
    return out


def mp_processed_splitting(m: MPMethod) -> tuple[list, list]:
    """drift/kick lists of the one-step map ``P^-1 K P`` of a processed method: P's
    operations, the kernel's, then P's reversed with negated coefficients. The merged
    coefficients are summed at 512 bits or more, whatever the caller's precision, so that
    the sums stay those of the coefficients (exact for decimals read at up to 150 digits)."""
    from mpmath import mp

    with mp.workprec(max(mp.prec, 512)):
        return _processed_splitting(m)


def _processed_splitting(m: MPMethod) -> tuple[list, list]:
    pre = _operations(m.data["processor"])
    ops = pre + _operations(m.data["kernel"]) + [[k, -c] for k, c in reversed(pre)]
    drift: list = []
    kick: list = []
    for kind, c in ops:
        if kind == "drift":
            if len(drift) > len(kick):
                drift[-1] += c
            else:
                drift.append(c)
        elif len(drift) == len(kick):
            if kick:
                kick[-1] += c
            else:
                drift.append(0)
                kick.append(c)
        else:
            kick.append(c)
    return drift, kick


def _flat_splitting(weights, drift, kick) -> tuple[list, list]:
    """drift/kick lists of ``weights`` applied to a splitting, with the drifts that meet
    across substeps added (the sequence alternates drift, kick, drift, ...)."""
    ops: list[list] = []  # [kind, coefficient], alternating
    for g in weights:
        for i, a in enumerate(drift):
            for kind, c in (("d", a), ("k", kick[i] if i < len(kick) else None)):
                if c is None:
                    continue
                if ops and ops[-1][0] == kind:
                    ops[-1][1] += g * c
                else:
                    ops.append([kind, g * c])
    if ops and ops[0][0] == "k":
        ops.insert(0, ["d", 0])
    return [c for k, c in ops if k == "d"], [c for k, c in ops if k == "k"]


# ------------------------------------------------------- a method's own exact definition


def family_tableaux(family: str, s: int) -> tuple[Any, Any, Any, Any]:
    """``(A_q, b_q, A_p, b_p)`` of a Gauss or Lobatto IIIA-IIIB family member at the working
    mpmath precision (nodes and weights computed at that precision)."""
    if family == "gauss":
        A, b, _ = gauss_tableau(s)
        return A, b, A, b
    A, b, _ = lobatto_IIIA_tableau(s)
    B, _, _ = lobatto_IIIB_tableau(s)
    return A, b, B, b


@lru_cache(maxsize=16)
def _family_matrix(family: str, s: int) -> Callable[[Any, str], Any]:
    """The family member's transfer matrix, its tableau computed at raised precision (not
    rounded to float64)."""
    from mpmath import mp

    with mp.workdps(HIGH_PRECISION_DIGITS + 10):
        return prk_transfer(*family_tableaux(family, s))


def defined(exact: Exact) -> Callable[[Any, str], Any]:
    """``Mfun(z, model)`` of a method's own definition: a family member's tableau at raised
    precision, or the method file (with its base swapped where ``exact.base`` says so) read
    at :data:`~stepsafe.methods.protocol.HIGH_PRECISION_DIGITS` digits."""
    if exact.source == "family":
        assert exact.stages is not None  # (a family member has its stage count)
        return _family_matrix(exact.name, exact.stages)
    return mp_transfer(mp_method(exact.name, exact.stages, exact.base, HIGH_PRECISION_DIGITS))


def high_precision_tableaux(prk: PartitionedRK) -> tuple[list, list, list, list]:
    """``(A_q, b_q, A_p, b_p)`` as mpmath numbers at the working precision: a Gauss or
    Lobatto family member's tableau computed at that precision, a library file's decimals
    read exactly, else the float coefficients taken as exact."""
    from mpmath import mp

    def rows(A):
        return [[A[i, j] for j in range(A.cols)] for i in range(A.rows)] \
            if isinstance(A, mp.matrix) else [list(r) for r in A]

    ex = prk.exact
    if ex is not None and ex.source == "family":
        assert ex.stages is not None  # (a family member has its stage count)
        A_q, b_q, A_p, b_p = family_tableaux(ex.name, ex.stages)
        return rows(A_q), list(b_q), rows(A_p), list(b_p)
    if ex is not None:
        m = mp_method(ex.name, ex.stages, ex.base, dps=mp.dps)
        if m.kind == "prk" and len(m.data["b_q"]) == prk.stages:
            d = m.data
            return rows(d["A_q"]), list(d["b_q"]), rows(d["A_p"]), list(d["b_p"])
    return ([[mp.mpf(float(x)) for x in r] for r in prk.A_q], [mp.mpf(float(x)) for x in prk.b_q],
            [[mp.mpf(float(x)) for x in r] for r in prk.A_p], [mp.mpf(float(x)) for x in prk.b_p])


# ------------------------------------------------------------- the matrix of each kind


def high_precision(method: MethodKind) -> Callable[[Any, str], Any]:
    """``Mfun(z, model)``: the transfer matrix of ``method`` at z (an mpf) as an mpmath
    matrix, from its own definition when it has one (:func:`defined`), else from its parts,
    the float coefficients taken as exact: a (partitioned) Runge-Kutta method's stage
    equations solved; a splitting's drifts and kicks multiplied; a composition's base at
    ``g_k z`` multiplied; a processed method's per-step map; a Langevin splitting's mean map
    (its A/B runs' splitting matrices and ``diag(1, exp(-gamma w z))`` for each O,
    multiplied in order). An impulse method has no single-force matrix: refused."""
    if method.exact is not None:
        return defined(method.exact)
    if isinstance(method, RungeKutta):
        method = method.as_prk()
    if isinstance(method, PartitionedRK):
        return prk_transfer(method.A_q.tolist(), method.b_q.tolist(), method.A_p.tolist(),
                            method.b_p.tolist())
    if isinstance(method, Splitting):
        drift, kick = method.drift.tolist(), method.kick.tolist()
        gradient = None if method.gradient is None else method.gradient.tolist()
        return lambda z, model: transfer_matrix_splitting(drift, kick, z, model, gradient)
    if isinstance(method, Composition):
        inner = high_precision(method.base)
        weights = [float(g) for g in method.weights]
        return lambda z, model: transfer_matrix_composition(lambda x: inner(x, model),
                                                            weights, z)
    if isinstance(method, Processed):
        return high_precision(method.per_step())
    if isinstance(method, Langevin):
        return _mean_map(method)
    if isinstance(method, Impulse):
        raise method._two_forces()
    raise TypeError(f"no high-precision transfer matrix for a {type(method).__name__}")


def _mean_map(method: Langevin) -> Callable[[Any, str], Any]:
    from mpmath import mp

    parts: list[tuple[Any, Any, float | None]] = []
    for block in method.decomposition():
        if isinstance(block, Shears):
            s = block.splitting
            parts.append((s.drift.tolist(), s.kick.tolist(), None))
        else:
            assert isinstance(block, Friction)
            parts.append((None, None, block.weight * block.gamma))

    def mean_map(z, model: str):
        M = mp.eye(2)
        for drift, kick, k in parts:
            if k is None:
                F = transfer_matrix_splitting(drift, kick, z, model)
            else:
                F = mp.matrix([[1, 0], [0, mp.exp(-mp.mpf(k) * z)]])
            M = F * M
        return M

    return mean_map

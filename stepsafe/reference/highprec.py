"""Independent high-precision (mpmath) reference for stepsafe (``--verify`` and the tests).

Shares no code with the float64 path. The methods' transfer matrices in mpmath (stage
equations solved, drifts and kicks multiplied, family tableaux at raised precision) are
those of :mod:`stepsafe.methods.exact`, which the core's escalation also uses, and are
importable from here; this module adds what the reference decides with them: the test
models' constraints, roots, poles, boundaries and regions. Every function works at the
caller's precision (``with mp.workdps(60): ...``).

Conventions: phase space x = (q, p); a method applied to x' = L x with step z
(z = beta*h) is the linear map x1 = M(z) x0.  Test models (L):

* ``oscillator`` q' = p, p' = -q: preserved iff |tr M| < 2 and M[0,1] > 0
  (elliptic with the rotation sense of the flow);
* ``saddle``     q' = q, p' = -p: preserved iff M is diagonal and
  M_qq > 1 > M_pp > 0;
* ``inverted``   q' = p, p' = q: preserved iff tr M > 2 and the expanding
  eigenvector v of M has v_q*v_p > 0.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

from stepsafe.methods.exact import (  # noqa: F401 (importable from here too)
    MODELS,
    SUM_TOL,
    MFun,
    _euler_pieces,
    gauss_tableau,
    langevin_hamiltonian_part,
    langevin_substeps,
    lobatto_IIIA_tableau,
    lobatto_IIIB_tableau,
    prk_transfer,
    splitting_to_prk,
    transfer_matrix_composition,
    transfer_matrix_langevin,
    transfer_matrix_prk,
    transfer_matrix_rk,
    transfer_matrix_splitting,
    triple_jump,
)

#: names of the functions g_k(M) that are all > 0 exactly when preserved
CONSTRAINT_NAMES = {
    "oscillator": ("2-tr", "2+tr", "M_qp"),
    "saddle": ("M_qq-1", "1-M_pp", "M_pp"),
    "inverted": ("tr-2", "orientation"),
    "elliptic": ("2-tr", "2+tr"),  # pseudo-model: |tr M| < 2, any sense
}
#: constraints that may touch zero tangentially (|tr M| = 2 resonances)
_TANGENT = {"oscillator": (0, 1), "saddle": (0,), "inverted": (0,),
            "elliptic": (0, 1)}


def constraints(M, model: str) -> list:
    """Continuous functions g_k(M), all > 0 iff preserved (CONSTRAINT_NAMES).
    Inverted orientation: with mu = tr/2 + sqrt(tr^2/4 - 1) the expanding
    eigenvector is v ~ (M_qp, mu - M_qq) ~ (mu - M_pp, M_pq), so
    M_qp (mu - M_qq) + M_pq (mu - M_pp) has the sign of v_q v_p.
    Pseudo-model 'elliptic': |tr M| < 2 only (islands of either sense)."""
    from mpmath import mp

    tr = M[0, 0] + M[1, 1]
    if model == "oscillator":
        return [2 - tr, 2 + tr, M[0, 1]]
    if model == "elliptic":
        return [2 - tr, 2 + tr]
    if model == "saddle":
        return [M[0, 0] - 1, 1 - M[1, 1], M[1, 1]]
    mu = tr / 2 + mp.sqrt(max(tr * tr / 4 - 1, 0))
    return [tr - 2, M[0, 1] * (mu - M[0, 0]) + M[1, 0] * (mu - M[1, 1])]


def is_preserved(M, model: str) -> bool:
    """True iff M is symplectic (det M = 1 to rounding; otherwise a centre
    becomes a spiral) and has the type and orientation of the flow."""
    from mpmath import mp

    tol = mp.eps * 2 ** 20
    scale = abs(M[0, 0] * M[1, 1]) + abs(M[0, 1] * M[1, 0])
    if abs(mp.det(M) - 1) > tol * scale:
        return False
    if model == "saddle" and abs(M[0, 1]) + abs(M[1, 0]) > tol:
        return False
    return all(g > 0 for g in constraints(M, model))


def classify(M) -> str:
    """Type of a 2x2 symplectic M: 'elliptic+' / 'elliptic-' (sign of M_qp =
    rotation sense), 'hyperbolic+' (tr > 2), 'hyperbolic-' (tr < -2, flip)."""
    tr = M[0, 0] + M[1, 1]
    if abs(tr) < 2:
        return "elliptic+" if M[0, 1] > 0 else "elliptic-"
    return "hyperbolic+" if tr > 2 else "hyperbolic-"


def refine_root(f: Callable, lo, hi, tol=None):
    """Zero (or sign-changing pole) of f in [lo, hi], f(lo) f(hi) < 0.

    Illinois (modified regula falsi) safeguarded by a bisection step
    whenever three steps failed to halve the bracket; stops at a bracket
    width ~ 64 ulp (about mp.dps digits).  A point where f raises
    ZeroDivisionError is returned at once (an exact pole)."""
    from mpmath import mp

    a, b = mp.mpf(lo), mp.mpf(hi)
    fa, fb = f(a), f(b)
    if fa == 0 or fb == 0:
        return a if fa == 0 else b
    if (fa > 0) == (fb > 0):
        raise ValueError("refine_root: no sign change on [lo, hi]")
    tol = tol or mp.eps * 2 ** 6 * max(1, abs(a), abs(b))
    side, width, bisect = 0, b - a, False
    for it in range(1, 20 * mp.prec):
        if b - a <= tol:
            break
        c = (a + b) / 2 if bisect else (a * fb - b * fa) / (fb - fa)
        if not a < c < b:
            c = (a + b) / 2
        try:
            fc = f(c)
        except ZeroDivisionError:
            return c
        if fc == 0:
            return c
        if (fc > 0) == (fa > 0):
            a, fa = c, fc
            fb, side = (fb / 2 if side == -1 else fb), -1
        else:
            b, fb = c, fc
            fa, side = (fa / 2 if side == 1 else fa), 1
        bisect = False
        if it % 3 == 0:
            bisect, width = b - a > width / 2, b - a
    return (a + b) / 2


def locate_pole(inv: Callable, lo, hi, tol=None):
    """The pole of ``tr M`` in ``[lo, hi]`` given ``inv(z) = 1 / tr M(z)`` (0 where the stage
    system is exactly singular), or None.  An odd pole is a sign change of ``inv``, refined
    by :func:`refine_root`; an even one (a double eigenvalue of the stage operator) is a
    zero of ``|inv|`` without a sign change, found by golden-section search and accepted
    when ``|inv|`` there is below ``10^(-dps/2)`` of its value at the nearer end (near a
    double pole ``|inv|`` falls like the square of the distance; a finite peak of
    ``tr M`` does not take it to zero)."""
    from mpmath import mp

    a, b = mp.mpf(lo), mp.mpf(hi)
    fa, fb = inv(a), inv(b)
    if fa == 0 or fb == 0:
        return a if fa == 0 else b
    if (fa > 0) != (fb > 0):
        return refine_root(inv, a, b, tol)
    ratio = (mp.sqrt(5) - 1) / 2
    c, d = b - ratio * (b - a), a + ratio * (b - a)
    fc, fd = abs(inv(c)), abs(inv(d))
    for _ in range(2 * mp.prec):
        if fc == 0 or fd == 0:
            return c if fc == 0 else d
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - ratio * (b - a)
            fc = abs(inv(c))
        else:
            a, c, fc = c, d, fd
            d = a + ratio * (b - a)
            fd = abs(inv(d))
        if b - a <= (tol or mp.eps * 2 ** 6 * max(1, abs(b))):
            break
    x, fx = (c, fc) if fc < fd else (d, fd)
    return x if fx <= mp.mpf(10) ** (-(mp.dps // 2)) * min(abs(fa), abs(fb)) else None


def _g(Mfun: MFun, model: str, k: int) -> Callable:
    return lambda z: constraints(Mfun(z), model)[k]


def _crossing_kind(g: Callable, x) -> str:
    """'root' if |g| is small next to x, 'pole' if it blows up."""
    from mpmath import mp

    d = mp.mpf(10) ** (-(mp.dps // 2)) * max(1, abs(x))
    try:
        vals = [abs(g(x - d)), abs(g(x + d))]
    except ZeroDivisionError:
        return "pole"
    return "root" if min(vals) < 1 else "pole"


def _tangency(g: Callable, lo, hi):
    """Local minimum of |g| in (lo, hi) via a root of g'; returns
    [(z, kind)] for a double zero ('resonance'), two crossings (a narrow
    gap whose extremum has the opposite sign), or [] (no contact)."""
    from mpmath import mp

    dg = lambda z: mp.diff(g, z)  # noqa: E731
    try:
        if (dg(lo) > 0) == (dg(hi) > 0):
            return []
        zm = refine_root(dg, lo, hi)
        gm, glo = g(zm), g(lo)
    except ZeroDivisionError:
        return []
    if abs(gm) < mp.mpf(10) ** (-(3 * mp.dps) // 4):
        return [(zm, "resonance")]
    if (gm > 0) != (glo > 0):
        return [(refine_root(g, lo, zm), "root"),
                (refine_root(g, zm, hi), "root")]
    return []


class Boundary(NamedTuple):
    z: object          # mp number
    kind: str          # 'root', 'pole' or 'resonance'
    which: str         # constraint(s) that vanish/blow up there
    preserved_before: bool
    preserved_after: bool


def _safe_M(Mfun: MFun, z, step):
    for _ in range(5):
        try:
            return z, Mfun(z)
        except ZeroDivisionError:
            z += step
    return z, None


def boundaries(Mfun: MFun, model: str, zmax, n: int = 400) -> list:
    """All boundaries of the preserved set in (0, zmax] (list of Boundary).

    Scan: constraints g_k(M(z)) on the float grid z_i = zmax i/n (mp
    evaluation); sign changes are refined with refine_root and labelled
    root/pole (pole: |g| blows up, stage system singular); grid local minima
    of |2 -+ tr| are refined through g' = 0 into resonances (tangency) or
    narrow gaps (two roots).  Candidates where the preservation status does
    not change are dropped, except poles and isolated resonances."""
    from mpmath import mp

    zmax = mp.mpf(zmax)
    step = zmax / n * mp.mpf("1e-7")
    grid = [_safe_M(Mfun, zmax * i / n, step) for i in range(1, n + 1)]
    grid = [(z, constraints(M, model)) for z, M in grid if M is not None]
    names = CONSTRAINT_NAMES[model]
    cand = []
    for k in range(len(names)):
        g = _g(Mfun, model, k)
        for (z0, v0), (z1, v1) in zip(grid, grid[1:]):
            if (v0[k] > 0) != (v1[k] > 0):
                x = refine_root(g, z0, z1)
                cand.append((x, _crossing_kind(g, x), names[k]))
        if k not in _TANGENT[model]:
            continue
        for (z0, v0), (_, v1), (z2, v2) in zip(grid, grid[1:], grid[2:]):
            same = (v0[k] > 0) == (v1[k] > 0) == (v2[k] > 0)
            if same and abs(v1[k]) < min(abs(v0[k]), abs(v2[k])):
                cand += [(x, kd, names[k]) for x, kd in _tangency(g, z0, z2)]
    cand.sort(key=lambda t: t[0])
    merged: list = []
    for x, kind, name in cand:
        if merged and abs(x - merged[-1][0]) < mp.eps ** 0.3 * max(1, x):
            _, k0, n0 = merged[-1]
            best = min((k0, kind), key=("pole", "resonance", "root").index)
            merged[-1] = (merged[-1][0], best, n0 + "," + name)
        else:
            merged.append((x, kind, name))
    pts = [m[0] for m in merged]
    mids = [min(pts[0] / 2, grid[0][0])] if pts else [zmax / 2]
    mids += [(u + v) / 2 for u, v in zip(pts, pts[1:])]
    mids += [(pts[-1] + zmax) / 2] if pts else []
    status = [_safe_M(Mfun, m, step)[1] for m in mids]
    status = [M is not None and is_preserved(M, model) for M in status]
    out = []
    for i, (x, kind, name) in enumerate(merged):
        before, after = status[i], status[i + 1]
        if before != after or (kind != "root" and (before or after)):
            out.append(Boundary(x, kind, name, before, after))
    return out


def _start(Mfun: MFun, model: str, zmax, bds: list) -> bool:
    from mpmath import mp

    if bds:
        return bds[0].preserved_before
    M = _safe_M(Mfun, mp.mpf(zmax) / 2, mp.mpf(zmax) * 1e-9)[1]
    return M is not None and is_preserved(M, model)


def first_boundary(Mfun: MFun, model: str, zmax, n: int = 400) -> tuple:
    """(z*, kind) ending the preserved interval that starts at z = 0+;
    (mp.inf, 'none') if none up to zmax; (0, 'never') if not preserved
    for small z (e.g. a non-symplectic method)."""
    from mpmath import mp

    bds = boundaries(Mfun, model, zmax, n)
    if not _start(Mfun, model, zmax, bds):
        return mp.zero, "never"
    return (bds[0].z, bds[0].kind) if bds else (mp.inf, "none")


def regions(Mfun: MFun, model: str, zmax, n: int = 400) -> list:
    """Preserved open intervals [(lo, hi)] in (0, zmax] (hi = zmax: open);
    an isolated resonance splits an interval in two."""
    from mpmath import mp

    bds = boundaries(Mfun, model, zmax, n)
    out, lo = [], (mp.zero if _start(Mfun, model, zmax, bds) else None)
    for bd in bds:
        if lo is not None:
            out.append((lo, bd.z))
        lo = bd.z if bd.preserved_after else None
    if lo is not None:
        out.append((lo, mp.mpf(zmax)))
    return out


def resonances(Mfun: MFun, zmax, n: int = 400) -> list:
    """Points where |tr M| = 2 tangentially (e.g. M = -I): [(z, M(z))].
    Uses the oscillator constraints 2 - tr, 2 + tr (model independent)."""
    from mpmath import mp

    zmax = mp.mpf(zmax)
    grid = [_safe_M(Mfun, zmax * i / n, zmax / n * 1e-7)
            for i in range(1, n + 1)]
    grid = [(z, M) for z, M in grid if M is not None]
    out = []
    for k in (0, 1):
        g = _g(Mfun, "oscillator", k)
        vals = [(z, constraints(M, "oscillator")[k]) for z, M in grid]
        for (z0, v0), (_, v1), (z2, v2) in zip(vals, vals[1:], vals[2:]):
            if 0 < v1 < min(v0, v2):
                out += [(x, Mfun(x)) for x, kd in _tangency(g, z0, z2)
                        if kd == "resonance"]
    return sorted(out, key=lambda t: t[0])

"""Small helpers shared by the tests (the tests folder is on sys.path)."""

from __future__ import annotations

from stepsafe.methods.library import resolve


def method(name: str, stages: int | None = None, base: str | None = None):
    """A method object by CLI name."""
    return resolve(name, stages, base)[0]


def respa_mp(fast, slow, k, H):
    """One r-RESPA outer step on (q, p) at the working mpmath precision, written out
    independently of stepsafe: K_slow(H/2) [K_fast(h/2) D(h) K_fast(h/2)]^k K_slow(H/2),
    h = H/k (Omega = fast, omega = slow)."""
    import mpmath as mp

    F, S, H = mp.mpf(fast) ** 2, mp.mpf(slow) ** 2, mp.mpf(H)

    def kick(c):
        return mp.matrix([[1, 0], [-c, 1]])

    def drift(c):
        return mp.matrix([[1, c], [0, 1]])

    h = H / k
    inner = kick(F * h / 2) * drift(h) * kick(F * h / 2)
    return kick(S * H / 2) * inner ** k * kick(S * H / 2)


def respa_stable_mp(fast, slow, k, H) -> bool:
    """|tr M| < 2 for that step, at 50 digits."""
    import mpmath as mp

    with mp.workdps(50):
        M = respa_mp(fast, slow, k, H)
        return bool(abs(M[0, 0] + M[1, 1]) < 2)

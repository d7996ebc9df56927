"""Invariants of the transfer matrix over every shipped method (one parametrised test)."""

from __future__ import annotations

import numpy as np
import pytest
from support import method

from stepsafe.core.models import MODELS
from stepsafe.core.transfer import has_form, poles, transfer_jet, transfer_matrix
from stepsafe.methods.families import gauss, lobatto3ab
from stepsafe.methods.library import builtin_names
from stepsafe.methods.residuals import residuals
from stepsafe.methods.tableaux import PartitionedRK, Splitting

LIBRARY = [n for n in builtin_names(single_force=True) if n not in ("gauss", "lobatto3ab")]
FAMILY = [gauss(s) for s in (1, 2, 3, 5, 8)] + [lobatto3ab(s) for s in (2, 3, 4, 6, 9)]
Z = np.concatenate([np.linspace(0.01, 1.5, 40), np.linspace(1.5, 6, 40)])


def _all_methods():
    return [method(n) for n in LIBRARY] + FAMILY


@pytest.mark.parametrize("m", _all_methods(), ids=lambda m: m.name)
def test_det_is_one_for_symplectic_methods(m):
    res = residuals(m)
    for model in MODELS:
        if not has_form(m, model) or not res.symplectic_for(model):
            continue
        z = Z[np.all(np.abs(Z[:, None] - poles(m, model)[None, :]) > 1e-3, axis=1)]
        M = transfer_matrix(m, z, model)
        det = np.linalg.det(M)
        scale = np.abs(M).max(axis=(1, 2)) ** 2
        assert np.all(np.abs(det - 1) <= 1e-11 * np.maximum(scale, 1)), (model, det)


@pytest.mark.parametrize("m", _all_methods(), ids=lambda m: m.name)
def test_derivatives_match_finite_differences(m):
    """dM/dz against central differences of M, d2M/dz2 against those of dM/dz."""
    z = np.array([0.3, 0.9, 1.7])
    for model in MODELS:
        if not has_form(m, model):
            continue
        if np.any(np.abs(z[:, None] - poles(m, model)[None, :]) < 1e-2):
            continue
        jet = transfer_jet(m, z, model, order=2)
        for h, value, derivative, rtol in ((1e-6, "M", jet.dM, 1e-6), (1e-5, "dM", jet.d2M, 1e-5)):
            fd = (getattr(transfer_jet(m, z + h, model), value)
                  - getattr(transfer_jet(m, z - h, model), value)) / (2 * h)
            np.testing.assert_allclose(derivative, fd, rtol=rtol,
                                       atol=rtol * max(np.abs(derivative).max(), 1.0))
        assert np.isnan(transfer_jet(m, z, model, order=1).d2M).all() or model.startswith("sad")


@pytest.mark.parametrize("name", ["verlet", "pefrl", "yoshida4", "symplectic-euler"])
def test_splitting_products_equal_prk_form(name):
    """The drift/kick product and the method's PRK form (b_q = b_p) give the same M."""
    m = method(name)
    base = m if isinstance(m, Splitting) else m.flattened().base
    prk = base.as_prk()
    assert isinstance(prk, PartitionedRK)
    for model in ("oscillator", "inverted", "saddle"):
        np.testing.assert_allclose(transfer_matrix(base, Z, model), transfer_matrix(prk, Z, model),
                                   rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("s", [2, 3, 4, 5, 8])
def test_both_lobatto_orderings_agree(s):
    """IIIA for q / IIIB for p and the swapped pair have the same oscillator trace."""
    ab = lobatto3ab(s)
    ba = PartitionedRK(ab.A_p, ab.b_p, ab.A_q, ab.b_q)
    for model in ("oscillator", "inverted"):
        ta = np.trace(transfer_matrix(ab, Z, model), axis1=1, axis2=2)
        tb = np.trace(transfer_matrix(ba, Z, model), axis1=1, axis2=2)
        np.testing.assert_allclose(ta, tb, rtol=1e-11, atol=1e-11)


def test_saddle_matrix_is_diagonal_for_partitioned_methods():
    for m in (method("pefrl"), lobatto3ab(4), method("yoshida4")):
        M = transfer_matrix(m, Z[:20], "saddle")
        assert np.all(M[:, 0, 1] == 0) and np.all(M[:, 1, 0] == 0)


def test_singular_stage_system_gives_nan_not_an_exception():
    M = transfer_matrix(method("midpoint"), np.array([1.0, 2.0, 3.0]), "saddle")
    assert np.all(np.isfinite(M[0])) and np.all(np.isnan(M[1])) and np.all(np.isfinite(M[2]))


def test_composition_with_weight_one_is_the_base():
    from stepsafe.methods.tableaux import Composition

    base = method("pefrl")
    comp = Composition(base, [1.0])
    for model in MODELS:
        np.testing.assert_array_equal(transfer_matrix(comp, Z, model),
                                      transfer_matrix(base, Z, model))

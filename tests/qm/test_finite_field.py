"""Finite-field polarizabilities (emlpack.qm.finite_field) with a stand-in labeler whose dipole
is exactly linear and quadratic in the field: the central differences, the base field, the
per-field cache and its check."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from emlpack.qm.finite_field import FiniteFieldError, finite_field_response
from emlpack.units import FIELD_AU_IN_V_PER_A

ALPHA = np.array([[0.4, 0.05, 0.0], [0.05, 0.5, -0.02], [0.0, -0.02, 0.6]])  # e·Å²/V
BETA = 0.3  # 1/(V/Å): the polarizability changes with the field


class Dipoles:
    """``mu(F) = mu0 + ALPHA F + BETA (ALPHA F) F_x``: d mu / dF at F0 depends on F0."""

    def __init__(self) -> None:
        self.calls = []

    def __call__(self, numbers, positions, field, charge=0.0, forces=False, localize=True):
        f = np.asarray(field, float)
        self.calls.append(f)
        mu = np.array([0.1, -0.2, 0.3]) + ALPHA @ f + BETA * (ALPHA @ f) * f[0]
        return SimpleNamespace(ok=True, error="", dipole=mu, forces=None)


def test_polarizability_about_zero_and_about_a_base_field(tmp_path):
    numbers, positions = np.array([1, 1]), np.array([[0, 0, 0], [0, 0, 0.74]])
    labeler = Dipoles()
    zero = finite_field_response(labeler, numbers, positions, step_au=1e-3)
    np.testing.assert_allclose(zero.polarizability, ALPHA, rtol=1e-8)
    base = np.array([0.2, 0.0, -0.1])  # V/Å
    resp = finite_field_response(labeler, numbers, positions, step_au=1e-3,
                                 cache=tmp_path / "c", base_field=base)
    # d mu_i / dF_j at base: ALPHA (1 + BETA F0_x) + BETA (ALPHA F0)_i delta_jx (symmetrised)
    exact = ALPHA * (1 + BETA * base[0])
    exact[:, 0] += BETA * ALPHA @ base
    np.testing.assert_allclose(resp.polarizability, 0.5 * (exact + exact.T), rtol=1e-7)
    h = 1e-3 * FIELD_AU_IN_V_PER_A
    np.testing.assert_allclose(labeler.calls[6], base + [h, 0, 0])
    n = len(labeler.calls)
    again = finite_field_response(labeler, numbers, positions, step_au=1e-3,
                                  cache=tmp_path / "c", base_field=base)
    assert len(labeler.calls) == n  # every field read from its file
    np.testing.assert_array_equal(again.polarizability, resp.polarizability)
    with pytest.raises(FiniteFieldError, match="field_x\\+.npz: computed at field"):
        finite_field_response(labeler, numbers, positions, step_au=1e-3,
                              cache=tmp_path / "c")  # same files, other base field

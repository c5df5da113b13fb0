"""The extended Hessian (positions or fractional coordinates, cell, field) of
emlpack.properties.response against the model's forces/virial and finite differences of the
gradient, for every registered short-range family."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from emlpack.properties.hessian import extended_hessian
from tests.nn.helpers import (
    FAMILIES,
    STENCIL_OFFSETS,
    STENCIL_WEIGHTS,
    all_forces,
    ammonium,
    glycine,
    kink_gap,
    random_model,
    water_crystal,
)

FIELD = np.array([0.2, -0.3, 0.25])


def gradients_at(model, structure, xs: np.ndarray) -> np.ndarray:
    """Gradients of the energy in the extended variables at the points ``xs`` (M, n_var),
    by autograd through ``model.energy`` with the topology of ``structure`` frozen."""
    m = len(xs)
    n = structure.n_cores + structure.n_pairs
    g = model.graph([structure] * m)
    x = torch.as_tensor(xs, dtype=torch.float64).requires_grad_(True)
    if structure.pbc:
        cell = x[:, 3 * n : 3 * n + 9].reshape(m, 3, 3)
        pos = torch.bmm(x[:, : 3 * n].reshape(m, n, 3), cell).reshape(-1, 3)
        energy = model.energy(g, pos, cell, x[:, 3 * n + 9 :])
    else:
        energy = model.energy(g, x[:, : 3 * n].reshape(-1, 3), None, x[:, 3 * n :])
    return torch.autograd.grad(energy.sum(), x)[0].numpy()


def _x0_and_gradient(model, s):
    """Extended variables of ``s`` and the gradient built from the model's forces, virial and
    dipole (independent of emlpack.properties.response)."""
    out = model.evaluate(s, stress=s.pbc)
    forces = all_forces(out)
    mu = s.dipole()
    if s.pbc:
        frac = s.all_positions @ np.linalg.inv(s.cell)
        x0 = np.concatenate([frac.ravel(), s.cell.ravel(), s.field])
        d_frac = -forces @ s.cell.T  # dE/ds = dE/dr . cell^T
        d_cell = np.linalg.inv(s.cell).T @ out["virial_including_field"]
        grad = np.concatenate([d_frac.ravel(), d_cell.ravel(), -mu])
    else:
        x0 = np.concatenate([s.all_positions.ravel(), s.field])
        grad = np.concatenate([-forces.ravel(), -mu])
    return x0, grad


def _fd_rows(model, s, x0, rows, steps):
    xs = []
    for r, h in zip(rows, steps, strict=True):
        for o in STENCIL_OFFSETS:
            x = x0.copy()
            x[r] += o * h
            xs.append(x)
    grads = gradients_at(model, s, np.array(xs)).reshape(len(rows), 4, -1)
    return np.einsum("rkv,k->rv", grads, STENCIL_WEIGHTS) / np.asarray(steps)[:, None]


@pytest.mark.parametrize("family", FAMILIES)
def test_molecule_extended_hessian(family):
    model = random_model(family=family)
    s = ammonium(FIELD)
    n = s.n_cores + s.n_pairs
    grad, hess = (t.numpy() for t in extended_hessian(model, s))
    x0, grad_ref = _x0_and_gradient(model, s)
    assert hess.shape == (3 * n + 3, 3 * n + 3)
    np.testing.assert_allclose(grad, grad_ref, atol=1e-11)
    np.testing.assert_allclose(hess, hess.T, atol=1e-10)
    # every row by finite differences of the gradient
    rows = list(range(3 * n + 3))
    h = min(1e-4, kink_gap(model, s) / 4)
    fd = _fd_rows(model, s, x0, rows, [h] * len(rows))
    scale = np.abs(hess).max()
    assert scale > 10
    np.testing.assert_allclose(hess, fd, atol=1e-8 * scale)
    # position-field block: d2E/dr_ia dE_b = -q_i delta_ab; field-field block: 0
    expected = -np.kron(s.charges[:, None], np.eye(3))
    np.testing.assert_allclose(hess[: 3 * n, 3 * n :], expected, atol=1e-12)
    np.testing.assert_allclose(hess[3 * n :, 3 * n :], 0.0, atol=1e-12)


CRYSTALS = {
    "water_crystal_field": lambda: water_crystal(FIELD),
    "glycine_p3": lambda: glycine("p3"),
}


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("name", list(CRYSTALS))
def test_crystal_extended_hessian(name, family):
    model = random_model(family=family)
    s = CRYSTALS[name]()
    n = s.n_cores + s.n_pairs
    grad, hess = (t.numpy() for t in extended_hessian(model, s))
    x0, grad_ref = _x0_and_gradient(model, s)
    assert hess.shape == (3 * n + 12, 3 * n + 12)
    np.testing.assert_allclose(grad, grad_ref, atol=1e-10 * max(1.0, np.abs(grad_ref).max()))
    np.testing.assert_allclose(hess, hess.T, atol=1e-9 * np.abs(hess).max())
    # selected rows: two particles (a core and a pair), all cell components, the field
    frac_rows = [3 * 1 + a for a in range(3)] + [3 * (s.n_cores + 2) + a for a in range(3)]
    cell_rows = [3 * n + k for k in range(9)]
    field_rows = [3 * n + 9 + a for a in range(3)]
    gap = kink_gap(model, s)
    extent = np.abs(x0[: 3 * n]).max() + 1.0  # |s| bound: a cell change moves r by s . dcell
    h_frac = min(1e-5, gap / (4 * np.linalg.norm(s.cell, axis=1).max()))
    h_cell = min(1e-5, gap / (4 * np.sqrt(3) * extent))
    rows = frac_rows + cell_rows + field_rows
    steps = [h_frac] * len(frac_rows) + [h_cell] * len(cell_rows) + [1e-3] * len(field_rows)
    fd = _fd_rows(model, s, x0, rows, steps)
    for label, sel in (("frac", frac_rows), ("cell", cell_rows), ("field", field_rows)):
        idx = [rows.index(r) for r in sel]
        block, ref = hess[sel], fd[idx]
        scale = np.abs(block).max()
        assert scale > 0.1, label
        np.testing.assert_allclose(block, ref, atol=2e-7 * scale, err_msg=label)
    # field rows exactly: d2E/dE_a ds_ib = -q_i cell_ba; d2E/dE dE = 0
    field_frac = hess[3 * n + 9 :, : 3 * n].reshape(3, n, 3)
    expected = -s.charges[None, :, None] * s.cell.T[:, None, :]
    np.testing.assert_allclose(field_frac, expected, atol=1e-10)
    np.testing.assert_allclose(hess[3 * n + 9 :, 3 * n + 9 :], 0.0, atol=1e-12)

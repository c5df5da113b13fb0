"""ModelLabeler (an eMLP as a labeler) and the Born-Oppenheimer (core positions, cell) Hessian
used to sample crystals from a model."""

from __future__ import annotations

import numpy as np
import pytest

from emlpack.calculators.labeler import ModelLabeler, bo_cell_hessian
from tests.nn.helpers import water_crystal
from tests.properties.toy import spring_model


@pytest.fixture(scope="module")
def setup():
    s = water_crystal()
    return spring_model(s, core_cutoff=3.5, pair_cutoff=2.0), s


def test_labeler_relaxes_pairs_and_labels(setup):
    model, s = setup
    out = ModelLabeler(model, fmax=1e-8)(s, stress=True)
    assert np.abs(model.evaluate(out)["pair_forces"]).max() < 1e-7
    np.testing.assert_allclose(out.forces.sum(axis=0), 0.0, atol=1e-8)  # neutral, no field
    assert out.stress.shape == (3, 3) and out.energy is not None
    with pytest.raises(ValueError, match="stress under a field"):
        ModelLabeler(model)(s.copy(field=np.array([0.0, 0.0, 0.01])), stress=True)


def test_bo_hessian_is_minus_derivative_of_bo_forces(setup):
    """Core-core block = -dF_BO/dR (pairs relaxed at every displaced geometry); translations of
    all cores are zero modes."""
    model, s = setup
    h = bo_cell_hessian(model, s, fmax=1e-10)
    nc = s.n_cores
    assert h.shape == (3 * nc + 9, 3 * nc + 9)
    np.testing.assert_allclose(h, h.T, atol=1e-8)
    trans = np.concatenate([np.tile([1.0, 0.0, 0.0], nc), np.zeros(9)])
    assert np.abs(h @ trans).max() < 1e-6 * np.abs(h).max()
    lab = ModelLabeler(model, fmax=1e-10)
    step = 1e-4
    for k in (0, 4, 3 * nc - 1):
        forces = []
        for sign in (1.0, -1.0):
            pos = s.positions.copy()
            pos.flat[k] += sign * step
            forces.append(lab(s.copy(positions=pos)).forces.reshape(-1))
        column = -(forces[0] - forces[1]) / (2 * step)
        np.testing.assert_allclose(h[: 3 * nc, k], column, atol=1e-5 * np.abs(h).max())


def test_the_callers_model_is_neither_converted_nor_switched_to_eval(setup):
    import copy

    import torch

    model, s = setup
    m32 = copy.deepcopy(model).float().train()
    lab = ModelLabeler(m32, fmax=1e-6)
    assert lab.model is not m32 and next(lab.model.parameters()).dtype == torch.float64
    assert not lab.model.training
    bo_cell_hessian(m32, s, fmax=1e-6)
    assert next(m32.parameters()).dtype == torch.float32 and m32.training
    m64 = copy.deepcopy(model).double().eval()
    assert ModelLabeler(m64).model is m64  # already float64 and in eval mode: no copy

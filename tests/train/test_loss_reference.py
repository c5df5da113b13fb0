"""The paper's loss and the live hydride reference (gradients flow through the hydrides)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from emlpack.data.dataset import make_batch
from emlpack.data.references import (
    ConstantReference,
    HydrideReference,
    HydrideReferenceError,
    hydride_coefficients,
    load_hydrides,
    reference_from_metadata,
)
from emlpack.io import read_structures
from emlpack.nn import EMLP, ModelConfig
from emlpack.train.loss import LossWeights, Metrics, combine, loss_terms, predict
from tests.conftest import shared_path

SMALL = ModelConfig(short_range={"n_features": 16, "n_filters": 8, "n_rbf": 8, "n_interactions": 2})


@pytest.fixture(scope="module")
def hydrides():
    return HydrideReference(*load_hydrides(shared_path("data/hydrides")))


@pytest.fixture(scope="module")
def frames():
    return read_structures(shared_path("data/eqm7_pbe0_subset.xyz"), index="::120")


def test_hydride_coefficients_balance_cores_and_pairs():
    # ethanol C2H6O = 2 CH4 + H2O - 2 H2
    np.testing.assert_allclose(hydride_coefficients(np.array([6, 6, 8] + [1] * 6)),
                               [-2, 2, 0, 1])
    with pytest.raises(HydrideReferenceError, match="Z=\\[16\\]"):
        hydride_coefficients(np.array([16, 1, 1]))


def test_methane_target_matches_reference_writer(hydrides, frames):
    # reference notes §10: frame 0 target 0.2794641080 eV
    assert hydrides.target(frames[0]) == pytest.approx(0.2794641080, abs=1e-8)


def test_metadata_round_trip(hydrides):
    again = reference_from_metadata(hydrides.to_metadata())
    np.testing.assert_allclose(again.energies, hydrides.energies)
    assert reference_from_metadata(ConstantReference(-3.5).to_metadata()).value == -3.5


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_hydride_itself_has_zero_relative_energy_and_zero_gradient(hydrides, dtype):
    """CH4 labelled with the DFT CH4 energy: target 0, prediction U(CH4) - U(CH4) = 0 exactly,
    so the energy loss and its gradient vanish only because the live reference is in the graph.
    """
    torch.manual_seed(0)
    model = EMLP(SMALL).to(dtype)
    ch4 = hydrides.structures[1].copy(energy=float(hydrides.energies[1]))
    batch = make_batch([ch4], hydrides, SMALL.cutoff, SMALL.gcut, dtype)
    assert float(batch.energy[0]) == 0.0
    pred = predict(model, batch, hydrides, create_graph=True)
    assert abs(float(pred["energy"][0].detach())) < 1e-5
    e_loss = float((pred["energy"].detach() ** 2).sum())
    grads = torch.autograd.grad(pred["energy"].sum(), list(model.parameters()),
                                allow_unused=True)
    assert all(g is None or float(g.abs().max()) < 1e-4 for g in grads)
    assert e_loss < 1e-9


def test_gradient_through_live_hydrides_matches_finite_differences(hydrides, frames):
    torch.manual_seed(1)
    model = EMLP(SMALL).double()
    batch = make_batch(frames[:3], hydrides, SMALL.cutoff, SMALL.gcut, torch.float64)
    weights = LossWeights()

    def loss() -> torch.Tensor:
        return combine(loss_terms(predict(model, batch, hydrides, create_graph=True), batch),
                       weights)

    param = model.short_range.output[0].bias
    g = torch.autograd.grad(loss(), param)[0]
    k, h = 0, 1e-5
    param.data[k] += h
    up = float(loss().detach())
    param.data[k] -= 2 * h
    down = float(loss().detach())
    param.data[k] += h
    assert float(g[k]) == pytest.approx((up - down) / (2 * h), rel=1e-5, abs=1e-8)
    # and the hydrides contribute: the relative energy differs from the raw one
    pred = predict(model, batch, hydrides)
    coeff_energy = batch.coefficients @ model(batch.graph)["energy"][3:].detach()
    np.testing.assert_allclose((pred["energy_raw"] - pred["energy"]).detach().numpy(),
                               coeff_energy.numpy(), rtol=1e-10)


def test_loss_terms_follow_the_cost_function(hydrides, frames):
    torch.manual_seed(2)
    model = EMLP(SMALL).double()
    batch = make_batch(frames[:4], hydrides, SMALL.cutoff, SMALL.gcut, torch.float64)
    pred = predict(model, batch, hydrides, create_graph=False)
    w = LossWeights(energy=0.1, forces=2.0, pair_forces=3.0)
    terms = loss_terms(pred, batch)
    f = pred["forces"].detach()
    n = np.array([s.n_cores for s in frames[:4]])
    e = ((pred["energy"].detach().numpy() - batch.energy.numpy()) / n) ** 2
    core = np.concatenate([(f[:len(f)][batch.core_mask] - batch.forces[batch.core_mask]).numpy()])
    pair = (f[batch.pair_mask] - batch.forces[batch.pair_mask]).numpy()
    expected = 0.1 * e.mean() + 2.0 * (core**2).mean() + 3.0 * (pair**2).mean()
    assert float(combine(terms, w).detach()) == pytest.approx(expected, rel=1e-10)
    m = Metrics()
    m.update(pred, batch)
    assert m.loss(w) == pytest.approx(expected, rel=1e-10)
    assert m.result()["forces_mae"] == pytest.approx(np.abs(core).mean())

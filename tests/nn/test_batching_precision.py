"""Batching without padding reproduces one-by-one results; float32 agrees with float64."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from tests.nn.helpers import (
    ammonium,
    glycine,
    hydroxide,
    methane,
    random_model,
    water_crystal,
    water_molecule,
)

FIELD = np.array([0.2, -0.1, 0.3])


def _mixed(with_glycine: bool):
    structures = [
        methane(FIELD),
        water_crystal(FIELD),
        ammonium(FIELD),
        water_molecule(),
        water_crystal(),
        hydroxide(-FIELD),
    ]
    if with_glycine:
        structures.insert(2, glycine("p3"))
        structures.append(glycine("p1"))
    return structures


@pytest.mark.parametrize("with_glycine", [False, True])
def test_batch_equals_one_by_one(with_glycine):
    model = random_model()
    structures = _mixed(with_glycine)
    g = model.graph(structures)
    out = {k: v.detach() for k, v in model(g, forces=True, stress=True).items()}
    forces = g.split(out["forces"])
    atomic = g.split(out["atomic_energies"])
    for b, s in enumerate(structures):
        single = model.evaluate(s, stress=True)
        for key in ("energy", "energy_short_range", "energy_long_range", "energy_field"):
            assert float(out[key][b]) == pytest.approx(single[key], abs=1e-12), (b, key)
        np.testing.assert_allclose(forces[b][: s.n_cores].numpy(), single["forces"], atol=1e-12)
        np.testing.assert_allclose(
            forces[b][s.n_cores :].numpy(), single["pair_forces"], atol=1e-12
        )
        np.testing.assert_allclose(atomic[b].numpy(), single["atomic_energies"], atol=1e-12)
        np.testing.assert_allclose(
            out["virial_including_field"][b].numpy(), single["virial_including_field"],
            atol=1e-12,
        )
        if s.pbc:
            np.testing.assert_allclose(out["stress"][b].numpy(), single["stress"], atol=1e-13)


def test_batch_order_does_not_matter():
    model = random_model()
    structures = _mixed(False)
    order = [3, 0, 5, 1, 4, 2]
    e1 = model(model.graph(structures), forces=False)["energy"].detach().numpy()
    e2 = model(model.graph([structures[i] for i in order]), forces=False)["energy"]
    np.testing.assert_allclose(e2.detach().numpy(), e1[order], atol=1e-12)


@pytest.mark.parametrize("with_glycine", [False, True])
def test_float32_agrees_with_float64(with_glycine):
    m64 = random_model()
    m32 = copy.deepcopy(m64).to(torch.float32)
    structures = _mixed(with_glycine)
    g64 = m64.graph(structures)
    g32 = m32.graph(structures)
    assert g32.positions.dtype == torch.float32
    o64 = {k: v.detach() for k, v in m64(g64, stress=True).items()}
    o32 = {k: v.detach() for k, v in m32(g32, stress=True).items()}
    assert o32["energy"].dtype == torch.float32
    e64, e32 = o64["energy"].numpy(), o32["energy"].numpy().astype(np.float64)
    # energies 10-100 eV: float32 resolution ~1e-6 relative
    np.testing.assert_allclose(e32, e64, rtol=2e-6, atol=1e-4)
    f64, f32 = o64["forces"].numpy(), o32["forces"].numpy()
    np.testing.assert_allclose(f32, f64, atol=2e-4 * max(1.0, np.abs(f64).max()))
    np.testing.assert_allclose(o32["stress"].numpy(), o64["stress"].numpy(), atol=1e-5)
    assert np.abs(e32 - e64).max() > 0  # really computed in single precision


def test_a_subgraph_is_the_batch_of_its_structures():
    """``Graph.subgraph(keep)``: the kept structures' particles, edges, Coulomb pairs and k
    vectors, renumbered; its energies and forces are those of a batch of only them."""
    model = random_model()
    structures = _mixed(False)
    keep = torch.tensor([k % 2 == 0 for k in range(len(structures))])
    sub = model.graph(structures).subgraph(keep)
    alone = model.graph([s for s, k in zip(structures, keep, strict=True) if k])
    for name in ("numbers", "batch", "edge_i", "edge_j", "coulomb_i", "kvec_n", "n_pairs"):
        assert torch.equal(getattr(sub, name), getattr(alone, name)), name
    a, b = model(sub), model(alone)
    torch.testing.assert_close(a["energy"], b["energy"], rtol=0, atol=1e-12)
    torch.testing.assert_close(a["forces"], b["forces"], rtol=0, atol=1e-12)

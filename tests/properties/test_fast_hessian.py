"""The fast extended Hessian (default ``method="fast"``) against today's reference method
(reverse over reverse through the whole energy), and its closed-form pieces against autograd:
Taylor filters, molecular Coulomb and reciprocal Ewald blocks, the node-space SchNet Hessian."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from emlpack.nn.electrostatics import (
    coulomb_molecular,
    coulomb_molecular_hessian,
    ewald_reciprocal,
    ewald_reciprocal_hessian_fractional,
)
from emlpack.nn.short_range.common import cosine_cutoff, shifted_softplus
from emlpack.properties.hessian import extended_hessian
from tests.conftest import shared_path
from tests.legacy.test_reference_fixtures import FIX, fixture_structure, load_model
from tests.nn.helpers import FAMILIES, ammonium, glycine, random_model, water_crystal

FIELD = np.array([0.2, -0.3, 0.25])


def assert_same(model, s, rtol=1e-10):
    g_ref, h_ref = extended_hessian(model, s, method="reference")
    g, h = extended_hessian(model, s)
    scale = h_ref.abs().max()
    assert float((h - h_ref).abs().max()) <= rtol * scale
    assert float((g - g_ref).abs().max()) <= 1e-12 * max(1.0, float(g_ref.abs().max()))
    # every block on its own scale too (SchNet-only blocks are far smaller than Coulomb's)
    n = len(h) - 3
    for rows in (slice(0, n), slice(n, None)):
        for cols in (slice(0, n), slice(n, None)):
            ref = h_ref[rows, cols]
            assert float((h[rows, cols] - ref).abs().max()) <= rtol * max(
                float(ref.abs().max()), 1e-3 * float(scale))
    return h_ref, h


CASES = {
    "ammonium_field": lambda: ammonium(FIELD),
    "water_crystal_field": lambda: water_crystal(FIELD),
    "glycine_p3": lambda: glycine("p3"),
}


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("name", list(CASES))
def test_fast_equals_reference_random_model(name, family):
    """Random weights with a short-range part comparable to the electrostatics (~1 eV/Å
    forces), every family (SchNet: closed form; others: their short range alone by reverse
    over reverse, beside the closed-form electrostatics)."""
    assert_same(random_model(family=family), CASES[name]())


def test_fast_equals_reference_fixtures():
    """The reference-fixture molecules (with field) and beta-glycine with the small model."""
    model = load_model("small")
    molecules = np.load(shared_path(FIX + "molecules_small.npz"))
    for slot in (0, 6, 8):
        assert_same(model, fixture_structure(molecules, f"c{slot:02d}_"))
    periodic = np.load(shared_path(FIX + "periodic_small.npz"))
    assert_same(model, fixture_structure(periodic, "p0_"))


def test_mixed_precision_close():
    """float32 SchNet directions: a small, bounded change of the Hessian."""
    model = random_model()
    for make in CASES.values():
        s = make()
        _, h = extended_hessian(model, s)
        _, h32 = extended_hessian(model, s, mixed=True)
        rel = float((h32 - h).abs().max() / h.abs().max())
        assert 0.0 < rel < 1e-6


def test_unknown_method():
    with pytest.raises(ValueError, match="unknown method"):
        extended_hessian(random_model(), ammonium(), method="nope")


# ---------------------------------------------------------------------- the pieces
def test_filter_taylor_matches_autograd():
    model = random_model()
    schnet = model.short_range
    r = torch.linspace(0.3, 4.2, 57, dtype=torch.float64)  # across the cutoff switch
    taylor = schnet.filter_taylor(r)
    for t, block in enumerate(schnet.interactions):
        x = r.clone().requires_grad_(True)
        w = block.filter(schnet.rbf(x), cosine_cutoff(x, schnet.cutoff, schnet.cutoff_transition))
        assert torch.allclose(taylor[t][0], w.detach(), rtol=0, atol=1e-13)
        d1 = torch.stack([torch.autograd.grad(w[:, k].sum(), x, create_graph=True)[0]
                          for k in range(w.shape[1])], 1)
        d2 = torch.stack([torch.autograd.grad(d1[:, k].sum(), x, retain_graph=True)[0]
                          for k in range(w.shape[1])], 1)
        assert torch.allclose(taylor[t][1], d1.detach(), rtol=0, atol=1e-12)
        assert torch.allclose(taylor[t][2], d2, rtol=0, atol=1e-11)
    assert shifted_softplus(torch.zeros(1)).item() == 0.0


def test_coulomb_molecular_hessian_matches_autograd():
    model = random_model()
    s = ammonium()
    g = model.graph(s)
    c = model.config

    def energy(x):
        return coulomb_molecular(x.reshape(-1, 3), g.charges, g.coulomb_i, g.coulomb_j,
                                 g.batch, ~g.pbc, 1, c.gamma, c.coulomb_eps)[0]

    ref = torch.autograd.functional.hessian(energy, g.positions.reshape(-1))
    ours = coulomb_molecular_hessian(g.positions, g.charges, g.coulomb_i, g.coulomb_j,
                                     c.gamma, c.coulomb_eps)
    assert float((ours - ref).abs().max()) < 1e-12 * float(ref.abs().max())


@pytest.mark.parametrize("make", [lambda: water_crystal(FIELD), lambda: glycine("p3")])
def test_ewald_fractional_hessian_matches_autograd(make):
    model = random_model()
    s = make()
    g = model.graph(s)
    n = g.n_particles
    cell0 = g.cell[0]
    frac0 = torch.linalg.solve(cell0.T, g.positions.T).T
    x0 = torch.cat([frac0.reshape(-1), cell0.reshape(-1)])

    def energy(x):
        cell = x[3 * n :].reshape(3, 3)
        pos = x[: 3 * n].reshape(n, 3) @ cell
        return ewald_reciprocal(pos, g.charges, g.batch, cell[None], g.kvec_n, g.kvec_batch,
                                model.config.gamma)[0]

    ref_h = torch.autograd.functional.hessian(energy, x0)
    ref_g = torch.autograd.functional.jacobian(energy, x0)
    grad, hess = ewald_reciprocal_hessian_fractional(frac0, g.charges, cell0, g.kvec_n,
                                                     model.config.gamma)
    assert float((grad - ref_g).abs().max()) < 1e-12 * float(ref_g.abs().max())
    for rows, cols in ((slice(0, 3 * n),) * 2, (slice(0, 3 * n), slice(3 * n, None)),
                       (slice(3 * n, None),) * 2):
        ref = ref_h[rows, cols]
        assert float((hess[rows, cols] - ref).abs().max()) < 1e-12 * float(ref.abs().max())


@pytest.mark.slow
def test_fast_equals_reference_benchmark_beta_glycine():
    """benchmarks/response.py's case: paper-size fixture model, beta-glycine (PBE Wannier
    centres), 162 variables (the reference method takes 15-40 s)."""
    from emlpack.io import read_structures

    model = load_model("paper")
    for p in model.parameters():
        p.requires_grad_(False)
    s = read_structures(shared_path("data/beta_glycine_pbe_wannier.xyz"))[0]
    assert_same(model, s)


def test_schnet_hessian_chunks():
    """Directions processed in several chunks give the same matrix as one chunk."""
    from emlpack.nn.short_range.hessian import edge_derivatives
    from emlpack.nn.short_range.schnet_hessian import schnet_edge_hessian

    model = random_model()
    s = water_crystal(FIELD)
    g = model.graph(s)
    cell0 = g.cell[0]
    frac0 = torch.linalg.solve(cell0.T, g.positions.T).T
    x0 = torch.cat([frac0.reshape(-1), cell0.reshape(-1)])
    r, jac, _ = edge_derivatives(model, g, x0, True)
    n_filters = model.config.short_range["n_filters"]
    with torch.no_grad():
        g1, h1 = schnet_edge_hessian(model.short_range, g.numbers, r, g.edge_i, g.edge_j, jac)
        g2, h2 = schnet_edge_hessian(model.short_range, g.numbers, r, g.edge_i, g.edge_j, jac,
                                     max_numbers=30 * n_filters * g.n_particles * 7)
    assert torch.equal(g1, g2)
    assert float((h1 - h2).abs().max()) <= 1e-13 * float(h1.abs().max())


def test_subclass_energy_uses_reference():
    """A model class with its own energy (toy springs) is differentiated as it is."""
    from tests.properties.toy import spring_model

    s = water_crystal()
    model = spring_model(s, core_cutoff=3.5, pair_cutoff=2.0)
    _, h = extended_hessian(model, s)
    _, h_ref = extended_hessian(model, s, method="reference")
    assert torch.equal(h, h_ref)

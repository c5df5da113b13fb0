"""The short-range seam: the registry, the protocol's capabilities, the model config of a
family, and what every family must satisfy (finite at a pair sitting on a core)."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch

from emlpack.nn import EMLP, ModelConfig
from emlpack.nn.potential import nest_flat_keys
from emlpack.nn.short_range import (
    FamilyError,
    FrozenAnyDtype,
    HoldsEdges,
    LengthHessian,
    ShortRange,
    TabulatesEdges,
    VectorGradient,
    build_short_range,
    families,
    family_defaults,
    register_family,
)
from emlpack.nn.short_range.schnet import SCHNET_DEFAULTS, SchNet
from emlpack.properties.hessian import extended_hessian
from emlpack.structure import Structure
from tests.nn.helpers import FAMILIES, RadialPairs, methane, random_model, water_crystal


# ---------------------------------------------------------------------- registry
def test_registry_lists_and_builds_the_families():
    assert families()[0] == "schnet" and "radial" in families()
    assert FAMILIES == families()
    assert family_defaults("schnet") == SCHNET_DEFAULTS
    # a family registered without defaults takes its constructor's keyword defaults
    assert family_defaults("radial") == {"n_features": 8, "n_hidden": 16, "norm": 10.0}
    sr = build_short_range("schnet", {"n_features": 8, "n_filters": 4}, cutoff=3.0,
                           cutoff_transition=0.7)
    assert isinstance(sr, SchNet) and sr.cutoff == 3.0 and sr.cutoff_transition == 0.7
    assert sr.embedding.weight.shape == (100, 8) and len(sr.interactions) == 4


def test_registry_refuses_unknown_families_and_parameters():
    with pytest.raises(FamilyError, match="unknown short-range family 'nope'.*schnet"):
        build_short_range("nope", {}, cutoff=4.0, cutoff_transition=0.5)
    with pytest.raises(FamilyError, match=r"'schnet' has no parameter\(s\) \['n_layers'\]"):
        ModelConfig(short_range={"n_layers": 3})
    with pytest.raises(FamilyError, match="already registered"):
        register_family("schnet", RadialPairs)
    register_family("radial", RadialPairs)  # the same class again: no change
    with pytest.raises(FamilyError, match="the model's .graph. arguments"):
        register_family("cut", RadialPairs, {"cutoff": 3.0})


def test_painn_is_registered_exactly_when_its_module_is_there():
    present = importlib.util.find_spec("emlpack.nn.short_range.painn") is not None
    assert ("painn" in families()) == present


def test_capabilities_are_found_by_method_not_class():
    schnet = random_model().short_range
    radial = random_model(family="radial").short_range
    for sr in (schnet, radial):
        assert isinstance(sr, ShortRange)
    assert isinstance(schnet, HoldsEdges) and isinstance(schnet, TabulatesEdges)
    assert isinstance(schnet, LengthHessian) and isinstance(schnet, FrozenAnyDtype)
    assert not isinstance(radial, HoldsEdges | TabulatesEdges | LengthHessian | FrozenAnyDtype)
    assert isinstance(random_model(family="painn").short_range, VectorGradient)
    assert not isinstance(radial, VectorGradient) and not isinstance(schnet, VectorGradient)
    model = random_model(family="radial")
    g = model.graph(methane())
    with pytest.raises(TypeError, match="'radial' cannot hold edges"):
        model.hold_edges(g, torch.ones(len(g.edge_i), dtype=torch.bool))


def test_held_edges_equal_the_plain_evaluation():
    """SchNet's held core-core filters: the same energies as evaluating every edge."""
    model = random_model()
    for p in model.parameters():
        p.requires_grad_(False)
    s = water_crystal()
    g = model.graph(s)
    core_core = ~(g.is_pair[g.edge_i] | g.is_pair[g.edge_j])
    held = model.hold_edges(g, core_core)
    assert 0 < len(held.i) < len(g.edge_i) and len(held.free) == int((~core_core).sum())
    plain = model.energy_parts(g)["atomic_energies"]
    np.testing.assert_allclose(model.energy_parts(g, held=held)["atomic_energies"], plain,
                               rtol=0, atol=1e-12)
    half = held.to(torch.float32)
    assert half.filters[0].dtype == torch.float32 and torch.equal(half.i, held.i)


# ---------------------------------------------------------------------- model config
def test_version_1_flat_config_means_schnet():
    flat = {"n_features": 64, "n_filters": 32, "cutoff": 3.5, "message_norm": 10.0}
    config = ModelConfig.from_dict(flat)
    assert config.family == "schnet"
    assert config.short_range == {**SCHNET_DEFAULTS, "n_features": 64, "n_filters": 32,
                                  "message_norm": 10.0}
    assert config.cutoff == 3.5
    assert ModelConfig.from_dict(config.to_dict()) == config
    assert nest_flat_keys({"gamma": 0.3}) == {"gamma": 0.3}
    with pytest.raises(ValueError, match=r"unknown model config keys: \['n_layers'\]"):
        ModelConfig.from_dict({"n_layers": 3})
    with pytest.raises(ValueError, match="family 'radial' takes its parameters under"):
        ModelConfig.from_dict({"family": "radial", "n_features": 8})
    with pytest.raises(ValueError, match="given both"):
        ModelConfig.from_dict({"n_features": 8, "short_range": {"n_features": 16}})


@pytest.mark.parametrize("family", FAMILIES)
def test_config_round_trip_builds_the_same_model(family):
    model = random_model(family=family, cutoff=3.7, cutoff_transition=0.6, elements=(1, 8))
    config = ModelConfig.from_dict(model.config.to_dict())
    assert config == model.config and config.family == family
    again = EMLP(config).double()
    again.load_state_dict(model.state_dict())
    s = water_crystal()
    assert again.evaluate(s)["energy"] == model.evaluate(s)["energy"]
    assert model.short_range.cutoff == 3.7


# ---------------------------------------------------------------------- every family
def _pair_on_a_core(pbc: bool) -> Structure:
    """Methane with one pair exactly on the carbon and one exactly on a hydrogen."""
    s = methane()
    pairs = s.pairs.copy()
    pairs[0] = s.positions[0]
    pairs[2] = s.positions[3]
    if not pbc:
        return s.copy(pairs=pairs, field=np.array([0.1, -0.2, 0.05]))
    return s.copy(pairs=pairs, cell=6.0 * np.eye(3) + 0.3, pbc=True)


@pytest.mark.parametrize("pbc", [False, True], ids=["molecule", "crystal"])
@pytest.mark.parametrize("family", FAMILIES)
def test_a_pair_on_a_core_is_finite(family, pbc):
    """Zero-length edges (a pair sitting on a core): energy, forces, stress and the extended
    Hessian are finite for every family, and the parameter gradients (training) too."""
    model = random_model(family=family)
    s = _pair_on_a_core(pbc)
    g = model.graph(s)
    d = model.edge_vectors(g, g.positions, g.cell)
    assert int((d.norm(dim=1) == 0).sum()) == 2
    out = model.evaluate(s, stress=pbc)
    assert np.isfinite(out["energy"]) and np.all(np.isfinite(out["forces"]))
    assert np.all(np.isfinite(out["pair_forces"]))
    if pbc:
        assert np.all(np.isfinite(out["stress"]))
    grad, hess = extended_hessian(model, s)
    assert torch.isfinite(grad).all() and torch.isfinite(hess).all()
    model.train()
    result = model(g, create_graph=True)
    loss = result["energy"].sum() + (result["forces"] ** 2).sum()
    loss.backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


@pytest.mark.parametrize("family", FAMILIES)
def test_short_range_curvatures_are_the_hessian_along_the_directions(family):
    """``short_range_curvatures`` of a batch of two structures (k directions on all their
    particles) equals ``d_a^T H d_c`` with each structure's exact short-range Hessian, and
    with ``create_graph`` it is differentiable in the parameters."""
    from emlpack.nn.short_range.hessian import short_range_curvatures, short_range_hessian

    model = random_model(family=family)
    structures = [methane(), methane(seed=8)]
    g = model.graph(structures)
    directions = torch.randn(3, g.n_particles, 3, generator=torch.Generator().manual_seed(0),
                             dtype=torch.float64)
    curv = short_range_curvatures(model, g, directions, create_graph=True)
    for b, s in enumerate(structures):
        sub = model.graph(s)
        h = short_range_hessian(model, sub, sub.positions.reshape(-1), pbc=False)
        d = directions[:, g.batch == b].reshape(3, -1)
        torch.testing.assert_close(curv[b].detach(), d @ h @ d.T, rtol=1e-10, atol=1e-10)
    (grad,) = torch.autograd.grad(curv.sum(), next(model.short_range.parameters()))
    assert float(grad.abs().max()) > 0

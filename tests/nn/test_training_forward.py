"""The training forward (``EMLP.forward(parameters_only=True)``): the same values as the plain
forward, and the same parameter gradients of a force and stress loss, for every family;
SchNet's written-out length gradient and PaiNN's vector gradient against autograd."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch._dynamo.utils import counters

from emlpack.nn.graph import collate
from emlpack.nn.short_range import (
    LengthGradient,
    VectorGradient,
    common,
    painn_gradient,
    schnet_gradient,
)
from emlpack.nn.short_range.common import edge_lengths
from tests.nn.helpers import (
    FAMILY_PARAMS,
    methane,
    random_model,
    water_crystal,
    water_molecule,
)

FAMILIES = sorted(FAMILY_PARAMS)


def _loss(out: dict) -> torch.Tensor:
    loss = (out["energy"] ** 2).sum() + (out["forces"] ** 3).sum()
    if "stress" in out:
        loss = loss + 1e3 * (out["stress"] ** 2).sum()
    return loss


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("crystal", [False, True], ids=["molecules", "crystal"])
@pytest.mark.parametrize("compiled", [False, True], ids=["autograd", "written-out"])
def test_parameters_only_forward_equals_the_plain_one(family, crystal, compiled):
    """Energies, forces, stress and every parameter gradient of a loss made of them: the
    training path against the double backward through the positions (float64); with
    ``compiled`` SchNet takes its written-out length gradient and PaiNN its written-out vector
    gradient (here with torch.compile switched off: the same code, run eagerly)."""
    model = random_model(family=family).train()
    structures = [water_crystal(field=(0.01, -0.02, 0.03))] if crystal else [
        water_molecule(), methane(field=(0.02, 0.0, -0.01))]
    g = collate(structures, model.config.cutoff, model.config.gcut, torch.float64)
    params = [p for p in model.parameters() if p.requires_grad]
    plain = model(g, stress=crystal, create_graph=True)
    with torch._dynamo.config.patch(disable=True):
        fast = model(g, stress=crystal, create_graph=True, parameters_only=True,
                     compiled=compiled)
    keys = ["energy", "energy_short_range", "energy_long_range", "energy_field", "forces"]
    keys += ["stress", "virial", "virial_including_field"] if crystal else []
    for key in keys:
        np.testing.assert_allclose(fast[key].detach(), plain[key].detach(), rtol=1e-12,
                                   atol=1e-12, err_msg=key)
    g_plain = torch.autograd.grad(_loss(plain), params, allow_unused=True)
    with torch._dynamo.config.patch(disable=True):
        g_fast = torch.autograd.grad(_loss(fast), params, allow_unused=True)
    for (name, _), a, b in zip(model.named_parameters(), g_plain, g_fast, strict=True):
        if a is None:
            assert b is None or not b.any(), name
            continue
        scale = float(a.abs().max()) + 1e-30
        assert float((a - b).abs().max()) <= 1e-11 * scale, name


@pytest.mark.parametrize("family", ["schnet", "painn"])  # the written-out steps
def test_float32_training_gradients_equal_the_double_backward(family, monkeypatch):
    """Float32, the study's precision: every parameter gradient of the written-out training
    step (eager; its edge products through oneDNN, the softplus and its slope from one
    exponential) within 1e-5 relative of the double backward's (issue 49)."""
    calls = []
    spy = common._onednn_linear

    def counted(x, w):
        calls.append(x.shape)
        return spy(x, w)

    if common._ONEDNN:
        monkeypatch.setattr(common, "_onednn_linear", counted)
    model = random_model(family=family, dtype=torch.float32).train()
    g = collate([water_molecule(), methane(field=(0.02, 0.0, -0.01))], model.config.cutoff,
                model.config.gcut, torch.float32)
    params = [p for p in model.parameters() if p.requires_grad]
    old = torch.autograd.grad(_loss(model(g, create_graph=True)), params, allow_unused=True)
    with torch._dynamo.config.patch(disable=True):
        out = model(g, create_graph=True, parameters_only=True, compiled=True)
        new = torch.autograd.grad(_loss(out), params, allow_unused=True)
    assert not common._ONEDNN or calls  # the oneDNN products were taken
    for (name, _), a, b in zip(model.named_parameters(), old, new, strict=True):
        if a is None:
            assert b is None or not b.any(), name
            continue
        assert float((a - b).abs().max()) <= 1e-5 * (float(a.abs().max()) + 1e-30), name


def test_parameters_only_forces_are_not_differentiable_in_the_positions():
    """Training path outputs hold no graph to the graph's positions (only to the
    parameters): nothing there to differentiate."""
    model = random_model().train()
    g = model.graph(water_molecule())
    pos = g.positions.clone().requires_grad_(True)
    out = model(g.with_positions(pos), create_graph=True, parameters_only=True)
    assert out["forces"].requires_grad  # through the parameters
    (none,) = torch.autograd.grad(out["forces"].sum(), pos, allow_unused=True)
    assert none is None


def test_schnet_length_gradient_equals_autograd():
    """Energies and dE/dr of the written-out reverse pass against autograd (float64 to
    rounding, float32 to its precision), including a pair on a core (r ~ 1e-10 Å) and edges
    on the cosine switch."""
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 2e-5)):
        model = random_model(dtype=dtype)
        sr = model.short_range
        assert isinstance(sr, LengthGradient)
        g = model.graph(water_crystal(), dtype=dtype)
        r = edge_lengths(model.edge_vectors(g, g.positions, g.cell)).detach()
        r[0] = 1e-10
        assert bool(((r > 3.5) & (r < 4.0)).any())
        rr = r.clone().requires_grad_(True)
        e_ref = sr.energies_from_lengths(g.numbers, rr, g.edge_i, g.edge_j)
        (d_ref,) = torch.autograd.grad(e_ref.sum(), rr)
        e, d = sr.energies_and_length_gradient(g.numbers, r, g.edge_i, g.edge_j)
        np.testing.assert_allclose(e.detach(), e_ref.detach(), rtol=0,
                                   atol=tol * float(e_ref.detach().abs().max()))
        np.testing.assert_allclose(d.detach(), d_ref, rtol=0, atol=tol * float(d_ref.abs().max()))


def test_painn_vector_gradient_equals_autograd():
    """PaiNN's energies and dE/dd of the written-out reverse pass against autograd (float64
    to rounding, float32 to its precision), including a pair on a core (|d| ~ 1e-11 Å),
    edges on the cosine switch, and the parameter gradients of a loss of both."""
    for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 2e-5)):
        model = random_model(family="painn", dtype=dtype)
        sr = model.short_range
        assert isinstance(sr, VectorGradient)
        g = collate([water_crystal(), methane()], model.config.cutoff, model.config.gcut,
                    dtype)
        d = model.edge_vectors(g, g.positions, g.cell).detach()
        d[0] = torch.tensor([1e-11, -2e-12, 5e-12], dtype=dtype)
        lengths = edge_lengths(d)
        assert bool(((lengths > 3.5) & (lengths < 4.0)).any())
        dd = d.clone().requires_grad_(True)
        e_ref = sr(g.numbers, dd, g.edge_i, g.edge_j)
        (d_ref,) = torch.autograd.grad(e_ref.sum(), dd, create_graph=True)
        e, de = sr.energies_and_vector_gradient(g.numbers, d, g.edge_i, g.edge_j)
        np.testing.assert_allclose(e.detach(), e_ref.detach(), rtol=0,
                                   atol=tol * float(e_ref.detach().abs().max()))
        np.testing.assert_allclose(de.detach(), d_ref.detach(), rtol=0,
                                   atol=tol * float(d_ref.detach().abs().max()))
        if dtype != torch.float64:
            continue
        weights = torch.linspace(-1.0, 1.0, de.numel(), dtype=dtype).view_as(de)
        params = list(sr.parameters())
        g_ref = torch.autograd.grad((e_ref**2).sum() + (weights * d_ref**3).sum(), params)
        g_new = torch.autograd.grad((e**2).sum() + (weights * de**3).sum(), params)
        for (name, _), a, b in zip(sr.named_parameters(), g_ref, g_new, strict=True):
            assert float((a - b).abs().max()) <= 1e-11 * float(a.abs().max()), name


def test_painn_compile_failure_falls_back_with_a_warning(monkeypatch, caplog):
    """A compiler error in the PaiNN training step is logged and the step runs uncompiled
    (same values), never raised; later calls do not try again."""
    def broken(*args):
        raise RuntimeError("inductor says no")

    monkeypatch.setattr(painn_gradient._STEP, "compiled", broken)
    monkeypatch.setattr(painn_gradient._STEP, "failure", None)  # restored after the test
    model = random_model(family="painn").train()
    g = model.graph(water_molecule())
    plain = model(g, create_graph=True)
    with caplog.at_level("WARNING", logger=painn_gradient.__name__):
        out = model(g, create_graph=True, parameters_only=True, compiled=True)
    assert "inductor says no" in (painn_gradient.compile_failure() or "")
    assert any("goes on uncompiled" in r.getMessage() for r in caplog.records)
    np.testing.assert_allclose(out["forces"].detach(), plain["forces"].detach(), rtol=1e-12,
                               atol=1e-12)
    model(g, create_graph=True, parameters_only=True, compiled=True)  # no second try


@pytest.mark.slow
@pytest.mark.parametrize("family", ["schnet", "painn"])
def test_compiled_training_step_equals_the_double_backward(family):
    """The training step through torch.compile (a minute or two to compile): loss gradients
    within float64 rounding of the double backward's, on a molecule batch and (another batch
    size: no recompilation needed to be right) a periodic crystal with stress. Dynamo's
    caches are reset first: a compiled function first called with dynamo disabled (the tests
    above) is skipped for good, and would run eagerly here."""
    torch._dynamo.reset()
    compiled_before = counters["stats"]["unique_graphs"]
    model = random_model(family=family).train()
    params = [p for p in model.parameters() if p.requires_grad]
    batches = [([water_molecule(), methane(field=(0.02, 0.0, -0.01))], False),
               ([water_crystal(field=(0.01, -0.02, 0.03))], True)]
    for structures, crystal in batches:
        g = collate(structures, model.config.cutoff, model.config.gcut, torch.float64)
        plain = torch.autograd.grad(_loss(model(g, stress=crystal, create_graph=True)), params)
        out = model(g, stress=crystal, create_graph=True, parameters_only=True, compiled=True)
        fast = torch.autograd.grad(_loss(out), params)
        module = schnet_gradient if family == "schnet" else painn_gradient
        assert module.compile_failure() is None  # compiled, no fallback to eager
        for a, b in zip(plain, fast, strict=True):
            assert float((a - b).abs().max()) <= 1e-10 * (float(a.abs().max()) + 1e-30)
    assert counters["stats"]["unique_graphs"] > compiled_before  # dynamo did compile

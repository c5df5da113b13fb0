"""The tabulated SchNet filters (:class:`emlpack.nn.short_range.schnet.FilterTable`) equal the
filter
network: values and first derivatives at any edge length, zero beyond the cutoff, nodes at the
ends of the cutoff switch, and they refuse second derivatives instead of returning wrong ones."""

from __future__ import annotations

import pytest
import torch

from tests.nn.helpers import random_model


@pytest.fixture(scope="module")
def schnet():
    model = random_model(seed=3, cutoff=4.0, cutoff_transition=0.7)
    for p in model.parameters():
        p.requires_grad_(False)
    return model.short_range


def _lengths(schnet) -> torch.Tensor:
    start = schnet.cutoff - schnet.cutoff_transition
    special = [0.0, 1e-6, start - 1e-9, start, start + 1e-9, schnet.cutoff - 1e-9]
    grid = torch.linspace(0.0, schnet.cutoff, 3001, dtype=torch.float64)[1:-1] + 1.7e-4
    return torch.cat([torch.tensor(special, dtype=torch.float64), grid])


def test_table_equals_the_filter_network(schnet):
    """Filters within 1e-9 and their derivatives within 1e-6 of their largest magnitude, at
    the switch's ends too (whose second derivative jumps: a node there keeps it exact)."""
    table = schnet.filter_table(1e-3)
    r = _lengths(schnet).requires_grad_(True)
    exact = schnet.filter_taylor(r.detach())
    tabulated = table(r)
    assert len(tabulated) == len(exact) == len(schnet.interactions)
    for (w, dw, _), wt in zip(exact, tabulated, strict=True):
        assert torch.abs(wt - w).max() <= 1e-9 * torch.abs(w).max()
        # d/dr of sum_k c_k W_k(r), per edge, with random weights c_k
        c = torch.linspace(-1.0, 1.0, w.shape[1], dtype=w.dtype)
        (grad,) = torch.autograd.grad((wt * c).sum(), r, retain_graph=True)
        ref = (dw * c).sum(1)
        assert torch.abs(grad - ref).max() <= 1e-6 * torch.abs(ref).max()


def test_table_is_zero_beyond_the_cutoff_and_refuses_second_derivatives(schnet):
    table = schnet.filter_table(1e-3)
    r = torch.tensor([schnet.cutoff, schnet.cutoff + 0.3, 9.0], dtype=torch.float64,
                     requires_grad=True)
    w = torch.cat(table(r), 1)
    assert torch.all(w == 0.0)
    (g,) = torch.autograd.grad(w.sum(), r)
    assert torch.all(g == 0.0)
    inside = torch.tensor([0.8, 2.1], dtype=torch.float64, requires_grad=True)
    (g,) = torch.autograd.grad(torch.cat(table(inside), 1).pow(2).sum(), inside,
                               create_graph=True)
    with pytest.raises(RuntimeError, match="twice|not have been used"):
        torch.autograd.grad(g.sum(), inside)


def test_table_in_float32_and_its_cache(schnet):
    """Rounded from the float64 table: filters within float32 resolution; the same table
    object until a parameter changes."""
    table = schnet.filter_table(1e-3)
    assert schnet.filter_table(1e-3) is table
    r = _lengths(schnet)
    w64 = torch.cat(table(r), 1)
    w32 = torch.cat(table(r.float()), 1)
    assert w32.dtype == torch.float32
    assert torch.abs(w32.double() - w64).max() <= 1e-5 * torch.abs(w64).max()
    with torch.no_grad():
        schnet.interactions[0].filter1.bias.add_(0.01)
    try:
        assert schnet.filter_table(1e-3) is not table
    finally:
        with torch.no_grad():
            schnet.interactions[0].filter1.bias.sub_(0.01)

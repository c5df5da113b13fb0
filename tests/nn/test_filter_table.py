"""Tabulated SchNet filters (:meth:`SchNet.filter_table`): cubic Hermite interpolation of the
filter network from exact values and slopes, against the network itself (float64)."""

from __future__ import annotations

import pytest
import torch

from tests.legacy.test_reference_fixtures import load_model


@pytest.mark.parametrize("size", ["small", "paper"])
def test_tabulated_filters_equal_the_filter_network(size):
    """Values within 2e-9 of max|W| and r-derivatives (autograd of the interpolant) within 1e-6
    of max|dW/dr| of the exact network (measured at the default spacing 0.002 Å: 4.5e-10 and
    1.7e-7 on the paper-size fixture weights, 2e-11 and 1.4e-8 on the small trained benchmark
    model), on random lengths over [0, cutoff], the cutoff switch's ends and beyond the
    cutoff (0)."""
    schnet = load_model(size).schnet
    for p in schnet.parameters():
        p.requires_grad_(False)
    gen = torch.Generator().manual_seed(0)
    c, tr = schnet.cutoff, schnet.cutoff_transition
    r = torch.cat([torch.rand(3000, generator=gen, dtype=torch.float64) * c,
                   torch.tensor([0.0, c - tr, c - tr - 1e-7, c - tr + 1e-7, c, c + 0.3],
                                dtype=torch.float64)])
    table = schnet.filter_table(torch.float64, r.device)
    assert schnet.filter_table(torch.float64, r.device) is table  # cached
    x = r.clone().requires_grad_(True)
    tabulated = schnet.tabulated_filters(x, table)
    exact = schnet.frozen_filters(r)
    taylor = schnet.filter_taylor(r)
    for t, (w, ref) in enumerate(zip(tabulated, exact, strict=True)):
        assert torch.abs(w.detach() - ref).max() <= 2e-9 * ref.abs().max()
        assert torch.abs(w.detach()[-2:]).max() <= 1e-15 * ref.abs().max()
        cols = range(0, w.shape[1], 5)
        dw = torch.stack([torch.autograd.grad(w[:, k].sum(), x, retain_graph=True)[0]
                          for k in cols], 1)
        dref = taylor[t][1][:, list(cols)]
        assert torch.abs(dw - dref).max() <= 1e-6 * taylor[t][1].abs().max()

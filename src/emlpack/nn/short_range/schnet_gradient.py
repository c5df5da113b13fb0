"""SchNet's atomic energies and the gradient of their sum in the edge lengths, written out.

Training fits forces, so its loss depends on ``dE/dr``: through autograd that is a reverse
pass taken with ``create_graph=True`` and then differentiated again (a double backward with
about 3,500 operators a mini-eQM7 step). Here the reverse pass is written out by hand
as ordinary tensor operations (:func:`energies_and_length_gradient`), so that energies and
``dE/dr`` are one first-order expression of the parameters: the loss then needs one backward
pass, and the whole expression can be compiled (``torch.compile``: elementwise chains fused
into the matrix products' neighbours) because nothing in it calls autograd.

With ``y = ssp(x) = softplus(x) - ln 2`` and ``s(x) = dy/dx`` (torch's softplus slope: the
logistic function, 1 above its threshold 20), one interaction ``t`` is, forward::

    w   = ssp(ssp(rbf W1 + b1) W2 + b2) f_c          (E, K), the filters
    a   = h Win + bin;  conv = S(a, w) / J           (N, K), S: both ways over the half list
    h  += ssp(conv Wc + bc) W3 + b3

and backward, from ``g = dE/dh`` after the output network::

    gc  = ((g W3^T) * s(z3)) Wc^T / J                (dE/dconv)
    gw  = a_j * gc_i + a_i * gc_j                    (dE/dw per edge)
    g  += S(gc, w) Win^T
    dE/dr += sum_k gw (dw/dr)_k

with ``dw/dr`` in forward mode through the filter network, from the basis' derivative
``drbf/dr`` and ``f_c'`` (:func:`radial_taylor`): value and derivative share each matrix
product (stacked rows), and the first layers of all interactions are one product.

The basis, the cutoff and their derivatives depend on the geometry only (no gradient flows
through them): computed before the step, compiled apart (:func:`_geometry`), and passed in,
so that inductor cannot recompute them inside the edge kernels. The edge-sized products go
through oneDNN in float32 (:func:`emlpack.nn.short_range.common.edge_linear`), the shifted
softplus and its slope come from one exponential (:func:`_ssp_slope`); measured in
``docs/performance.md`` (issue 49). Float64 results equal autograd's to rounding
(``tests/nn/test_training_forward.py``: energies and dE/dr 1e-12, the loss gradients 1e-11
eager and 1e-10 compiled; float32 loss gradients within 1e-5 of the double backward's).
"""

from __future__ import annotations

import logging
import math

import torch
from torch import nn

from emlpack.nn.scatter import convolve
from emlpack.nn.short_range.common import LN2, CompiledOnce, edge_linear

log = logging.getLogger(__name__)


__all__ = ["compile_failure", "energies_and_length_gradient", "radial_taylor", "schnet_weights"]

#: weights per interaction in :func:`schnet_weights` (filter1, filter2, atom_in, conv_out,
#: atom_out: weight and bias each)
_PER_INTERACTION = 10


def radial_taylor(schnet: nn.Module, r: torch.Tensor, order: int) -> list[tuple[torch.Tensor, ...]]:
    """The Gaussian basis (E, n_rbf) and the cosine cutoff (E, 1) at the edge lengths ``r``
    (E,) (Å) with their derivatives in ``r`` up to ``order`` (1 or 2): ``[(rbf, rbf', ...),
    (f_c, f_c', ...)]`` (1/Å, 1/Å^2). The cutoff's derivatives are those of the cosine on the
    switch, 0 elsewhere (one-sided at its ends, as autograd takes them)."""
    return _radial_taylor(r, schnet.rbf.centers.to(r.dtype), schnet.rbf.width,
                          schnet.cutoff - schnet.cutoff_transition, schnet.cutoff_transition,
                          order)


def _radial_taylor(r: torch.Tensor, centers: torch.Tensor, width: float, start: float,
                   tr: float, order: int) -> list[tuple[torch.Tensor, ...]]:
    diff = r[:, None] - centers
    rbf = torch.exp(-0.5 * (diff / width) ** 2)
    basis = [rbf, -diff / width**2 * rbf]
    if order >= 2:
        basis.append(((diff / width**2) ** 2 - 1.0 / width**2) * rbf)
    x = (r - start) / tr
    inside = (x >= 0.0) & (x <= 1.0)
    xc = torch.clamp(x, 0.0, 1.0)
    cut = [(0.5 * (1.0 + torch.cos(math.pi * xc)))[:, None],
           torch.where(inside, -0.5 * math.pi / tr * torch.sin(math.pi * xc), 0.0)[:, None]]
    if order >= 2:
        cut.append(torch.where(inside, -0.5 * (math.pi / tr) ** 2 * torch.cos(math.pi * xc),
                               0.0)[:, None])
    return [tuple(basis), tuple(cut)]


def schnet_weights(schnet: nn.Module) -> list[torch.Tensor]:
    """The parameters in :func:`energies_and_length_gradient`'s order: the embedding, per
    interaction the weight and bias of filter1, filter2, atom_in, conv_out, atom_out, then
    the three output layers' weights and biases."""
    out = [schnet.embedding.weight]
    for b in schnet.interactions:
        for layer in (b.filter1, b.filter2, b.atom_in, b.conv_out, b.atom_out):
            out += [layer.weight, layer.bias]
    for layer in schnet.output:
        out += [layer.weight, layer.bias]
    return out


def _ssp_slope(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(ssp(x), s(x))``, the shifted softplus and its slope, from one exponential
    ``e = exp(min(x, 20))``: ``softplus = log1p(e)`` (torch's formula; ``x`` above its
    threshold 20), ``s = e / (1 + e)`` (1 above 20, as autograd takes torch's): one
    transcendental per element fewer than ``softplus`` and ``sigmoid`` apart (measured 42.9
    -> 39.4 ms a step, docs/performance.md). A custom autograd function saving ``s`` for the
    backward does not trace under dynamo (torch 2.13: ``lift_tracked_freevar_to_input``
    with the split's symbolic size), so the partitioner decides what to save."""
    big = x > 20.0
    e = torch.exp(torch.clamp(x, max=20.0))
    return torch.where(big, x, torch.log1p(e)) - LN2, torch.where(big, 1.0, e / (1.0 + e))


def _energies_and_gradient(
    weights: list[torch.Tensor],
    numbers: torch.Tensor,
    basis: torch.Tensor,
    fc: torch.Tensor,
    dfc: torch.Tensor,
    i: torch.Tensor,
    j: torch.Tensor,
    norm: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The module docstring's forward and backward on plain tensors (compilable); ``basis``
    (2E, n_rbf): the Gaussians and their r-derivative stacked, ``fc``, ``dfc`` (E, 1): the
    cutoff and its derivative (:func:`radial_taylor`, computed outside: no gradient flows
    there)."""
    linear = nn.functional.linear
    n_int = (len(weights) - 7) // _PER_INTERACTION
    blocks = [weights[1 + _PER_INTERACTION * t: 1 + _PER_INTERACTION * (t + 1)]
              for t in range(n_int)]
    w_o0, b_o0, w_o1, b_o1, w_o2, b_o2 = weights[1 + _PER_INTERACTION * n_int:]
    n_edges = fc.shape[0]
    # the filters and their derivative in r (forward mode), the first layer of every
    # interaction in one product of the basis and its derivative stacked: (2E, n_rbf)
    # the filters and their derivative in r (forward mode): value and derivative rows
    # stacked in each product (the first layers of all interactions in one product, sliced
    # apart, measured slower: its gradient is assembled from the slices)
    filters, slopes = [], []
    for w1, b1, w2, b2, *_ in blocks:
        z1, t1 = edge_linear(basis, w1).split(n_edges)
        y1, s1 = _ssp_slope(z1 + b1)
        second = edge_linear(torch.cat([y1, s1 * t1]), w2)
        z2, t2 = second.split(n_edges)
        y2, s2 = _ssp_slope(z2 + b2)
        filters.append(y2 * fc)
        slopes.append(s2 * t2 * fc + y2 * dfc)  # dw/dr (E, K)
    h = weights[0].index_select(0, numbers).to(basis.dtype)
    saved = []
    for (*_, w_in, b_in, w_c, b_c, w3, b3), w in zip(blocks, filters, strict=True):
        a = linear(h, w_in, b_in)
        z3 = linear(convolve(a, w, i, j) / norm, w_c, b_c)
        y3, s3 = _ssp_slope(z3)
        h = h + linear(y3, w3, b3)
        saved.append((a, s3))
    y0, s0 = _ssp_slope(linear(h, w_o0, b_o0))
    y1, s1 = _ssp_slope(linear(y0, w_o1, b_o1))
    energies = linear(y1, w_o2, b_o2).squeeze(-1)
    # reverse pass: g = dE/dh, every step an ordinary (differentiable) operation
    g = ((s1 * w_o2) @ w_o1) * s0 @ w_o0
    dedr = None
    for (*_, w_in, _, w_c, _, w3, _), w, dw, (a, s3) in zip(
            reversed(blocks), reversed(filters), reversed(slopes), reversed(saved), strict=True):
        gc = ((g @ w3) * s3) @ w_c / norm
        gw = (a.index_select(0, j) * gc.index_select(0, i)
              + a.index_select(0, i) * gc.index_select(0, j))
        g = g + convolve(gc, w, i, j) @ w_in
        term = (gw * dw).sum(1)
        dedr = term if dedr is None else dedr + term
    return energies, dedr


def _geometry(r: torch.Tensor, centers: torch.Tensor, width: float, start: float,
              tr: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The basis and its r-derivative stacked (2E, n_rbf), the cutoff and its derivative
    (E, 1) each: :func:`radial_taylor`'s, the step's geometry (no gradient flows there)."""
    (rbf, drbf), (fc, dfc) = _radial_taylor(r, centers, width, start, tr, order=1)
    return torch.cat([rbf, drbf]), fc, dfc


_GEOMETRY = CompiledOnce(_geometry, "SchNet geometry", log)
_STEP = CompiledOnce(_energies_and_gradient, "SchNet", log)


def compile_failure() -> str | None:
    """Why ``torch.compile`` of the SchNet training step failed in this process (None: it did
    not, or was not tried)."""
    return _STEP.failure


def energies_and_length_gradient(
    schnet: nn.Module,
    numbers: torch.Tensor,
    r: torch.Tensor,
    i: torch.Tensor,
    j: torch.Tensor,
    compiled: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Atomic energies (N,) (eV) and ``dE/dr`` (E,) (eV/Å) of their sum in the half-list edge
    lengths ``r`` (E,) (Å) of the edges ``(i, j)``, both differentiable (once) in the
    parameters and not in ``r``; ``compiled``: through ``torch.compile`` (the first call
    compiles, about a minute; a compiler error falls back to the plain evaluation with a
    logged warning)."""
    with torch.no_grad():
        basis, fc, dfc = _GEOMETRY(r.detach(), schnet.rbf.centers.to(r.dtype), schnet.rbf.width,
                                   schnet.cutoff - schnet.cutoff_transition,
                                   schnet.cutoff_transition, compiled=compiled)
    args = (schnet_weights(schnet), numbers, basis, fc, dfc, i, j, float(schnet.message_norm))
    return _STEP(*args, compiled=compiled)

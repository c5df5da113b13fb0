"""SchNet short-range energy of the eMLP, acting on cores and electron pairs alike.

Exactly the network of the paper and of the authors' TensorFlow reference:

* embedding: one learned row per particle number (Z for cores, 99 for electron pairs);
* radial basis: ``n_rbf`` Gaussians ``exp(-(r - mu_k)^2 / (2 s^2))``, ``mu_k = start + k s``,
  ``s = (end - start) / n_rbf`` (so the last centre is ``end - s``);
* cosine cutoff, flat up to ``cutoff - transition``: ``f_c = 1``, then
  ``(1 + cos(pi (r - cutoff + transition) / transition)) / 2``, and 0 beyond ``cutoff``;
* interaction ``t``: ``a = h W_in + b_in``;
  ``W_ij = ssp(ssp(rbf_ij W_f1 + b_f1) W_f2 + b_f2) f_c(r_ij)``;
  ``conv_i = sum_j a_j * W_ij / J`` (J = 70); ``h += ssp(conv W_2 + b_2) W_3 + b_3``;
* output MLP ``F -> F -> F/2 -> 1`` with shifted softplus ``ssp(x) = softplus(x) - ln 2``,
  giving one energy (eV) per particle.

Distances are ``sqrt(|d|^2 + 1e-20)`` as in the reference (finite gradient at d = 0,
:func:`emlpack.nn.short_range.common.edge_lengths`). The filter of an unordered pair is
computed once and the message is scattered both ways.

The short-range family ``"schnet"`` (:mod:`emlpack.nn.short_range.protocol`) with every
capability: held filters (:class:`HeldFilters`), a filter table (:class:`FilterTable`) and the
exact edge-length Hessian (:mod:`emlpack.nn.short_range.schnet_hessian`); with frozen
parameters it evaluates its folded weights (:meth:`SchNet.folded_weights`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch
from torch import nn
from torch.autograd.function import once_differentiable

from emlpack.nn.scatter import convolve
from emlpack.nn.short_range.common import (
    LN2,
    cosine_cutoff,
    edge_lengths,
    shifted_softplus,
    softplus_slopes,
)
from emlpack.nn.short_range.schnet_gradient import energies_and_length_gradient, radial_taylor
from emlpack.nn.short_range.schnet_hessian import schnet_edge_hessian
from emlpack.structure import PAIR_NUMBER

if TYPE_CHECKING:
    from torch.autograd.function import FunctionCtx

__all__ = ["SCHNET_DEFAULTS", "FilterTable", "HeldFilters", "SchNet"]

#: the family's parameters and their defaults (the paper's model; cutoff and transition are
#: the eMLP's, 4 and 0.5 Å)
SCHNET_DEFAULTS = {
    "n_features": 512,
    "n_filters": 128,
    "n_rbf": 32,
    "n_interactions": 4,
    "rbf_start": 0.0,
    "rbf_end": 4.0,
    "message_norm": 70.0,
}


class _CubicTable(torch.autograd.Function):
    """Piecewise-cubic table lookup ``w(r)`` (E, M) and its first derivative in one gather.

    ``u``: grid coordinate of every edge (E,) (interval ``floor(u)``, fraction ``u - floor``);
    ``coefficients`` (n, 4 M) the cubic of every interval in the fraction. Differentiable
    once (first derivatives only)."""

    #: edges per gathered block (measured, 4544 edges x 192 filters, float64, 1 thread:
    #: 4.5 ms in blocks of 256 vs 7.2 ms in one gather, whose 28 MB leave the caches)
    block = 256

    @staticmethod
    def forward(  # noqa: D102
        ctx: FunctionCtx, u: torch.Tensor, coefficients: torch.Tensor
    ) -> torch.Tensor:
        k = torch.clamp(u.floor().long(), 0, coefficients.shape[0] - 1)
        t = u - k
        one = torch.ones_like(t)
        # rows: powers of the fraction for the value, and for its derivative when needed
        powers = [one, t, t * t, t * t * t]
        if ctx.needs_input_grad[0]:
            powers += [torch.zeros_like(t), one, 2.0 * t, 3.0 * t * t]
        powers = torch.stack(powers, 1).view(len(u), -1, 4)
        m = coefficients.shape[1] // 4
        out = u.new_empty(len(u), powers.shape[1], m)
        for a in range(0, len(u), _CubicTable.block):
            rows = slice(a, a + _CubicTable.block)
            c = coefficients.index_select(0, k[rows]).view(-1, 4, m)
            torch.bmm(powers[rows], c, out=out[rows])
        if ctx.needs_input_grad[0]:
            ctx.save_for_backward(out[:, 1])
        return out[:, 0]

    @staticmethod
    @once_differentiable
    def backward(ctx: FunctionCtx, grad_w: torch.Tensor) -> tuple[torch.Tensor, None]:  # noqa: D102
        (dw,) = ctx.saved_tensors
        return (grad_w * dw).sum(1), None


class FilterTable:
    """The frozen filters ``W_ij(r)`` of every interaction as a cubic Hermite table in the edge
    length (values and exact first derivatives at the nodes, :meth:`SchNet.filter_taylor`).

    Nodes: uniform with spacing about ``spacing`` (Å) on ``[0, cutoff - transition]`` and on
    ``[cutoff - transition, cutoff]`` (the cutoff function's second derivative jumps at both
    ends, so they are nodes), zero beyond the cutoff. One gather of 4 L K numbers per edge
    replaces the filter network (32 -> K -> K per interaction); the table is differentiable
    once (energy and forces, no Hessians). Measured on the trained benchmark model with
    spacing 1e-3 Å: filters within 2e-12 of the network (scale 1.7), their derivatives within
    7e-8 (scale 22).
    """

    def __init__(self, schnet: SchNet, spacing: float = 1e-3) -> None:
        cutoff, transition = schnet.cutoff, schnet.cutoff_transition
        start = cutoff - transition
        self.n_flat = max(1, math.ceil(start / spacing)) if start > 0 else 0
        self.n_switch = max(1, math.ceil(transition / spacing)) if transition > 0 else 0
        self.h_flat = start / self.n_flat if self.n_flat else 1.0
        self.h_switch = transition / self.n_switch if self.n_switch else 1.0
        self.start, self.cutoff = start, cutoff
        nodes = torch.cat([
            torch.arange(self.n_flat, dtype=torch.float64) * self.h_flat,
            start + torch.arange(self.n_switch + 1, dtype=torch.float64) * self.h_switch,
        ])
        widths = torch.cat([torch.full((self.n_flat,), self.h_flat, dtype=torch.float64),
                            torch.full((self.n_switch,), self.h_switch, dtype=torch.float64)])
        taylor = schnet.filter_taylor(nodes)
        f = torch.cat([t[0] for t in taylor], 1)  # (nodes, L K)
        d = torch.cat([t[1] for t in taylor], 1)  # dW/dr
        d0, d1 = d[:-1] * widths[:, None], d[1:] * widths[:, None]
        f0, f1 = f[:-1], f[1:]
        cubic = torch.stack([f0, d0, 3.0 * (f1 - f0) - 2.0 * d0 - d1, 2.0 * (f0 - f1) + d0 + d1], 1)
        # one interval of zeros beyond the cutoff (every edge farther away lands there)
        cubic = torch.cat([cubic, torch.zeros_like(cubic[:1])]).reshape(len(widths) + 1, -1)
        self.n_interactions = len(taylor)
        self._coefficients = {torch.float64: cubic.contiguous()}

    def coefficients(
        self, dtype: torch.dtype, device: torch.device | str | None = None
    ) -> torch.Tensor:
        """The table (intervals, 4 L K) in ``dtype`` (rounded from float64, cached)."""
        key = (dtype, str(device))
        if key not in self._coefficients:
            self._coefficients[key] = self._coefficients[torch.float64].to(dtype=dtype,
                                                                          device=device)
        return self._coefficients[key]

    def __call__(self, r: torch.Tensor) -> list[torch.Tensor]:
        """Filters (E, K) of every interaction at the edge lengths ``r`` (E,) (Å)."""
        flat = r < self.start
        u = torch.where(flat, r / self.h_flat, self.n_flat + (r - self.start) / self.h_switch)
        w = _CubicTable.apply(u, self.coefficients(r.dtype, r.device))
        return list(w.chunk(self.n_interactions, dim=1))


@dataclass
class HeldFilters:
    """Filters held fixed on part of the half-list edges, whose lengths do not change between
    calls (the core-core edges while only electron pairs move at fixed cores and cell).

    ``i``, ``j`` (H,) are the held edges and ``filters`` their filters ``W_ij`` (H, K), one per
    interaction, computed once (:meth:`SchNet.frozen_filters`); ``free`` (E - H,) indexes the
    graph's edges whose filters are evaluated at every call. The energy equals the plain
    evaluation up to rounding (only the order of the message sums changes). With ``table``
    the free edges' filters come from that :class:`FilterTable` instead of the filter network
    (first derivatives only).
    """

    i: torch.Tensor
    j: torch.Tensor
    filters: list[torch.Tensor]
    free: torch.Tensor
    table: FilterTable | None = None

    def subset(
        self, rows: torch.Tensor, old_to_new: torch.Tensor, free: torch.Tensor
    ) -> HeldFilters:
        """The held edges ``rows`` (H,) bool, renumbered by ``old_to_new`` (N,), with the new
        graph's free edges ``free`` (no filter recomputed; the table is kept)."""
        return HeldFilters(i=old_to_new[self.i[rows]], j=old_to_new[self.j[rows]],
                           filters=[f[rows] for f in self.filters], free=free, table=self.table)

    def to(self, dtype: torch.dtype) -> HeldFilters:
        """The held filters rounded to ``dtype`` (not recomputed)."""
        return replace(self, filters=[f.to(dtype) for f in self.filters])


class GaussianBasis(nn.Module):
    """Gaussian radial basis: centres ``start + k w``, width ``w = (end - start)/n``."""

    def __init__(self, n_rbf: int, start: float, end: float) -> None:
        super().__init__()
        width = (end - start) / n_rbf
        self.register_buffer(
            "centers", start + width * torch.arange(n_rbf, dtype=torch.float64), persistent=False
        )
        self.width = width

    def forward(self, r: torch.Tensor) -> torch.Tensor:
        """Basis values (E, n_rbf) at the edge lengths ``r`` (E,) (Å)."""
        diff = r[:, None] - self.centers.to(r.dtype)
        return torch.exp(-0.5 * (diff / self.width) ** 2)


class Interaction(nn.Module):
    """One continuous-filter convolution block with residual update."""

    def __init__(self, n_features: int, n_filters: int, n_rbf: int) -> None:
        super().__init__()
        self.filter1 = nn.Linear(n_rbf, n_filters)
        self.filter2 = nn.Linear(n_filters, n_filters)
        self.atom_in = nn.Linear(n_features, n_filters)
        self.conv_out = nn.Linear(n_filters, n_filters)
        self.atom_out = nn.Linear(n_filters, n_features)

    def filter(self, rbf: torch.Tensor, fcut: torch.Tensor) -> torch.Tensor:
        """Filters ``W_ij`` (E, K) of the half-list edges."""
        return shifted_softplus(self.filter2(shifted_softplus(self.filter1(rbf)))) * fcut[:, None]

    def update(
        self, h: torch.Tensor, w: torch.Tensor, i: torch.Tensor, j: torch.Tensor, norm: float
    ) -> torch.Tensor:
        """Residual update of ``h`` from the filters ``w`` of the half-list edges ``(i, j)``."""
        a = self.atom_in(h)
        return h + self.atom_out(shifted_softplus(self.conv_out(convolve(a, w, i, j) / norm)))

    def forward(
        self,
        h: torch.Tensor,
        rbf: torch.Tensor,
        fcut: torch.Tensor,
        i: torch.Tensor,
        j: torch.Tensor,
        norm: float,
    ) -> torch.Tensor:
        """Filters of the half-list edges from ``rbf`` and ``fcut``, then the residual
        update of ``h``."""
        return self.update(h, self.filter(rbf, fcut), i, j, norm)


class SchNet(nn.Module):
    """Per-particle short-range energies (eV) of a batch of structures: the family
    ``"schnet"`` (:class:`~emlpack.nn.short_range.protocol.ShortRange`)."""

    #: capability :class:`~emlpack.nn.short_range.protocol.FrozenAnyDtype`: the folded
    #: weights are cast to the input's dtype
    frozen_any_dtype = True

    def __init__(
        self,
        n_features: int = 512,
        n_filters: int = 128,
        n_rbf: int = 32,
        n_interactions: int = 4,
        cutoff: float = 4.0,
        cutoff_transition: float = 0.5,
        rbf_start: float = 0.0,
        rbf_end: float = 4.0,
        message_norm: float = 70.0,
        n_embeddings: int = PAIR_NUMBER + 1,
    ) -> None:
        """The paper's hyperparameters by default (lengths in Å); ``n_embeddings``: rows of
        the embedding (atomic numbers below it; the electron pair is 99)."""
        super().__init__()
        self.cutoff = cutoff
        self.cutoff_transition = cutoff_transition
        self.message_norm = message_norm
        self.embedding = nn.Embedding(n_embeddings, n_features)
        self.rbf = GaussianBasis(n_rbf, rbf_start, rbf_end)
        self.interactions = nn.ModuleList(
            Interaction(n_features, n_filters, n_rbf) for _ in range(n_interactions)
        )
        half = n_features // 2
        self.output = nn.ModuleList(
            [nn.Linear(n_features, n_features), nn.Linear(n_features, half), nn.Linear(half, 1)]
        )

    def forward(
        self,
        numbers: torch.Tensor,
        vectors: torch.Tensor,
        i: torch.Tensor,
        j: torch.Tensor,
        held: HeldFilters | None = None,
    ) -> torch.Tensor:
        """Atomic energies (N,) (eV) from particle numbers and the half-list edge vectors
        ``vectors`` (E, 3) (Å) of the edges ``(i, j)``; with ``held`` (frozen weights only) the
        edges ``held.i``, ``held.j`` contribute with their held filters in addition."""
        return self.energies_from_lengths(numbers, edge_lengths(vectors), i, j, held)

    def energies_from_lengths(
        self,
        numbers: torch.Tensor,
        r: torch.Tensor,
        i: torch.Tensor,
        j: torch.Tensor,
        held: HeldFilters | None = None,
    ) -> torch.Tensor:
        """:meth:`forward` from the edge lengths ``r`` (E,) (Å): SchNet sees only those."""
        frozen = not any(p.requires_grad for p in self._parameter_list())
        if held is not None and not frozen:
            raise ValueError("held filters need frozen parameters (requires_grad=False)")
        if frozen:
            return self._forward_folded(numbers, r, i, j, held)
        rbf = self.rbf(r)
        fcut = cosine_cutoff(r, self.cutoff, self.cutoff_transition)
        h = self.embedding(numbers).to(r.dtype)
        for block in self.interactions:
            h = block(h, rbf, fcut, i, j, self.message_norm)
        h = shifted_softplus(self.output[0](h))
        h = shifted_softplus(self.output[1](h))
        return self.output[2](h).squeeze(-1)

    # ------------------------------------------------------------------ frozen weights
    # With frozen parameters (inference: forces, Hessians, relaxation, MD) the same network is
    # evaluated with the linear maps between the 128-wide interaction outputs and the 512-wide
    # features multiplied out. The features are h_t = h_0 + sum_{s<t} (v_s W3_s + b3_s), with
    # v_s = ssp(conv_s W2_s + b2_s) (N, K) and h_0 the embedding, so
    #   a_t = h_t Win_t + bin_t = T_t[Z] + sum_{s<t} v_s (W3_s Win_t)
    # with per-species tables T_t = emb Win_t + bin_t + sum_{s<t} b3_s Win_t, and the first
    # output layer is T_out[Z] + [v_0 ... v_{L-1}] [W3_0 W0; ...; W3_{L-1} W0]. Per particle this
    # replaces 2 L F K + F^2 multiply-adds by L (L - 1) K^2 / 2 + L K F (paper model: 1.05M ->
    # 0.36M, about a quarter of the model's work). The products are formed in float64 once per
    # parameter version and cached; the result equals the plain evaluation up to rounding.
    def folded_weights(self, dtype: torch.dtype, device: torch.device | str | None) -> dict:
        """The frozen-weight tables and matrices described above (cached per dtype, device and
        parameter version): ``tables``, ``cross``, ``table_out``, ``w_out``, ``filters`` (per
        interaction ``(w1, b1, w2, b2, wc, bc)``, ``wc`` divided by the message norm) and
        ``heads``."""
        key = self._parameter_key()
        caches = self.__dict__.setdefault("_fold_cache", {})  # per dtype and device
        cache = caches.get((dtype, str(device)))
        if cache is not None and cache[0] == key:
            return cache[1]
        with torch.no_grad():
            f64 = torch.float64
            emb = self.embedding.weight.to(f64)
            blocks = self.interactions
            w_in = [b.atom_in.weight.to(f64).T for b in blocks]  # (F, K)
            b_in = [b.atom_in.bias.to(f64) for b in blocks]
            w3 = [b.atom_out.weight.to(f64).T for b in blocks]  # (K, F)
            b3 = [b.atom_out.bias.to(f64) for b in blocks]
            w0 = self.output[0].weight.to(f64).T  # (F, F)
            b0 = self.output[0].bias.to(f64)
            # the "- ln 2" of every shifted softplus moves into the next layer's bias: the
            # stored activations are plain softplus values
            tables, cross = [], []
            for t in range(len(blocks)):
                bias = b_in[t] + sum((b3[s] @ w_in[t] for s in range(t)), torch.zeros_like(b_in[t]))
                c = [w3[s] @ w_in[t] for s in range(t)]
                bias = bias - LN2 * sum((m.sum(0) for m in c), torch.zeros_like(bias))
                tables.append(emb @ w_in[t] + bias)
                cross.append(c)
            w_out = torch.cat(w3, 0) @ w0
            bias0 = b0 + sum((b3[s] @ w0 for s in range(len(blocks))), torch.zeros_like(b0))
            bias0 = bias0 - LN2 * w_out.sum(0)
            filters = []
            for b in blocks:
                w2 = b.filter2.weight.to(f64).T
                wc = b.conv_out.weight.to(f64).T / self.message_norm
                filters.append(
                    (
                        b.filter1.weight.to(f64).T,
                        b.filter1.bias.to(f64),
                        w2,
                        b.filter2.bias.to(f64) - LN2 * w2.sum(0),
                        wc,
                        b.conv_out.bias.to(f64),
                    )
                )
            heads = []
            for layer in self.output[1:]:
                w = layer.weight.to(f64).T
                heads.append((w, layer.bias.to(f64) - LN2 * w.sum(0)))

            def cast(x: torch.Tensor) -> torch.Tensor:
                return x.to(dtype=dtype, device=device).contiguous()

            out = {
                "tables": [cast(x) for x in tables],
                "cross": [[cast(x) for x in c] for c in cross],
                "table_out": cast(emb @ w0 + bias0),
                "w_out": cast(w_out),
                "filters": [tuple(cast(x) for x in f) for f in filters],
                "heads": [tuple(cast(x) for x in h) for h in heads],
            }
        caches[(dtype, str(device))] = (key, out)
        return out

    def filter_taylor(self, r: torch.Tensor) -> list[tuple[torch.Tensor, ...]]:
        """Filters of every interaction and their first and second derivatives in the edge
        length, ``(W, dW/dr, d2W/dr2)`` each (E, K), at the edge lengths ``r`` (Å).

        ``W(r0) + W'(r0) (r - r0) + W''(r0) (r - r0)^2 / 2`` is the filters' exact second-order
        Taylor expansion: a function of ``r`` through it has the same value, gradient and
        Hessian at ``r0`` as through the filter network (used by
        :mod:`emlpack.nn.short_range.schnet_hessian`). Softplus derivatives follow torch's threshold
        (``x > 20``: slope 1, curvature 0), so they equal autograd's exactly.
        """
        fw = self.folded_weights(r.dtype, r.device)
        (rbf, rbf1, rbf2), (fc, fc1, fc2) = radial_taylor(self, r, order=2)
        out = []
        for w1, b1, w2, b2, _, _ in fw["filters"]:
            z1 = torch.addmm(b1, rbf, w1)
            s1, c1 = softplus_slopes(z1)
            z1d, z1dd = rbf1 @ w1, rbf2 @ w1
            y1 = nn.functional.softplus(z1)
            z2 = torch.addmm(b2, y1, w2)
            z2d = (s1 * z1d) @ w2
            z2dd = (c1 * z1d * z1d + s1 * z1dd) @ w2
            s2, c2 = softplus_slopes(z2)
            y2 = nn.functional.softplus(z2) - LN2
            y2d = s2 * z2d
            y2dd = c2 * z2d * z2d + s2 * z2dd
            out.append((y2 * fc, y2d * fc + y2 * fc1, y2dd * fc + 2.0 * y2d * fc1 + y2 * fc2))
        return out

    def _apply(self, fn: Callable[[torch.Tensor], torch.Tensor], recurse: bool = True) -> SchNet:
        # .to(), .double(), ... may replace the parameters: list them again
        self.__dict__.pop("_parameters_listed", None)
        return super()._apply(fn, recurse)

    def _parameter_list(self) -> tuple[nn.Parameter, ...]:
        """The parameters, listed once per conversion (walking the modules took 0.24 ms a
        call, 7 % of hexane's energy+gradient; measured)."""
        params = self.__dict__.get("_parameters_listed")
        if params is None:
            params = self.__dict__["_parameters_listed"] = tuple(self.parameters())
        return params

    def _parameter_key(self) -> tuple:
        """Identity, version and storage of every parameter: changes when a weight does."""
        return tuple((id(p), p._version, p.data_ptr()) for p in self._parameter_list())

    def filter_table(self, spacing: float = 1e-3) -> FilterTable:
        """The :class:`FilterTable` of the current (frozen) weights, cached per parameter
        version and spacing (Å)."""
        key = self._parameter_key()
        caches = self.__dict__.setdefault("_table_cache", {})
        cached = caches.get(spacing)
        if cached is None or cached[0] != key:
            with torch.no_grad():
                cached = caches[spacing] = (key, FilterTable(self, spacing))
        return cached[1]

    def frozen_filters(self, r: torch.Tensor) -> list[torch.Tensor]:
        """Filters ``W_ij`` (E, K) of every interaction at the edge lengths ``r`` (Å), from
        the frozen-weight tables (:meth:`folded_weights`), as the folded evaluation forms them
        (for :class:`HeldFilters`)."""
        fw = self.folded_weights(r.dtype, r.device)
        rbf = self.rbf(r)
        fc = cosine_cutoff(r, self.cutoff, self.cutoff_transition)[:, None]
        return [self._filter(f, rbf, fc) for f in fw["filters"]]

    # ------------------------------------------------------------------ capabilities
    def hold(
        self, vectors: torch.Tensor, i: torch.Tensor, j: torch.Tensor, free: torch.Tensor
    ) -> HeldFilters:
        """Capability :class:`~emlpack.nn.short_range.protocol.HoldsEdges`: the filters of the
        edges ``(i, j)`` of vectors ``vectors`` (H, 3) (Å), computed once (frozen weights)."""
        with torch.no_grad():
            filters = self.frozen_filters(edge_lengths(vectors.detach()))
        return HeldFilters(i=i, j=j, filters=filters, free=free)

    def tabulate(self, held: HeldFilters, spacing: float) -> HeldFilters:
        """Capability :class:`~emlpack.nn.short_range.protocol.TabulatesEdges`: ``held`` with
        the free edges' filters from :meth:`filter_table` (``spacing`` Å)."""
        return replace(held, table=self.filter_table(spacing))

    def length_hessian(
        self,
        numbers: torch.Tensor,
        r: torch.Tensor,
        i: torch.Tensor,
        j: torch.Tensor,
        jac: torch.Tensor,
        tangent_dtype: torch.dtype | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Capability :class:`~emlpack.nn.short_range.protocol.LengthHessian`:
        :func:`~emlpack.nn.short_range.schnet_hessian.schnet_edge_hessian`."""
        return schnet_edge_hessian(self, numbers, r, i, j, jac, tangent_dtype=tangent_dtype)

    def energies_and_length_gradient(
        self,
        numbers: torch.Tensor,
        r: torch.Tensor,
        i: torch.Tensor,
        j: torch.Tensor,
        compiled: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Capability :class:`~emlpack.nn.short_range.protocol.LengthGradient`:
        :func:`~emlpack.nn.short_range.schnet_gradient.energies_and_length_gradient`."""
        return energies_and_length_gradient(self, numbers, r, i, j, compiled=compiled)

    @staticmethod
    def _filter(f: tuple[torch.Tensor, ...], rbf: torch.Tensor, fc: torch.Tensor) -> torch.Tensor:
        # W_ij = (softplus(z) - ln 2) f_c in one pass
        w1, b1, w2, b2, _, _ = f
        softplus = nn.functional.softplus
        return torch.addcmul(
            fc * -LN2, softplus(torch.addmm(b2, softplus(torch.addmm(b1, rbf, w1)), w2)), fc
        )

    def _forward_folded(
        self,
        numbers: torch.Tensor,
        r: torch.Tensor,
        i: torch.Tensor,
        j: torch.Tensor,
        held: HeldFilters | None = None,
    ) -> torch.Tensor:
        fw = self.folded_weights(r.dtype, r.device)
        softplus = nn.functional.softplus
        if held is not None and held.table is not None:
            filters = held.table(r)
        else:
            rbf = self.rbf(r)
            fc = cosine_cutoff(r, self.cutoff, self.cutoff_transition)[:, None]
            filters = [self._filter(f, rbf, fc) for f in fw["filters"]]
        vs = []
        for t, f in enumerate(fw["filters"]):
            wc, bc = f[4], f[5]
            a = fw["tables"][t].index_select(0, numbers)
            for s, m in enumerate(fw["cross"][t]):
                a = torch.addmm(a, vs[s], m)
            w = filters[t]
            conv = None
            if held is not None:
                conv = convolve(a, held.filters[t].to(a.dtype), held.i, held.j)
            conv = convolve(a, w, i, j, conv)
            vs.append(softplus(torch.addmm(bc, conv, wc)))
        h = softplus(
            torch.addmm(fw["table_out"].index_select(0, numbers), torch.cat(vs, 1), fw["w_out"])
        )
        (w1, b1), (w2, b2) = fw["heads"]
        h = softplus(torch.addmm(b1, h, w1))
        return torch.addmm(b2, h, w2).squeeze(-1)

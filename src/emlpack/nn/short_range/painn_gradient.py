"""PaiNN's atomic energies and the gradient of their sum in the edge vectors, written out.

Training fits forces, so its loss depends on ``dE/dd`` of the half-list edge vectors ``d``
(E, 3): through autograd a reverse pass taken with ``create_graph=True`` and differentiated
again (a double backward). Here that reverse pass is written out by hand as ordinary tensor
operations (:func:`energies_and_vector_gradient`): energies and ``dE/dd`` are one
first-order expression of the parameters, whose gradient is one ordinary backward pass, and
the whole expression compiles (``torch.compile``) because nothing in it calls autograd.

The forward is :class:`emlpack.nn.short_range.painn.PaiNN`'s (same operations up to their
order: all filters of all interactions come from one product ``basis @ [W_f; b_f]^T``, and
the direction filters as ``u (x) (basis W_vr^T)``), saving what the reverse needs. The
reverse, from ``gs = dE/ds`` (N, F) after the output network and ``gv = dE/dv = 0``
(N, 3, F), per interaction from the last:

* update ``s' = s + g_sv <Uv, Vv> + g_ss``, ``v' = v + g_vv Uv`` with
  ``(g_vv, g_sv, g_ss) = MLP([s, n(Vv)])``: ``d/dg = (<gv, Uv>, gs <Uv, Vv>, gs)`` through
  the MLP back to ``s`` and ``n``; ``d/dUv = gs g_sv Vv + g_vv gv``,
  ``d/dVv = gs g_sv Uv + (dE/dn) Vv / n``; both through the mixing map back to ``v``;
* message, both directions of each half edge (sources ``j`` then ``i``, the ``a_vr``
  channel negated for the second: the ``flip``): with ``GS, GV`` the gradients gathered at
  the targets, ``d/da_s = GS W_s``, ``d/da_vr = <GV, u> W_vr``, ``d/da_vv = <GV, v_src>
  W_vv`` (scattered back to the sources' ``phi`` rows, then through the message MLP to
  ``s``), ``d/dv_src = a_vv W_vv GV`` (to ``v``), and the filters' gradients (summed over
  both directions) ``d/dW_s = GS a_s``, ``d/dW_vv = <GV, v_src> a_vv``, and for ``u (x)
  W_vr``: ``G = sum_dir GV a_vr`` (E, 3, F), ``d/dW_vr = <G, u>``, ``d/du += G W_vr``.

Then the filters' gradients of all interactions through ``[W_f; b_f]`` in one product to the
basis ``[rbf f_c, f_c]``, from there to ``r = sqrt(|d|^2 + edge_eps)`` (Gaussians) and the
cutoff's length ``|d|`` (:func:`emlpack.nn.short_range.common.edge_lengths`), and
``dE/dd = dE/dr d/r + dE/d|d| d/|d| + (dE/du - u <u, dE/du>) / r``. The basis, the cutoff,
``u`` and their derivatives depend on the geometry only (no gradient flows through them).
Float64 results equal autograd's to rounding (``tests/nn/test_training_forward.py``).
"""

from __future__ import annotations

import logging
import math

import torch
from torch import nn

from emlpack.nn.scatter import segment_sum
from emlpack.nn.short_range.common import CompiledOnce, edge_lengths, edge_linear

log = logging.getLogger(__name__)

__all__ = ["compile_failure", "energies_and_vector_gradient", "painn_weights"]

#: weights per interaction in :func:`painn_weights` (message MLP: 2 weights, 2 biases;
#: update: mixing map, context MLP's 2 weights and 2 biases)
_PER_INTERACTION = 9


def painn_weights(painn: nn.Module) -> list[torch.Tensor]:
    """The parameters in :func:`energies_and_vector_gradient`'s order: the embedding, the
    filters' weight and bias, per interaction the message MLP's (W1, b1, W2, b2), the update's
    mixing map and its context MLP's (W1, b1, W2, b2), then the output MLP's (W1, b1, W2,
    b2)."""
    out = [painn.embedding.weight, painn.filters.weight, painn.filters.bias]
    for m, u in zip(painn.messages, painn.updates, strict=True):
        out += [m[0].weight, m[0].bias, m[2].weight, m[2].bias, u.mix.weight]
        out += [u.context[0].weight, u.context[0].bias, u.context[2].weight, u.context[2].bias]
    out += [painn.output[0].weight, painn.output[0].bias, painn.output[2].weight,
            painn.output[2].bias]
    return out


def _silu_slope(x: torch.Tensor) -> torch.Tensor:
    """d silu(x)/dx = sigma(x) (1 + x (1 - sigma(x))), as torch's autograd takes it."""
    sig = torch.sigmoid(x)
    return sig * (1.0 + x * (1.0 - sig))


def _edge_geometry(
    d: torch.Tensor, centers: torch.Tensor, radial: tuple[float, ...]
) -> tuple[torch.Tensor, ...]:
    """``(r, rl, u, rbf, drbf/dr, f_c, df_c/drl)`` of the edge vectors ``d`` (E, 3) (Å):
    ``r = sqrt(|d|^2 + edge_eps)``, ``rl = edge_lengths(d)``, ``u = d / r`` (E, 3), the
    Gaussians (E, R) in ``r``, the cutoff divided by the message norm (E,) in ``rl`` (its
    slope that of the cosine on the switch, 0 elsewhere, one-sided at its ends as autograd
    takes it); ``radial``: Gaussian width, cutoff switch start and width (Å), edge_eps
    (Å^2), message norm."""
    width, start, tr, edge_eps, norm = radial
    r = torch.sqrt((d * d).sum(-1) + edge_eps)
    rl = edge_lengths(d)
    u = d / r[:, None]
    diff = r[:, None] - centers
    rbf = torch.exp(-0.5 * (diff / width) ** 2)
    drbf = -diff / width**2 * rbf
    x = (rl - start) / tr
    inside = (x >= 0.0) & (x <= 1.0)
    xc = torch.clamp(x, 0.0, 1.0)
    fc = 0.5 * (1.0 + torch.cos(math.pi * xc)) / norm
    dfc = torch.where(inside, -0.5 * math.pi / tr * torch.sin(math.pi * xc), 0.0) / norm
    return r, rl, u, rbf, drbf, fc, dfc


def _energies_and_gradient(
    weights: list[torch.Tensor],
    numbers: torch.Tensor,
    d: torch.Tensor,
    centers: torch.Tensor,
    i: torch.Tensor,
    j: torch.Tensor,
    radial: tuple[float, ...],
    norm_eps: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The module docstring's forward and reverse on plain tensors (compilable)."""
    linear, silu = nn.functional.linear, nn.functional.silu
    r, rl, u, rbf, drbf, fc, dfc = _edge_geometry(d, centers, radial)
    emb, w_f, b_f = weights[:3]
    n_t = (len(weights) - 7) // _PER_INTERACTION
    blocks = [weights[3 + _PER_INTERACTION * t: 3 + _PER_INTERACTION * (t + 1)]
              for t in range(n_t)]
    w_o1, b_o1, w_o2, b_o2 = weights[3 + _PER_INTERACTION * n_t:]
    n, n_edges, f = numbers.shape[0], d.shape[0], emb.shape[1]
    # all filters of all interactions in one product (E, T, 3, F): channels (s, vv, vr)
    basis = torch.cat([rbf * fc[:, None], fc[:, None]], 1)  # (E, R + 1)
    w_all = torch.cat([w_f, b_f[:, None]], 1)  # (3 F T, R + 1)
    filt = edge_linear(basis, w_all).view(n_edges, n_t, 3, f)
    source = torch.cat([j, i + n])
    source_v, target = torch.cat([j, i]), torch.cat([i, j])
    flip = torch.ones(3 * f, dtype=d.dtype, device=d.device)
    flip[2 * f:] = -1.0
    s = emb.index_select(0, numbers).to(d.dtype)
    v = None
    saved = []
    for t, (w1, b1, w2, b2, mix, c1, cb1, c2, cb2) in enumerate(blocks):
        fs, fvv, fr = filt[:, t].unbind(1)  # (E, F) each
        z1 = linear(s, w1, b1)
        phi = linear(silu(z1), w2, b2)
        p = torch.cat([phi, phi * flip]).index_select(0, source).view(2, n_edges, 3 * f)
        p_s, p_vv, p_vr = p.split(f, -1)  # (2, E, F) each
        wu = u[:, :, None] * fr[:, None, :]  # (E, 3, F)
        dv = p_vr.unsqueeze(2) * wu  # (2, E, 3, F)
        v_src = None
        if v is not None:
            v_src = v.index_select(0, source_v).view(2, n_edges, 3, f)
            dv = torch.addcmul(dv, (p_vv * fvv).unsqueeze(2), v_src)
        s = s + segment_sum((p_s * fs).view(2 * n_edges, f), target, n)
        dv = segment_sum(dv.view(2 * n_edges, 3 * f), target, n).view(n, 3, f)
        v = dv if v is None else v + dv
        uv, vv = linear(v, mix).split(f, -1)  # (N, 3, F) each
        nrm = torch.sqrt((vv * vv).sum(1) + norm_eps)
        zc = linear(torch.cat([s, nrm], -1), c1, cb1)
        g_vv, g_sv, g_ss = linear(silu(zc), c2, cb2).split(f, -1)
        q = (uv * vv).sum(1)
        s = s + g_sv * q + g_ss
        v = v + g_vv.unsqueeze(1) * uv
        saved.append((z1, p_s, p_vv, p_vr, wu, v_src, uv, vv, nrm, zc, g_vv, g_sv, q))
    zo = linear(s, w_o1, b_o1)
    energies = linear(silu(zo), w_o2, b_o2).squeeze(-1)
    # reverse: gs = dE/ds, gv = dE/dv, every step an ordinary (differentiable) operation
    gs = (_silu_slope(zo) * w_o2) @ w_o1  # (N, F)
    gv = torch.zeros_like(v)
    g_u = torch.zeros_like(d)
    g_filt = []
    for t in reversed(range(n_t)):
        w1, _, w2, _, mix, c1, _, c2, _ = blocks[t]
        z1, p_s, p_vv, p_vr, wu, v_src, uv, vv, nrm, zc, g_vv, g_sv, q = saved[t]
        fs, fvv, fr = filt[:, t].unbind(1)
        # update block
        g_o = torch.cat([(gv * uv).sum(1), gs * q, gs], -1)  # (N, 3F)
        g_sc, g_n = (((g_o @ c2) * _silu_slope(zc)) @ c1).split(f, -1)
        a = (gs * g_sv).unsqueeze(1)
        g_uv = torch.addcmul(a * vv, gv, g_vv.unsqueeze(1))
        g_vvf = torch.addcmul(a * uv, (g_n / nrm).unsqueeze(1), vv)
        gv = gv + torch.cat([g_uv, g_vvf], -1) @ mix
        gs = gs + g_sc
        # message block, both directions (2, E, ...)
        gs_t = gs.index_select(0, target).view(2, n_edges, f)
        gv_t = gv.index_select(0, target).view(2, n_edges, 3, f)
        g_ps = gs_t * fs
        g_fs = (gs_t * p_s).sum(0)
        g_pvr = (gv_t * wu).sum(2)
        g_wu = (gv_t * p_vr.unsqueeze(2)).sum(0)  # (E, 3, F)
        g_fr = (g_wu * u[:, :, None]).sum(1)
        g_u = g_u + (g_wu * fr[:, None, :]).sum(2)
        if v_src is not None:
            g_a = (gv_t * v_src).sum(2)  # (2, E, F)
            g_pvv = g_a * fvv
            g_fvv = (g_a * p_vv).sum(0)
            g_src = gv_t * (p_vv * fvv).unsqueeze(2)  # (2, E, 3, F)
            gv = gv + segment_sum(g_src.view(2 * n_edges, 3 * f), source_v, n).view(n, 3, f)
        else:
            g_pvv = torch.zeros_like(g_ps)
            g_fvv = torch.zeros_like(g_fs)
        g_tab = segment_sum(torch.cat([g_ps, g_pvv, g_pvr], -1).view(2 * n_edges, 3 * f),
                            source, 2 * n)  # (2N, 3F)
        g_phi = g_tab[:n] + g_tab[n:] * flip
        gs = gs + ((g_phi @ w2) * _silu_slope(z1)) @ w1
        g_filt.append(torch.stack([g_fs, g_fvv, g_fr], 1))  # (E, 3, F)
    g_filt = torch.stack(g_filt[::-1], 1).view(n_edges, -1)
    g_basis = edge_linear(g_filt, w_all.t())  # (E, R + 1); oneDNN in float32 (common.py)
    g_rbf = g_basis[:, :-1]
    g_fc = (g_rbf * rbf).sum(1) + g_basis[:, -1]
    g_r = (g_rbf * drbf).sum(1) * fc
    g_perp = (g_u - u * (g_u * u).sum(1, keepdim=True)) / r[:, None]
    ded = torch.addcmul(g_perp, (g_r / r + g_fc * dfc / rl)[:, None], d)
    return energies, ded


_STEP = CompiledOnce(_energies_and_gradient, "PaiNN", log)


def compile_failure() -> str | None:
    """Why ``torch.compile`` of the PaiNN training step failed in this process (None: it did
    not, or was not tried)."""
    return _STEP.failure


def energies_and_vector_gradient(
    painn: nn.Module,
    numbers: torch.Tensor,
    d: torch.Tensor,
    i: torch.Tensor,
    j: torch.Tensor,
    compiled: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Atomic energies (N,) (eV) and ``dE/dd`` (E, 3) (eV/Å) of their sum in the half-list
    edge vectors ``d`` (E, 3) (Å) of the edges ``(i, j)``, both differentiable (once) in the
    parameters and not in ``d``; ``compiled``: through ``torch.compile`` (the first call
    compiles, a minute or two; a compiler error falls back to the plain evaluation with a
    logged warning)."""
    radial = (painn.rbf.width, painn.cutoff - painn.cutoff_transition, painn.cutoff_transition,
              float(painn.edge_eps), float(painn.message_norm))
    args = (painn_weights(painn), numbers, d.detach(), painn.rbf.centers.to(d.dtype), i, j,
            radial, float(painn.updates[0].norm_eps))
    return _STEP(*args, compiled=compiled)

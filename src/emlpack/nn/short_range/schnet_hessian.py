"""Exact second derivatives of the SchNet energy in a set of coordinates, in node space.

For the Hessian of ``E_sr(r(x))`` in m coordinates ``x`` (e.g. all positions and the cell),
with ``r`` the E half-list edge lengths and ``J = dr/dx`` (E, m):

``H = J^T (d2E/dr dr) J + sum_e (dE/dr_e) d2r_e/dx2``;

:func:`schnet_edge_hessian` (SchNet's capability
:meth:`~emlpack.nn.short_range.schnet.SchNet.length_hessian`) returns ``dE/dr`` and the first
term, the caller adds the second (a cheap function of the geometry). Two exact rewritings
make the first term cheap:

* the filters enter through their second-order Taylor expansion in ``r``
  (:meth:`SchNet.filter_taylor`), so no filter network is differentiated;
* at fixed filters the convolution ``conv_i = sum_j a_j W_ij`` (both directions of every
  half-list edge) is, per channel k, a symmetric N x N matrix ``M_k`` acting on the node
  features. All m directional derivatives of the gradient (forward over reverse, written out
  for the folded network of :meth:`SchNet.folded_weights`) are then batched matrix products
  in node space; the filter derivatives enter only through the sparse ``J``
  (``A_t = S(w'_t a_t)``, ``B_t = S(w'_t g_t)`` below), so no m x E x K tensor is formed.

Cost: about ``m N (2 F^2 + F^2 + ...)`` multiply-adds in dense products (F = 4 K, the folded
output layer's width, 512 in the paper's model) instead of m reverse passes through the filter
network; memory ``~45 K N c`` numbers for a chunk of c directions (tangents and spreads).
"""

from __future__ import annotations

import torch
from torch import nn

from emlpack.nn.scatter import segment_sum
from emlpack.nn.short_range.common import softplus_slopes


def _node_conv(m: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """``conv[i, k] = sum_j M[k, i, j] a[j, k]`` for node features ``a`` (N, K)."""
    return torch.bmm(m, a.T[:, :, None])[:, :, 0].T


def _padded_groups(side: torch.Tensor, n: int, n_edges: int) -> torch.Tensor:
    """(N, D) edge indices grouped by ``side[e]`` (D = largest group), padded with ``n_edges``."""
    counts = torch.bincount(side, minlength=n)
    order = torch.argsort(side, stable=True)
    start = torch.cumsum(counts, 0) - counts
    slot = torch.arange(n_edges, device=side.device) - start[side[order]]
    pad = torch.full((n, max(int(counts.max()), 1)), n_edges, dtype=torch.long,
                     device=side.device)
    pad[side[order], slot] = order
    return pad


def schnet_edge_hessian(
    schnet: nn.Module,
    numbers: torch.Tensor,
    r: torch.Tensor,
    i: torch.Tensor,
    j: torch.Tensor,
    jac: torch.Tensor,
    tangent_dtype: torch.dtype | None = None,
    max_numbers: int = 2**25,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(dE/dr (E,), J^T (d2E/dr dr) J (m, m))`` of the summed energy (eV, Å) of the
    :class:`~emlpack.nn.short_range.schnet.SchNet` ``schnet`` for one structure with particle
    numbers ``numbers`` (N,), half-list edges ``(i, j)`` of lengths ``r`` (E,) and edge
    Jacobian ``jac = dr/dx`` (E, m), in ``r``'s dtype.

    ``tangent_dtype`` (default: ``r``'s): dtype of the m directional derivatives (the dense
    products); ``torch.float32`` halves their cost at ~1e-7 relative error of the result.
    ``max_numbers``: the directions are processed in chunks whose tangent arrays hold about
    this many numbers (default 2^25, ~270 MB in float64; beta-glycine's 159 directions are
    one chunk); with several chunks the spreads of each pair of chunks are recomputed.
    """
    dt = r.dtype
    tdt = tangent_dtype or dt
    fw = schnet.folded_weights(dt, r.device)
    taylor = schnet.filter_taylor(r)
    n = numbers.numel()
    n_edges = r.numel()
    m_dir = jac.shape[1]
    softplus = nn.functional.softplus
    # ---------------------------------------------------------------- value and gradient
    mats, acts = [], []  # per interaction: M (K, N, N); (a, p)
    idx_pairs = torch.cat([i * n + j, j * n + i])
    us = []
    for t, (_, _, _, _, wc, bc) in enumerate(fw["filters"]):
        w0 = taylor[t][0]
        k = w0.shape[1]
        mat = segment_sum(torch.cat([w0, w0]), idx_pairs, n * n)
        mat = mat.reshape(n, n, k).permute(2, 0, 1).contiguous()
        a = fw["tables"][t].index_select(0, numbers)
        for s, c in enumerate(fw["cross"][t]):
            a = torch.addmm(a, us[s], c)
        p = torch.addmm(bc, _node_conv(mat, a), wc)
        u = softplus(p)
        mats.append(mat)
        acts.append((a, p))
        us.append(u)
    (wh1, bh1), (wh2, _) = fw["heads"]
    z1 = torch.addmm(fw["table_out"].index_select(0, numbers), torch.cat(us, 1), fw["w_out"])
    s1, c1 = softplus_slopes(z1)
    z2 = torch.addmm(bh1, softplus(z1), wh1)
    s2, c2 = softplus_slopes(z2)
    gz2 = s2 * wh2[:, 0]
    gy1 = gz2 @ wh1.T
    gu_all = (s1 * gy1) @ fw["w_out"].T
    n_int = len(fw["filters"])
    k = us[0].shape[1]
    gus = [gu_all[:, t * k : (t + 1) * k].clone() for t in range(n_int)]
    gconvs = [None] * n_int
    grad_r = r.new_zeros(n_edges)
    curv_r = r.new_zeros(n_edges)  # sum_t sum_k dE/dW_t W''_t
    for t in reversed(range(n_int)):
        _, _, _, _, wc, _ = fw["filters"][t]
        a, p = acts[t]
        sp1, _ = softplus_slopes(p)
        gconv = (sp1 * gus[t]) @ wc.T
        ga = _node_conv(mats[t], gconv)
        for s, c in enumerate(fw["cross"][t]):
            gus[s] = gus[s] + ga @ c.T
        gw = gconv.index_select(0, i) * a.index_select(0, j) + gconv.index_select(
            0, j
        ) * a.index_select(0, i)
        grad_r = grad_r + (gw * taylor[t][1]).sum(1)
        curv_r = curv_r + (gw * taylor[t][2]).sum(1)
        gconvs[t] = gconv
    # ---------------------------------------------------------------- m directions
    # The m directions are batched with features first, (K, N, m): every dense layer is one
    # matrix product and every convolution one batched product with M (K, N, N).
    # Edges grouped by their first (i) and second (j) particle, padded to (N, D) with a
    # sentinel edge E of zero Jacobian, so that the spreads below are batched products.
    pads = [_padded_groups(side, n, n_edges) for side in (i, j)]
    jac_ext = torch.cat([jac, jac.new_zeros(1, m_dir)])
    jac_pad = [jac_ext[pad] for pad in pads]  # (N, D, m) each

    def spread(w1: torch.Tensor, x: torch.Tensor, cols: slice) -> torch.Tensor:
        """``S[k, n, m] = sum_e J[e, m] w1[e, k] (x[j_e, k] [n = i_e] + x[i_e, k] [n = j_e])``
        (the convolution's derivative along direction m at fixed features ``x``), for the
        directions ``cols``."""
        out = None
        for jp, pad, other in ((jac_pad[0], pads[0], j), (jac_pad[1], pads[1], i)):
            y = torch.cat([w1 * x.index_select(0, other), w1.new_zeros(1, k)])
            y = y[pad].transpose(1, 2)  # (N, K, D)
            jp = jp[:, :, cols]
            out = torch.bmm(y, jp) if out is None else out.baddbmm_(y, jp)  # (N, K, m)
        return out.transpose(0, 1).to(tdt).contiguous()

    def spreads(cols: slice) -> tuple[list, list]:
        return ([spread(taylor[t][1], acts[t][0], cols) for t in range(n_int)],
                [spread(taylor[t][1], gconvs[t], cols) for t in range(1, n_int)])

    def node(x: torch.Tensor) -> torch.Tensor:
        """Per-particle factor (N, F) as (F, N, 1) in the tangent dtype."""
        return x.T.to(tdt).contiguous()[:, :, None]

    def cast(x: torch.Tensor) -> torch.Tensor:
        return x.to(tdt)

    mats_t = [cast(x) for x in mats]
    wcs = [cast(f[4]) for f in fw["filters"]]
    # a_t depends on u_0..u_{t-1} through the stacked (t K, K) matrix [C_0t; ...; C_(t-1)t]
    cross = [cast(torch.cat(cs, 0)) if cs else None for cs in fw["cross"]]
    w_out, wh1_t = cast(fw["w_out"]), cast(wh1)
    slopes = [softplus_slopes(acts[t][1]) for t in range(n_int)]
    node_s1, node_c2, node_c1 = node(s1), node(c2 * wh2[:, 0]), node(c1 * gy1)
    node_sp = [(node(sp1), node(sp2 * gus[t])) for t, (sp1, sp2) in enumerate(slopes)]

    def directions(spread_a: list, spread_g: list) -> tuple[list, list]:
        """Forward over reverse along the c directions of ``spread_a``: per interaction the
        directional derivatives of ``dE/dconv_t`` and of ``a_t`` (K, N, c)."""
        c = spread_a[0].shape[2]
        nc = n * c
        d_u = torch.empty(n_int * k, n, c, dtype=tdt, device=r.device)
        das, dps = [None], []
        for t in range(n_int):
            if t == 0:
                dconv = spread_a[0]
            else:
                da = (cross[t].T @ d_u[: t * k].view(t * k, nc)).view(k, n, c)
                dconv = torch.baddbmm(spread_a[t], mats_t[t], da)
                das.append(da)
            dp = (wcs[t].T @ dconv.view(k, nc)).view(k, n, c)
            torch.mul(node_sp[t][0], dp, out=d_u[t * k : (t + 1) * k])
            dps.append(dp)
        dz1 = (w_out.T @ d_u.view(-1, nc)).view(-1, n, c)
        dz2 = (wh1_t.T @ (node_s1 * dz1).view(-1, nc)).view(-1, n, c)
        back = (wh1_t @ (node_c2 * dz2).view(-1, nc)).view(-1, n, c)
        dgz1 = torch.addcmul(node_s1 * back, node_c1, dz1)
        dg_u = (w_out @ dgz1.view(-1, nc)).view(-1, n, c)
        dgconvs = [None] * n_int
        for t in reversed(range(n_int)):
            dgp = torch.addcmul(node_sp[t][0] * dg_u[t * k : (t + 1) * k], node_sp[t][1], dps[t])
            dgconvs[t] = (wcs[t] @ dgp.view(k, nc)).view(k, n, c)
            if t > 0:
                dga = torch.baddbmm(spread_g[t - 1], mats_t[t], dgconvs[t]).view(k, nc)
                dg_u[: t * k].view(t * k, nc).addmm_(cross[t], dga)
        return dgconvs, das

    def contract(dgconvs: list, das: list, spread_a: list, spread_g: list) -> torch.Tensor:
        """``H[m, x] = sum_t dgconv_t[m] . A_t[x] + da_t[m] . B_t[x]``."""
        out = dgconvs[0].view(-1, dgconvs[0].shape[2]).T @ spread_a[0].view(k * n, -1)
        for t in range(1, n_int):
            out.addmm_(dgconvs[t].view(k * n, -1).T, spread_a[t].view(k * n, -1))
            out.addmm_(das[t].view(k * n, -1).T, spread_g[t - 1].view(k * n, -1))
        return out

    # directions in chunks so that the ~30 (K, N, chunk) tangent arrays stay within budget
    chunk = max(1, min(m_dir, max_numbers // (30 * k * n)))
    chunks = [slice(c, min(c + chunk, m_dir)) for c in range(0, m_dir, chunk)]
    if len(chunks) == 1:
        spread_a, spread_g = spreads(chunks[0])
        hess = contract(*directions(spread_a, spread_g), spread_a, spread_g)
    else:
        hess = torch.empty(m_dir, m_dir, dtype=tdt, device=r.device)
        for rows in chunks:
            own = spreads(rows)
            dgconvs, das = directions(*own)
            for cols in chunks:
                other = own if cols == rows else spreads(cols)
                hess[rows, cols] = contract(dgconvs, das, *other)
    hess = hess.to(dt) + jac.T @ (curv_r[:, None] * jac)
    return grad_r, hess

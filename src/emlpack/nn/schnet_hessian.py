"""Exact second derivatives of the SchNet energy in a set of coordinates, in node space.

For the Hessian of ``E_sr(r(x))`` in m coordinates ``x`` (e.g. all positions and the cell),
with ``r`` the E half-list edge lengths and ``J = dr/dx`` (E, m):

``H = J^T (d2E/dr dr) J + sum_e (dE/dr_e) d2r_e/dx2``;

:func:`schnet_edge_hessian` returns ``dE/dr`` and the first term, the caller adds the second
(a cheap function of the geometry). Two exact rewritings make the first term cheap:

* the filters enter through their second-order Taylor expansion in ``r``
  (:meth:`SchNet.filter_taylor`), so no filter network is differentiated;
* at fixed filters the convolution ``conv_i = sum_j a_j W_ij`` (both directions of every
  half-list edge) is, per channel k, a symmetric N x N matrix ``M_k`` acting on the node
  features. All m directional derivatives of the gradient (forward over reverse, written out
  for the folded network of :meth:`SchNet.folded_weights`) are then batched matrix products
  in node space; the filter derivatives enter only through the sparse ``J``
  (``A_t = S(w'_t a_t)``, ``B_t = S(w'_t g_t)`` below), so no m x E x K tensor is formed.

Cost: about ``m N (2 F^2 + 3 F F/2 + ...)`` multiply-adds in dense products (F = 4 K for the
folded output layer) instead of m reverse passes through the filter network; memory
``~ 10 m N K`` numbers for the tangents.
"""

from __future__ import annotations

import torch
from torch import nn

from emlpack.nn.scatter import segment_sum
from emlpack.nn.schnet import SchNet, softplus_slopes


def _node_conv(m: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """``conv[..., i, k] = sum_j M[k, i, j] a[..., j, k]`` for ``a`` (N, K) or (B, N, K)."""
    if a.ndim == 2:
        return torch.bmm(m, a.T[:, :, None])[:, :, 0].T
    b, n, k = a.shape
    out = torch.bmm(m, a.permute(2, 1, 0))  # (K, N, B)
    return out.permute(2, 1, 0)


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
    schnet: SchNet,
    numbers: torch.Tensor,
    r: torch.Tensor,
    i: torch.Tensor,
    j: torch.Tensor,
    jac: torch.Tensor,
    tangent_dtype: torch.dtype | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(dE/dr (E,), J^T (d2E/dr dr) J (m, m))`` of the summed SchNet energy (eV, Å) of one
    structure with particle numbers ``numbers`` (N,), half-list edges ``(i, j)`` of lengths
    ``r`` (E,) and edge Jacobian ``jac = dr/dx`` (E, m), in ``r``'s dtype.

    ``tangent_dtype`` (default: ``r``'s): dtype of the m directional derivatives (the dense
    products); ``torch.float32`` halves their cost at ~1e-7 relative error of the result.
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
    mats, acts = [], []  # per interaction: M (K, N, N); (a, p, u)
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
    nm = n * m_dir

    def spread(w1: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``S[k, n, m] = sum_e J[e, m] w1[e, k] (x[j_e, k] [n = i_e] + x[i_e, k] [n = j_e])``
        (the convolution's derivative along direction m at fixed features ``x``)."""
        out = None
        for jp, pad, other in ((jac_pad[0], pads[0], j), (jac_pad[1], pads[1], i)):
            y = torch.cat([w1 * x.index_select(0, other), w1.new_zeros(1, k)])
            y = y[pad].transpose(1, 2)  # (N, K, D)
            out = torch.bmm(y, jp) if out is None else out.baddbmm_(y, jp)  # (N, K, m)
        return out.transpose(0, 1).to(tdt).contiguous()

    def node(x: torch.Tensor) -> torch.Tensor:
        """Per-particle factor (N, F) as (F, N, 1) in the tangent dtype."""
        return x.T.to(tdt).contiguous()[:, :, None]

    def cast(x: torch.Tensor) -> torch.Tensor:
        return x.to(tdt)

    spread_a = [spread(taylor[t][1], acts[t][0]) for t in range(n_int)]
    spread_g = [spread(taylor[t][1], gconvs[t]) for t in range(1, n_int)]
    mats_t = [cast(x) for x in mats]
    wcs = [cast(f[4]) for f in fw["filters"]]
    # a_t depends on u_0..u_{t-1} through the stacked (t K, K) matrix [C_0t; ...; C_(t-1)t]
    cross = [cast(torch.cat(cs, 0)) if cs else None for cs in fw["cross"]]
    w_out, wh1_t = cast(fw["w_out"]), cast(wh1)
    slopes = [softplus_slopes(acts[t][1]) for t in range(n_int)]
    d_u = torch.empty(n_int * k, n, m_dir, dtype=tdt, device=r.device)
    das, dps = [], []
    for t in range(n_int):
        if t == 0:
            dconv, da = spread_a[0], None
        else:
            da = (cross[t].T @ d_u[: t * k].view(t * k, nm)).view(k, n, m_dir)
            dconv = torch.baddbmm(spread_a[t], mats_t[t], da)
        dp = (wcs[t].T @ dconv.view(k, nm)).view(k, n, m_dir)
        torch.mul(node(slopes[t][0]), dp, out=d_u[t * k : (t + 1) * k])
        das.append(da)
        dps.append(dp)
    dz1 = (w_out.T @ d_u.view(-1, nm)).view(-1, n, m_dir)
    dz2 = (wh1_t.T @ (node(s1) * dz1).view(-1, nm)).view(-1, n, m_dir)
    dgz2 = node(c2 * wh2[:, 0]) * dz2
    dgz1 = node(c1 * gy1) * dz1 + node(s1) * (wh1_t @ dgz2.view(-1, nm)).view(-1, n, m_dir)
    dg_u = (w_out @ dgz1.view(-1, nm)).view(-1, n, m_dir)

    hess = torch.zeros(m_dir, m_dir, dtype=tdt, device=r.device)
    for t in reversed(range(n_int)):
        sp1, sp2 = slopes[t]
        dgp = torch.addcmul(node(sp1) * dg_u[t * k : (t + 1) * k], node(sp2 * gus[t]), dps[t])
        dgconv = (wcs[t] @ dgp.view(k, nm)).view(k, n, m_dir)
        hess.addmm_(dgconv.view(-1, m_dir).T, spread_a[t].view(-1, m_dir))
        if t > 0:
            dga = torch.baddbmm(spread_g[t - 1], mats_t[t], dgconv).view(k, nm)
            dg_u[: t * k].view(t * k, nm).addmm_(cross[t], dga)
            hess.addmm_(das[t].view(-1, m_dir).T, spread_g[t - 1].view(-1, m_dir))
    hess = hess.to(dt) + jac.T @ (curv_r[:, None] * jac)
    return grad_r, hess

"""PaiNN short-range energy: equivariant message passing on cores and electron pairs alike.

The polarizable interaction neural network of Schütt, Unke and Gastegger (ICML 2021), with the
eMLP's cutoff and species (one embedding row per particle number: Z for cores, 99 for electron
pairs). Every particle carries scalar features ``s`` (N, F) and vector features ``v`` (N, 3, F)
(``v = 0`` at the start). Interaction ``t`` is a message block and an update block:

* message: ``phi = W_2 silu(W_1 s + b_1) + b_2`` (N, 3F) and the filters
  ``W_ij = (rbf(r_ij) W_f + b_f) f_c(r_ij) / message_norm`` (E, 3F, one slice of a single
  linear map for all interactions); split ``phi_j * W_ij`` into ``(a_s, a_vv, a_vr)`` and add
  ``ds_i = sum_j a_s``, ``dv_i = sum_j a_vv v_j + a_vr u_ij``;
* update (gated): ``(U v, V v)`` (no bias), ``(g_vv, g_sv, g_ss) = MLP([s, n(V v)])``
  (``2F -> F -> 3F``, SiLU), ``v += g_vv U v``, ``s += g_sv <U v, V v> + g_ss``;
* output: ``F -> F/2 -> 1`` (SiLU) on ``s``: one energy (eV) per particle.

Conventions of the short-range protocol: ``(i, j)`` is the half edge list and
``vectors = r_j - r_i`` (Å, image shift included); the message to ``i`` from ``j`` uses
``u_ij`` and the one to ``j`` from ``i`` uses ``-u_ij``. Both directions share the filter of
the edge and go through one gather and one scatter (no concatenated copy of the filters).

Smooth everywhere, zero-length edges included (an electron pair may sit on a core):

* ``r = sqrt(|d|^2 + edge_eps)`` and ``u = d / r``: ``u`` vanishes linearly at ``d = 0``
  instead of jumping (no 0/0), and every edge function is analytic in ``d``. The smoothing
  length ``sqrt(edge_eps)`` (0.1 Å by default) bounds the slope of ``u`` (``1/sqrt(edge_eps)``
  at ``d = 0``) and so the forces and Hessians of a pair that sits on a core; above it the
  learned radial filters absorb the factor ``|d| / r`` (in mini-eQM7, 99 % of the pairs sit
  more than 0.29 Å from their nearest core, the closest 0.10 Å).
* Radial basis: Gaussians in ``r`` (:class:`emlpack.nn.short_range.schnet.GaussianBasis`);
  cutoff :func:`emlpack.geometry.cosine_cutoff` of the edge's length ``|d|`` (as SchNet's:
  ``sqrt(|d|^2 + 1e-20)``, so the switch and its kinks sit where the neighbour list and every
  family put them; flat, hence smooth, at ``d = 0``) (flat up to ``cutoff - transition``, 0 at
  ``cutoff``, zero slope at both ends): energies and forces are continuous as an edge crosses
  the cutoff.
* ``n(x) = sqrt(|x|^2 + norm_eps)`` replaces PaiNN's ``|x|``: the norm has a cone at ``x = 0``
  (e.g. the vector features of an atom at a centre of symmetry), whose curvature would
  dominate Hessians there; with ``norm_eps = 1`` it is smooth with curvature <= 1.

Written here rather than taken from a library (evaluated 2026-12, torch 2.13 CPU): SchNetPack
2.1.1's ``PaiNN`` wants the full edge list (messages scatter to ``idx_i`` only), gives NaN at
a zero-length edge (``r / torch.norm(r)``) and has no flat part in its cosine cutoff;
mace-torch 0.3.16 pins ``e3nn==0.4.4``, takes positions, a full edge list and shifts, and its
Bessel basis ``sin(x)/x`` and normalised directions give NaN energies at a zero-length edge.
"""

from __future__ import annotations

import torch
from torch import nn

from emlpack import geometry
from emlpack.errors import InputError
from emlpack.nn.scatter import segment_sum
from emlpack.nn.short_range.common import edge_lengths
from emlpack.nn.short_range.painn_gradient import energies_and_vector_gradient
from emlpack.nn.short_range.schnet import GaussianBasis

__all__ = ["PaiNN"]


class _Update(nn.Module):
    """PaiNN's update block: gated mixing of a particle's own scalar and vector features."""

    def __init__(self, n_features: int, norm_eps: float) -> None:
        super().__init__()
        self.n_features = n_features
        self.norm_eps = norm_eps
        self.mix = nn.Linear(n_features, 2 * n_features, bias=False)
        self.context = nn.Sequential(
            nn.Linear(2 * n_features, n_features), nn.SiLU(), nn.Linear(n_features, 3 * n_features)
        )

    def forward(self, s: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Updated ``(s, v)`` from scalar ``s`` (N, F) and vector ``v`` (N, 3, F) features."""
        uv, vv = self.mix(v).split(self.n_features, -1)  # (N, 3, F) each
        norm = torch.sqrt((vv * vv).sum(1) + self.norm_eps)  # (N, F)
        g_vv, g_sv, g_ss = self.context(torch.cat([s, norm], -1)).split(self.n_features, -1)
        return s + g_sv * (uv * vv).sum(1) + g_ss, v + g_vv.unsqueeze(1) * uv


class PaiNN(nn.Module):
    """Per-particle short-range energies (eV) from particle numbers and half-list edge vectors.

    Hyperparameters: ``n_features`` F, ``n_interactions`` T, ``n_rbf`` Gaussians with centres
    from ``rbf_start`` to ``rbf_end`` (default ``cutoff``) (Å), ``cutoff`` and
    ``cutoff_transition`` (Å), ``n_embeddings`` rows (particle numbers below it; 99 is the
    electron pair), ``message_norm`` (messages are divided by it), ``edge_eps`` (Å^2) and
    ``norm_eps`` (see the module docstring).

    Capability :class:`~emlpack.nn.short_range.protocol.VectorGradient` (training):
    :meth:`energies_and_vector_gradient`.
    """

    def __init__(
        self,
        n_features: int = 64,
        n_interactions: int = 3,
        n_rbf: int = 20,
        cutoff: float = 4.0,
        cutoff_transition: float = 0.5,
        n_embeddings: int = 100,
        rbf_start: float = 0.0,
        rbf_end: float | None = None,
        message_norm: float = 1.0,
        edge_eps: float = 1e-2,
        norm_eps: float = 1.0,
    ) -> None:
        super().__init__()
        if not 0.0 < cutoff_transition <= cutoff:
            raise InputError(f"PaiNN: cutoff_transition must be in (0, cutoff], got "
                             f"{cutoff_transition} with cutoff {cutoff}")
        if edge_eps <= 0.0 or norm_eps <= 0.0:
            raise InputError(f"PaiNN: edge_eps and norm_eps must be positive, got {edge_eps} "
                             f"and {norm_eps}")
        self.n_features = n_features
        self.n_interactions = n_interactions
        self.cutoff = cutoff
        self.cutoff_transition = cutoff_transition
        self.message_norm = message_norm
        self.edge_eps = edge_eps
        self.embedding = nn.Embedding(n_embeddings, n_features)
        self.rbf = GaussianBasis(n_rbf, rbf_start, cutoff if rbf_end is None else rbf_end)
        self.filters = nn.Linear(n_rbf, 3 * n_features * n_interactions)
        self.messages = nn.ModuleList(
            nn.Sequential(nn.Linear(n_features, n_features), nn.SiLU(),
                          nn.Linear(n_features, 3 * n_features))
            for _ in range(n_interactions)
        )
        self.updates = nn.ModuleList(_Update(n_features, norm_eps) for _ in range(n_interactions))
        half = n_features // 2
        self.output = nn.Sequential(nn.Linear(n_features, half), nn.SiLU(), nn.Linear(half, 1))

    def forward(
        self, numbers: torch.Tensor, vectors: torch.Tensor, i: torch.Tensor, j: torch.Tensor
    ) -> torch.Tensor:
        """Atomic energies (N,) (eV).

        Args:
            numbers: (N,) particle numbers (Z for cores, 99 for electron pairs).
            vectors: (E, 3) edge vectors ``r_j - r_i`` (+ image shift) (Å); the network works
                in their dtype.
            i, j: (E,) the half edge list (each unordered pair within the cutoff once).
        """
        n, n_edges = numbers.shape[0], vectors.shape[0]
        f, n_t = self.n_features, self.n_interactions
        r = torch.sqrt((vectors * vectors).sum(-1) + self.edge_eps)  # (E,)
        u = vectors / r[:, None]  # (E, 3), smooth, 0 at d = 0
        fc = geometry.cosine_cutoff(edge_lengths(vectors), self.cutoff, self.cutoff_transition,
                                    xp=torch)
        if self.message_norm != 1.0:
            fc = fc / self.message_norm
        # filters (rbf W_f + b_f) f_c as products [rbf f_c, f_c] [W_f; b_f] (no broadcast of
        # f_c over wide outputs), one per interaction and channel (contiguous results, whose
        # gradients need no zero-filled slices); the direction filters W_vr u (3E, F) come
        # from the same product on [rbf f_c, f_c] u, the 3 components as rows
        basis = torch.cat([self.rbf(r) * fc[:, None], fc[:, None]], 1)  # (E, R + 1)
        basis_u = (basis[:, None, :] * u[:, :, None]).view(3 * n_edges, -1)  # (3E, R + 1)
        weights = torch.cat([self.filters.weight, self.filters.bias[:, None]], 1)
        weights = weights.view(n_t, 3, f, -1).unbind(0)  # T x (3, F, R + 1)
        # both directions of every edge: to i from j along u, to j from i along -u (the sign
        # rides on the gathered rows: sources i read the table's second, negated half)
        source = torch.cat([j, i + n])  # (2E,) rows of the (2N, 3F) table below
        source_v, target = torch.cat([j, i]), torch.cat([i, j])
        flip = torch.ones(3 * f, dtype=vectors.dtype, device=vectors.device)
        flip[2 * f:] = -1.0
        s = self.embedding(numbers).to(vectors.dtype)  # (N, F)
        v = None  # (N, 3, F); zero before the first message
        for t in range(n_t):
            phi = self.messages[t](s)  # (N, 3F)
            phi = torch.cat([phi, phi * flip]).index_select(0, source).view(2, n_edges, 3 * f)
            p_s, p_vv, p_vr = phi.split(f, -1)  # (2, E, F) each
            w_s, w_vv, w_vr = weights[t].unbind(0)  # (F, R + 1) each
            wu = (basis_u @ w_vr.T).view(n_edges, 3, f)
            dv = p_vr.unsqueeze(2) * wu  # (2, E, 3, F)
            if v is not None:
                v_source = v.index_select(0, source_v).view(2, n_edges, 3, f)
                dv = torch.addcmul(dv, (p_vv * (basis @ w_vv.T)).unsqueeze(2), v_source)
            ds = (p_s * (basis @ w_s.T)).view(2 * n_edges, f)
            s = s + segment_sum(ds, target, n)
            dv = segment_sum(dv.view(2 * n_edges, 3 * f), target, n).view(n, 3, f)
            v = dv if v is None else v + dv
            s, v = self.updates[t](s, v)
        return self.output(s).squeeze(-1)

    def energies_and_vector_gradient(
        self,
        numbers: torch.Tensor,
        vectors: torch.Tensor,
        i: torch.Tensor,
        j: torch.Tensor,
        compiled: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Capability :class:`~emlpack.nn.short_range.protocol.VectorGradient`: atomic
        energies (N,) (eV) and ``dE/d(vectors)`` (E, 3) (eV/Å), the reverse pass written out
        (:func:`~emlpack.nn.short_range.painn_gradient.energies_and_vector_gradient`)."""
        return energies_and_vector_gradient(self, numbers, vectors, i, j, compiled=compiled)

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

Distances are ``sqrt(|d|^2 + 1e-20)`` as in the reference (finite gradient at d = 0).
The filter of an unordered pair is computed once and the message is scattered both ways.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from emlpack.nn.scatter import segment_sum

LN2 = math.log(2.0)


def shifted_softplus(x: torch.Tensor) -> torch.Tensor:
    """ssp(x) = ln(1 + e^x) - ln 2."""
    return nn.functional.softplus(x) - LN2


def cosine_cutoff(r: torch.Tensor, cutoff: float, transition: float) -> torch.Tensor:
    """1 below ``cutoff - transition``, cosine switch to 0 at ``cutoff`` (Å)."""
    start = cutoff - transition
    x = torch.clamp((r - start) / transition, 0.0, 1.0)
    return 0.5 * (1.0 + torch.cos(math.pi * x))


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

    def forward(
        self,
        h: torch.Tensor,
        rbf: torch.Tensor,
        fcut: torch.Tensor,
        i: torch.Tensor,
        j: torch.Tensor,
        norm: float,
    ) -> torch.Tensor:
        w = shifted_softplus(self.filter2(shifted_softplus(self.filter1(rbf)))) * fcut[:, None]
        a = self.atom_in(h)
        messages = torch.cat([a[j] * w, a[i] * w], dim=0)
        conv = segment_sum(messages, torch.cat([i, j]), a.shape[0]) / norm
        return h + self.atom_out(shifted_softplus(self.conv_out(conv)))


class SchNet(nn.Module):
    """Per-particle short-range energies (eV) of a batch of structures."""

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
        n_embeddings: int = 100,
    ) -> None:
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
        self, numbers: torch.Tensor, r: torch.Tensor, i: torch.Tensor, j: torch.Tensor
    ) -> torch.Tensor:
        """Atomic energies (N,) from particle numbers and the half-list edge lengths ``r`` (Å)."""
        h = self.embedding(numbers).to(r.dtype)
        rbf = self.rbf(r)
        fcut = cosine_cutoff(r, self.cutoff, self.cutoff_transition)
        for block in self.interactions:
            h = block(h, rbf, fcut, i, j, self.message_norm)
        h = shifted_softplus(self.output[0](h))
        h = shifted_softplus(self.output[1](h))
        return self.output[2](h).squeeze(-1)

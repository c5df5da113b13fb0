"""Long-range electrostatics of Gaussian charges and the external-field energy (eV, Å, e).

Every particle carries a spherical Gaussian charge of width parameter ``gamma`` (1/Å; the
paper's gamma = 1/(2 sigma) = 0.3928/Å). The interaction of two such charges is
``k_e q_i q_j erf(gamma r) / r`` with ``k_e = 14.3996 eV·Å`` (units.COULOMB_EV_A).

* Molecules: all pairs (no truncation) plus the self energy ``k_e gamma/sqrt(pi) sum q^2``.
  The reference evaluates ``erf(gamma r)/(r + 1e-10)``; we mirror that 1e-10 Å (``eps``), which
  changes energies by ~1e-7 eV and is needed to agree with the reference to 1e-8.
* Crystals: Ewald summation with splitting parameter alpha = gamma. The real-space term
  ``erf(gamma r)/r - erf(alpha r)/r`` vanishes and the Gaussian self energy cancels the Ewald
  self correction, so only the reciprocal sum remains:
  ``E = k_e (2 pi / V) sum_{k != 0} |S(k)|^2 exp(-k^2 / (4 gamma^2)) / k^2``,
  ``S(k) = sum_i q_i exp(i k.r_i)``, ``k = 2 pi n . cell^-T``. Cells must be neutral.
* External field: ``E_field = -sum_i q_i E . r_i`` (E in V/Å).
"""

from __future__ import annotations

import math

import torch

from emlpack.nn.scatter import segment_sum
from emlpack.units import COULOMB_EV_A, SQRT_PI


def _distance(d: torch.Tensor) -> torch.Tensor:
    return torch.sqrt((d * d).sum(-1) + 1e-20)


def coulomb_molecular(
    positions: torch.Tensor,
    charges: torch.Tensor,
    pair_i: torch.Tensor,
    pair_j: torch.Tensor,
    batch: torch.Tensor,
    is_molecule: torch.Tensor,
    n_structures: int,
    gamma: float,
    eps: float = 1e-10,
) -> torch.Tensor:
    """Gaussian-charge Coulomb energy (eV) of each molecular structure, self energy included.

    ``pair_i``, ``pair_j`` list every unordered pair of particles of the molecular structures
    once; ``is_molecule`` (B,) selects the structures that get a self energy.
    """
    energy = positions.new_zeros(n_structures)
    if pair_i.numel():
        r = _distance(positions[pair_j] - positions[pair_i])
        e = charges[pair_i] * charges[pair_j] * torch.erf(gamma * r) / (r + eps)
        energy = energy + segment_sum(e, batch[pair_i], n_structures)
    self_energy = segment_sum(charges * charges, batch, n_structures)
    energy = energy + torch.where(is_molecule, self_energy, 0.0) * (gamma / SQRT_PI)
    return COULOMB_EV_A * energy


def ewald_reciprocal(
    positions: torch.Tensor,
    charges: torch.Tensor,
    batch: torch.Tensor,
    cell: torch.Tensor,
    kvec_n: torch.Tensor,
    kvec_batch: torch.Tensor,
    gamma: float,
) -> torch.Tensor:
    """Reciprocal-space Ewald energy (eV) of each structure (zero for structures without k).

    ``kvec_n`` (K, 3) are the integer triples n of the k vectors ``k = 2 pi n . cell^-T``;
    they are fixed while ``cell`` may carry gradients (strain derivatives).
    """
    n_structures = cell.shape[0]
    energy = positions.new_zeros(n_structures)
    if kvec_n.numel() == 0:
        return energy
    periodic = torch.unique(kvec_batch)
    inv = torch.zeros_like(cell)
    inv[periodic] = torch.linalg.inv(cell[periodic])
    k = 2.0 * math.pi * torch.einsum("kj,kaj->ka", kvec_n, inv[kvec_batch])
    k2 = (k * k).sum(-1)
    # (k, particle) combinations of the same structure
    kk, pp = _same_structure_products(kvec_batch, batch)
    phase = (k[kk] * positions[pp]).sum(-1)
    q = charges[pp]
    s_re = segment_sum(q * torch.cos(phase), kk, k.shape[0])
    s_im = segment_sum(q * torch.sin(phase), kk, k.shape[0])
    term = (s_re * s_re + s_im * s_im) * torch.exp(-k2 / (4.0 * gamma * gamma)) / k2
    volume = torch.abs(torch.linalg.det(cell[periodic]))
    sums = segment_sum(term, kvec_batch, n_structures)
    energy = energy.index_put((periodic,), sums[periodic] * (2.0 * math.pi) / volume)
    return COULOMB_EV_A * energy


def _same_structure_products(
    kvec_batch: torch.Tensor, batch: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Index pairs (k, particle) belonging to the same structure."""
    n_per = torch.bincount(batch)
    start = torch.cumsum(n_per, 0) - n_per
    counts = n_per[kvec_batch]
    kk = torch.repeat_interleave(torch.arange(kvec_batch.numel(), device=batch.device), counts)
    first = torch.repeat_interleave(start[kvec_batch], counts)
    within = torch.arange(kk.numel(), device=batch.device) - torch.repeat_interleave(
        torch.cumsum(counts, 0) - counts, counts
    )
    return kk, first + within


def field_energy(
    positions: torch.Tensor,
    charges: torch.Tensor,
    batch: torch.Tensor,
    field: torch.Tensor,
) -> torch.Tensor:
    """External-field energy ``-sum_i q_i E . r_i`` (eV) of each structure (E in V/Å)."""
    per_particle = -charges * (positions * field[batch]).sum(-1)
    return segment_sum(per_particle, batch, field.shape[0])

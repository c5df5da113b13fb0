"""Batched model input: many structures concatenated without padding.

Particles of all structures are concatenated (per structure: cores first, then electron
pairs); ``batch`` maps each particle to its structure. Topology (neighbour edges with image
shifts, the molecular all-pairs list, the Ewald k set as integer triples) is computed once in
:func:`collate` and is held fixed inside derivatives (forces, stress, Hessians).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING

import numpy as np
import torch

from emlpack.nn.neighbors import NeighborListError, all_pairs, half_neighbor_list
from emlpack.structure import PAIR_NUMBER, Structure

if TYPE_CHECKING:
    from numpy.typing import DTypeLike


@dataclass
class Graph:
    """Tensors describing a batch of structures (lengths in Å, field in V/Å, charges in e)."""

    numbers: torch.Tensor  # (N,) Z for cores, 99 for pairs
    positions: torch.Tensor  # (N, 3)
    charges: torch.Tensor  # (N,)
    is_pair: torch.Tensor  # (N,) bool
    batch: torch.Tensor  # (N,) structure index of each particle
    cell: torch.Tensor  # (B, 3, 3) rows are lattice vectors (zeros for molecules)
    pbc: torch.Tensor  # (B,) bool
    field: torch.Tensor  # (B, 3) V/Å
    edge_i: torch.Tensor  # (E,) half neighbour list within the short-range cutoff
    edge_j: torch.Tensor  # (E,)
    edge_shift: torch.Tensor  # (E, 3) integer image shifts (as floats)
    coulomb_i: torch.Tensor  # (P,) all pairs i<j of molecular (non-periodic) structures
    coulomb_j: torch.Tensor  # (P,)
    kvec_n: torch.Tensor  # (K,) integer reciprocal-lattice triples (as floats), k != 0
    kvec_batch: torch.Tensor  # (K,) structure of each k
    n_cores: torch.Tensor  # (B,) number of cores per structure
    n_pairs: torch.Tensor  # (B,) number of electron pairs per structure

    @property
    def n_structures(self) -> int:
        """Number of structures B in the batch."""
        return int(self.cell.shape[0])

    @property
    def n_particles(self) -> int:
        """Number of particles N (cores and pairs of all structures)."""
        return int(self.numbers.shape[0])

    @property
    def dtype(self) -> torch.dtype:
        """Floating-point dtype of the positions."""
        return self.positions.dtype

    def to(
        self, dtype: torch.dtype | None = None, device: torch.device | str | None = None
    ) -> Graph:
        """A copy with floating tensors cast to ``dtype`` and all tensors moved to ``device``."""
        out = {}
        for f in fields(self):
            t = getattr(self, f.name)
            if t.is_floating_point():
                t = t.to(device=device, dtype=dtype)
            else:
                t = t.to(device=device)
            out[f.name] = t
        return Graph(**out)

    def with_positions(self, positions: torch.Tensor) -> Graph:
        """The same topology with new particle positions (Å), e.g. relaxed electron pairs."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["positions"] = positions
        return Graph(**out)

    def subgraph(self, keep: torch.Tensor) -> Graph:
        """The structures ``keep`` (B,) bool of this batch with the same (frozen) topology:
        their particles, edges, Coulomb pairs and k vectors, renumbered."""
        g = self
        old_to_new_s = torch.cumsum(keep.long(), 0) - 1
        part = keep[g.batch]
        old_to_new = torch.cumsum(part.long(), 0) - 1
        e_keep = part[g.edge_i]
        c_keep = part[g.coulomb_i]
        k_keep = keep[g.kvec_batch]
        return Graph(
            numbers=g.numbers[part],
            positions=g.positions[part],
            charges=g.charges[part],
            is_pair=g.is_pair[part],
            batch=old_to_new_s[g.batch[part]],
            cell=g.cell[keep],
            pbc=g.pbc[keep],
            field=g.field[keep],
            edge_i=old_to_new[g.edge_i[e_keep]],
            edge_j=old_to_new[g.edge_j[e_keep]],
            edge_shift=g.edge_shift[e_keep],
            coulomb_i=old_to_new[g.coulomb_i[c_keep]],
            coulomb_j=old_to_new[g.coulomb_j[c_keep]],
            kvec_n=g.kvec_n[k_keep],
            kvec_batch=old_to_new_s[g.kvec_batch[k_keep]],
            n_cores=g.n_cores[keep],
            n_pairs=g.n_pairs[keep],
        )

    def split(self, values: torch.Tensor) -> list[torch.Tensor]:
        """Split a per-particle tensor into one tensor per structure."""
        counts = (self.n_cores + self.n_pairs).tolist()
        return list(torch.split(values, counts))


def reciprocal_triples(cell: np.ndarray, gcut: float) -> np.ndarray:
    """Integer triples n != 0 with |k|/(2 pi) <= gcut, k = 2 pi n . cell^-T (gcut in 1/Å).

    The search box |n_i| <= floor(gcut |a_i|) is exact: |n_i| = |k . a_i|/(2 pi) <= gcut |a_i|,
    so every vector of the sphere is found for any triclinic cell.
    """
    nmax = np.floor(gcut * np.linalg.norm(cell, axis=1) + 1e-12).astype(int)
    ranges = [np.arange(-m, m + 1) for m in nmax]
    n = np.stack(np.meshgrid(*ranges, indexing="ij"), axis=-1).reshape(-1, 3)
    g = n @ np.linalg.inv(cell).T  # k / (2 pi)
    keep = (np.linalg.norm(g, axis=1) <= gcut) & np.any(n != 0, axis=1)
    return n[keep]


def collate(
    structures: Sequence[Structure],
    cutoff: float,
    gcut: float,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
) -> Graph:
    """Build the batched :class:`Graph` of ``structures`` for a model with SchNet ``cutoff`` (Å)
    and Ewald reciprocal cutoff ``gcut`` (1/Å)."""
    if len(structures) == 0:
        raise ValueError("collate: no structures given")
    numbers, positions, charges, batch = [], [], [], []
    ei, ej, es, ci, cj, kn, kb = [], [], [], [], [], [], []
    offset = 0
    for b, s in enumerate(structures):
        n = s.n_cores + s.n_pairs
        pos = s.all_positions
        numbers.append(s.all_numbers)
        positions.append(pos)
        charges.append(s.charges)
        batch.append(np.full(n, b))
        try:
            i, j, shifts = half_neighbor_list(pos, s.cell, s.pbc, cutoff)
        except NeighborListError as exc:
            raise NeighborListError(f"{s.source}: {exc}") from None
        ei.append(i + offset)
        ej.append(j + offset)
        es.append(shifts)
        if s.pbc:
            if abs(s.charges.sum()) > 1e-8:
                raise ValueError(
                    f"{s.source}: charged periodic cells (total charge {s.charges.sum():g}) are"
                    " not supported by the reciprocal-space Ewald sum"
                )
            n_k = reciprocal_triples(s.cell, gcut)
            kn.append(n_k)
            kb.append(np.full(len(n_k), b))
        else:
            i, j = all_pairs(n)
            ci.append(i + offset)
            cj.append(j + offset)
        offset += n

    def cat(
        arrays: list[np.ndarray], shape: tuple[int, ...] = (0,), kind: DTypeLike = np.int64
    ) -> np.ndarray:
        return np.concatenate(arrays) if arrays else np.zeros(shape, dtype=kind)

    f = {"dtype": dtype, "device": device}
    li = {"dtype": torch.long, "device": device}
    all_numbers = cat(numbers)
    return Graph(
        numbers=torch.as_tensor(all_numbers, **li),
        positions=torch.as_tensor(cat(positions, (0, 3), float), **f),
        charges=torch.as_tensor(cat(charges, kind=float), **f),
        is_pair=torch.as_tensor(all_numbers == PAIR_NUMBER, device=device),
        batch=torch.as_tensor(cat(batch), **li),
        cell=torch.as_tensor(np.stack([s.cell for s in structures]), **f),
        pbc=torch.as_tensor([s.pbc for s in structures], device=device),
        field=torch.as_tensor(np.stack([s.field for s in structures]), **f),
        edge_i=torch.as_tensor(cat(ei), **li),
        edge_j=torch.as_tensor(cat(ej), **li),
        edge_shift=torch.as_tensor(cat(es, (0, 3)), **f),
        coulomb_i=torch.as_tensor(cat(ci), **li),
        coulomb_j=torch.as_tensor(cat(cj), **li),
        kvec_n=torch.as_tensor(cat(kn, (0, 3)), **f),
        kvec_batch=torch.as_tensor(cat(kb), **li),
        n_cores=torch.as_tensor([s.n_cores for s in structures], **li),
        n_pairs=torch.as_tensor([s.n_pairs for s in structures], **li),
    )


__all__ = ["Graph", "collate", "reciprocal_triples"]

"""Neighbour lists from vesin (half lists, triclinic PBC, integer image shifts).

Convention: for an edge ``(i, j, S)`` the pair vector is ``r_j - r_i + S @ cell`` (cell rows are
lattice vectors, Å). Half lists hold each unordered pair once; the SchNet layer scatters the
message both ways.
"""

from __future__ import annotations

import functools

import numpy as np
import vesin


def half_neighbor_list(
    positions: np.ndarray, cell: np.ndarray, pbc: bool, cutoff: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edges ``(i, j, shifts)`` with ``|r_j - r_i + S cell| < cutoff``, each pair once.

    Args:
        positions: (n, 3) positions in Å.
        cell: (3, 3) lattice vectors as rows in Å (ignored when ``pbc`` is False).
        pbc: periodic in all three directions.
        cutoff: cutoff radius in Å.

    Returns:
        int64 arrays ``i`` (E,), ``j`` (E,) and ``shifts`` (E, 3).
    """
    positions = np.ascontiguousarray(positions, dtype=np.float64)
    box = np.ascontiguousarray(cell, dtype=np.float64) if pbc else np.zeros((3, 3))
    nl = vesin.NeighborList(cutoff=float(cutoff), full_list=False)
    i, j, shifts = nl.compute(points=positions, box=box, periodic=bool(pbc), quantities="ijS")
    return i.astype(np.int64), j.astype(np.int64), shifts.astype(np.int64)


@functools.lru_cache(maxsize=64)
def all_pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """All unordered pairs ``i < j`` of ``n`` particles (for the molecular Coulomb sum);
    cached per ``n`` (MD and relaxations rebuild graphs of one size), read-only arrays."""
    i, j = np.triu_indices(n, k=1)
    i, j = i.astype(np.int64), j.astype(np.int64)
    i.flags.writeable = j.flags.writeable = False
    return i, j

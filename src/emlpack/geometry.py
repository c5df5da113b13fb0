"""Geometry shared by the package (torch-free): minimum image and pairs carried with cores.

Minimum-image vectors come from :func:`ase.geometry.find_mic`, which reduces the cell first
and is exact for any triclinic cell (a hand-written 27-image search is not for skewed cells).
"""

from __future__ import annotations

import numpy as np
from ase.geometry import find_mic


def minimum_image(vectors, cell=None, pbc=None) -> np.ndarray:
    """Shortest periodic images of ``vectors`` (Å), shape (..., 3); unchanged without PBC.

    ``cell`` rows are the lattice vectors (Å); ``pbc`` three booleans (default: all periodic
    when a non-zero cell is given).
    """
    v = np.asarray(vectors, dtype=float)
    if cell is None or not np.any(cell):
        return v
    pbc = np.ones(3, dtype=bool) if pbc is None else np.asarray(pbc, dtype=bool)
    if not np.any(pbc):
        return v
    mic, _ = find_mic(v.reshape(-1, 3), np.asarray(cell, dtype=float), pbc)
    return mic.reshape(v.shape)


def nearest_cores(pairs, cores, cell=None, pbc=None) -> np.ndarray:
    """Index of the nearest core of every pair (minimum image under PBC), shape (n_pairs,)."""
    pairs = np.asarray(pairs, dtype=float).reshape(-1, 3)
    cores = np.asarray(cores, dtype=float).reshape(-1, 3)
    d = minimum_image(pairs[:, None, :] - cores[None, :, :], cell, pbc)
    return np.argmin(np.linalg.norm(d, axis=-1), axis=1)


def carry_pairs(pairs, old_cores, new_cores, old_cell=None, new_cell=None,
                pbc=None) -> np.ndarray:
    """Electron pairs (Å) moved rigidly with their nearest core from ``old_cores`` to
    ``new_cores``; with cells, first affinely with the cell (same fractional coordinates).

    This is the warm start of a relaxation after the cores (and cell) moved, e.g. between MD
    steps, optimisation steps or samples of a crystal.
    """
    pairs = np.asarray(pairs, dtype=float).reshape(-1, 3)
    old_cores = np.asarray(old_cores, dtype=float).reshape(-1, 3)
    new_cores = np.asarray(new_cores, dtype=float).reshape(-1, 3)
    nearest = nearest_cores(pairs, old_cores, old_cell, pbc)
    if old_cell is not None and new_cell is not None and np.any(old_cell):
        affine = np.linalg.solve(np.asarray(old_cell, float), np.asarray(new_cell, float))
        pairs = pairs @ affine
        old_cores = old_cores @ affine
    return pairs + (new_cores - old_cores)[nearest]

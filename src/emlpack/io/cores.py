"""Removal of inner-shell (1s, and 2s2p for Na..Ar) localized-orbital centres from data files.

Localization (Foster-Boys, Wannier) of an all-electron calculation also yields centres for the
core orbitals; they sit on the nuclei (within ~4e-4 Å for 1s). The eMLP folds those pairs into
the core charge, so they are removed on read: each core with inner pairs
(:func:`emlpack.structure.n_core_pairs`) takes its nearest centre(s) within a tolerance.

Unlike the reference's ``filter_cores`` (nearest centre, no threshold, no periodic images), the
distances here are minimum-image distances when the structure is periodic, a centre farther than
the tolerance is never removed, and two cores claiming the same centre is an error.
"""

from __future__ import annotations

import numpy as np

from emlpack.geometry import minimum_image_distances
from emlpack.structure import StructureError, core_charges, n_core_pairs

#: default distance (Å) within which a centre counts as a core centre of a nucleus
CORE_TOLERANCE = 0.01


def find_core_centres(
    numbers: np.ndarray,
    positions: np.ndarray,
    centres: np.ndarray,
    cell: np.ndarray | None = None,
    pbc: bool = False,
    tolerance: float = CORE_TOLERANCE,
    source: str = "<memory>",
) -> np.ndarray:
    """Indices into ``centres`` of the core centres, in core order (nearest first per core).

    Every core with ``n_core_pairs(Z) = k > 0`` claims its ``k`` nearest centres (minimum image
    under ``pbc``); each must lie within ``tolerance`` (Å).

    Raises:
        StructureError: naming ``source``, when a core has too few centres within the tolerance,
            or two cores claim the same centre.
    """
    numbers = np.asarray(numbers, dtype=np.int64).reshape(-1)
    needs = n_core_pairs(numbers)
    heavy = np.flatnonzero(needs > 0)
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    if len(heavy) == 0:
        return np.zeros(0, dtype=np.int64)
    dist = minimum_image_distances(np.asarray(positions)[heavy], centres, cell, pbc)
    claimed: dict[int, int] = {}
    found: list[int] = []
    for row, atom in enumerate(heavy):
        k = int(needs[atom])
        order = np.argsort(dist[row], kind="stable")[:k]
        close = order[dist[row, order] <= tolerance]
        if len(close) < k:
            nearest = float(dist[row].min()) if dist.shape[1] else float("inf")
            what = "no 1s core centre" if k == 1 else f"{len(close)} of its {k} inner-shell centres"
            raise StructureError(
                f"{source}: atom {atom} (Z={numbers[atom]}) has {what} within {tolerance:g} Å"
                f" (nearest electron-pair row is {nearest:.4g} Å away)"
            )
        for c in close.tolist():
            if c in claimed:
                raise StructureError(
                    f"{source}: atoms {claimed[c]} and {atom} both claim electron-pair row {c}"
                    f" as their core centre (within {tolerance:g} Å); cannot assign core centres"
                )
            claimed[c] = int(atom)
            found.append(c)
    return np.asarray(found, dtype=np.int64)


def split_core_centres(
    numbers: np.ndarray,
    positions: np.ndarray,
    centres: np.ndarray,
    cell: np.ndarray | None = None,
    pbc: bool = False,
    charge: float = 0.0,
    tolerance: float = CORE_TOLERANCE,
    source: str = "<memory>",
) -> tuple[np.ndarray, np.ndarray]:
    """Decide per frame whether ``centres`` include core centres and remove them.

    Returns ``(kept_rows, core_rows)``: indices into ``centres`` of the valence pairs (file order)
    and of the removed core centres (core order). Rules:

    * centre count equals the valence pair count (or the valence count is not integral): no
      core centres, nothing removed (e.g. Wannier files such as beta-glycine);
    * count equals valence + inner pairs: every core must have its centres within ``tolerance``;
    * any other count: cores are removed only if some centre lies within ``tolerance`` of a
      core with inner pairs (then all such cores must have one); the caller's count check
      reports the mismatch.
    """
    numbers = np.asarray(numbers, dtype=np.int64).reshape(-1)
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    n = len(centres)
    everything = np.arange(n, dtype=np.int64)
    n_inner = int(n_core_pairs(numbers).sum())
    valence = (float(np.sum(core_charges(numbers))) - charge) / 2.0
    if n_inner == 0 or n == 0 or valence != round(valence) or n == int(round(valence)):
        return everything, np.zeros(0, dtype=np.int64)
    if n != int(round(valence)) + n_inner:
        heavy = n_core_pairs(numbers) > 0
        dist = minimum_image_distances(np.asarray(positions)[heavy], centres, cell, pbc)
        if not np.any(dist <= tolerance):
            return everything, np.zeros(0, dtype=np.int64)
    core = find_core_centres(numbers, positions, centres, cell, pbc, tolerance, source)
    keep = np.setdiff1d(everything, core)
    return keep, core


"""Covalent bonding of a molecule and whether a geometry change broke it (torch-free).

A bond is a pair of atoms closer than :data:`BOND_FACTOR` times the sum of their covalent
radii (ASE's ``covalent_radii``, Cordero et al. 2008). :func:`bonding_changes` compares two
geometries of the same atoms and names every bond broken (stretched beyond
:data:`BROKEN_FACTOR` times its reference length) or formed (a new bond between atoms that
were more than :data:`BROKEN_FACTOR` times their covalent sum apart). This is how emlpack tells
an optimised, relaxed or simulated molecule that is no longer the input molecule (e.g. a C=O
stretched from 1.21 to 1.9 Å, or an H that moved to another carbon).
:func:`largest_molecule` counts the heavy atoms of the largest bonded molecule of a
configuration: how a trained model's domain of molecule sizes is recorded and checked.
"""

from __future__ import annotations

import numpy as np
from ase.data import chemical_symbols, covalent_radii

#: a bond is shorter than this factor times the sum of the covalent radii
BOND_FACTOR = 1.2
#: a bond is broken beyond this factor times its reference length; a new bond counts as
#: formed only between atoms that were beyond this factor times their covalent sum
BROKEN_FACTOR = 1.5


def _distances(positions: np.ndarray) -> np.ndarray:
    pos = np.asarray(positions, dtype=float).reshape(-1, 3)
    return np.linalg.norm(pos[:, None, :] - pos[None, :, :], axis=-1)


def bonds(
    numbers: np.ndarray, positions: np.ndarray, factor: float = BOND_FACTOR
) -> set[tuple[int, int]]:
    """Pairs ``(i, j)``, ``i < j``, closer than ``factor`` x the covalent-radius sum (Å)."""
    r = covalent_radii[np.asarray(numbers, dtype=int)]
    d = _distances(positions)
    i, j = np.nonzero(np.triu(d < factor * (r[:, None] + r[None, :]), k=1))
    return {(int(a), int(b)) for a, b in zip(i, j, strict=True)}


def bonding_changes(
    numbers: np.ndarray, reference_positions: np.ndarray, positions: np.ndarray
) -> list[str]:
    """Bonds of ``reference_positions`` broken and bonds formed in ``positions`` (Å), as
    readable lines such as ``"bond C0-O1 broken (1.21 -> 1.90 Å)"``; empty when unchanged."""
    numbers = np.asarray(numbers, dtype=int)
    d_ref, d_new = _distances(reference_positions), _distances(positions)
    r = covalent_radii[numbers]
    sums = r[:, None] + r[None, :]

    def label(i: int, j: int) -> str:
        return (f"{chemical_symbols[numbers[i]]}{i}-{chemical_symbols[numbers[j]]}{j}"
                f" ({d_ref[i, j]:.2f} -> {d_new[i, j]:.2f} Å)")

    ref = bonds(numbers, reference_positions)
    new = bonds(numbers, positions)
    out = [f"bond {label(i, j)} broken" for i, j in sorted(ref)
           if d_new[i, j] > BROKEN_FACTOR * d_ref[i, j]]
    out += [f"bond {label(i, j)} formed" for i, j in sorted(new - ref)
            if d_ref[i, j] > BROKEN_FACTOR * sums[i, j]]
    return out


def largest_molecule(numbers: np.ndarray, positions: np.ndarray) -> int:
    """Heavy atoms (Z > 1) of the largest covalently bonded molecule among the atoms (Å
    positions; bonds as :func:`bonds`): 4 for propanal (C3H6O), and for a dimer of propanal
    and water too; 0 without heavy atoms."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    numbers = np.asarray(numbers, dtype=int)
    heavy = numbers > 1
    if not heavy.any():
        return 0
    n = len(numbers)
    ij = np.array(sorted(bonds(numbers, positions)), dtype=int).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(ij)), (ij[:, 0], ij[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    return int(np.bincount(label[heavy]).max())

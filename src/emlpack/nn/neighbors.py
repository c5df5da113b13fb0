"""Neighbour lists from vesin (half lists, triclinic PBC, integer image shifts).

Convention: for an edge ``(i, j, S)`` the pair vector is ``r_j - r_i + S @ cell`` (cell rows are
lattice vectors, Å). Half lists hold each unordered pair once; the SchNet layer scatters the
message both ways.

vesin's cell list holds at most :data:`MAX_CELLS` cells of the cutoff's size; beyond that it
shrinks the grid, and for an elongated box (a particle far from the rest: a molecule with one
coordinate of 1e6 Å) the shrunk grid has no cell along some axis and vesin divides by zero
(SIGFPE, vesin 0.6.2). :func:`neighbor_list_problem` restates its cell count, and
:func:`half_neighbor_list` refuses such a structure with :class:`NeighborListError` first.
"""

from __future__ import annotations

import functools

import numpy as np
import vesin

from emlpack.errors import EmlpackError

#: the most cells of the cutoff's size vesin's cell list holds unchanged (vesin 0.6:
#: ``MAX_NUMBER_OF_CELLS`` in ``cpu_cell_list.cpp``); a larger structure is refused
MAX_CELLS = 100_000


class NeighborListError(EmlpackError, ValueError):
    """A structure the neighbour list cannot take (larger than :data:`MAX_CELLS` cells)."""


def neighbor_list_widths(positions: np.ndarray, cell: np.ndarray, pbc: bool) -> np.ndarray:
    """The widths (3, Å) vesin divides into cells: the distances between the faces of the cell
    (rows, Å) under ``pbc``, else of the bounding box of ``positions`` (n, 3, Å) widened by 1 %
    (at least 1 Å), as vesin builds it."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if pbc:
        cell = np.asarray(cell, dtype=np.float64).reshape(3, 3)
        areas = np.linalg.norm(np.cross(cell[[1, 2, 0]], cell[[2, 0, 1]]), axis=1)
        return abs(float(np.linalg.det(cell))) / np.maximum(areas, 1e-300)
    if not len(positions):
        return np.ones(3)
    with np.errstate(over="ignore", invalid="ignore"):  # 1e308 Å: an infinite width
        extent = positions.max(axis=0) - positions.min(axis=0)
        return np.maximum(np.where(extent < 1e-6, 1.0, extent) * 1.01, 1.0)


def neighbor_list_problem(positions: np.ndarray, cell: np.ndarray, pbc: bool,
                          cutoff: float) -> str:
    """Why the neighbour list cannot take these particles (Å), or ``""``: more than
    :data:`MAX_CELLS` cells of the ``cutoff`` (Å), ``max(1, floor(width / cutoff))`` per axis
    of :func:`neighbor_list_widths`."""
    width = neighbor_list_widths(positions, cell, pbc)
    with np.errstate(over="ignore", invalid="ignore"):
        cells = np.maximum(np.floor(width / float(cutoff)), 1.0)
        total = float(np.prod(cells))
    if np.isfinite(total) and total <= MAX_CELLS:
        return ""
    what, hint = (("the cell", "a cell not in Å?") if pbc else
                  ("the bounding box of the particles", "a particle far from the others?"))
    return (f"{what} ({' x '.join(f'{w:.4g}' for w in width)} Å) holds {total:.3g} cells of"
            f" the {cutoff:g} Å cutoff, more than the neighbour list (vesin) can take"
            f" ({MAX_CELLS}; {hint})")


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

    Raises:
        NeighborListError: more than :data:`MAX_CELLS` cells (:func:`neighbor_list_problem`),
            which would crash vesin.
    """
    positions = np.ascontiguousarray(positions, dtype=np.float64)
    problem = neighbor_list_problem(positions, cell, pbc, cutoff)
    if problem:
        raise NeighborListError(problem)
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

"""The neighbour list's own limit: a structure vesin cannot take is refused, not a crash."""

from __future__ import annotations

import numpy as np
import pytest

from emlpack.errors import EmlpackError
from emlpack.nn.neighbors import (
    MAX_CELLS,
    NeighborListError,
    half_neighbor_list,
    neighbor_list_problem,
)

NO_CELL = np.zeros((3, 3))


def test_a_particle_far_away_is_refused_before_vesin_divides_by_zero():
    """One coordinate of 1e6 Å makes vesin's shrunk cell grid empty along two axes (SIGFPE
    in vesin 0.6.2); the check refuses it with an EmlpackError naming the box and the limit."""
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1e6, 0.0, 0.0]])
    with pytest.raises(NeighborListError, match=r"holds 2.52e\+05 cells of the 4 Å cutoff") as e:
        half_neighbor_list(points, NO_CELL, False, 4.0)
    assert isinstance(e.value, EmlpackError) and str(MAX_CELLS) in str(e.value)


def test_the_largest_accepted_molecule_is_listed_and_one_more_cell_is_refused():
    """The limit is vesin's cell count, max(1, floor(1.01 width / cutoff)) per axis: a 1-D
    structure just inside it is listed exactly (its one close pair), just outside refused."""
    cutoff = 4.0
    inside = MAX_CELLS * cutoff / 1.01 - 1.0
    points = np.array([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [inside, 0.0, 0.0]])
    assert neighbor_list_problem(points, NO_CELL, False, cutoff) == ""
    i, j, shifts = half_neighbor_list(points, NO_CELL, False, cutoff)
    assert sorted(zip(i.tolist(), j.tolist(), strict=True)) == [(0, 1)]
    points[2, 0] = (MAX_CELLS + 1) * cutoff / 1.01
    assert "more than the neighbour list (vesin) can take" in neighbor_list_problem(
        points, NO_CELL, False, cutoff)


def test_a_cell_of_1e6_angstrom_is_refused():
    problem = neighbor_list_problem(np.zeros((1, 3)), np.eye(3) * 1e6, True, 4.0)
    assert problem.startswith("the cell (1e+06 x 1e+06 x 1e+06 Å)") and "not in Å" in problem
    assert neighbor_list_problem(np.zeros((1, 3)), np.eye(3) * 10.0, True, 4.0) == ""

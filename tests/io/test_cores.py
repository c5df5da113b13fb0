"""Core-centre removal: minimum image under PBC, multi-pair cores, and the failure modes."""

from __future__ import annotations

import ase.io
import numpy as np
import pytest
from ase import Atoms

from emlpack.geometry import minimum_image_distances
from emlpack.io import (
    find_core_centres,
    read_structures,
    split_core_centres,
    write_structures,
)
from emlpack.structure import Structure, StructureError
from tests.conftest import shared_path

GLYCINE = "data/beta_glycine_pbe_wannier.xyz"


def reference_filter_cores(centres, positions, numbers):
    """The reference's ``filter_cores`` as documented: nearest centre per non-H atom, no PBC."""
    d2 = ((centres[None, :, :] - positions[:, None, :]) ** 2).sum(-1)
    remove = np.argmin(d2, axis=1)[numbers != 1]
    return np.delete(centres, remove, axis=0)


def test_minimum_image_distance_triclinic():
    cell = np.array([[5.0, 0.0, 0.0], [4.0, 3.0, 0.0], [0.0, 0.0, 6.0]])  # strongly skewed
    rng = np.random.default_rng(0)
    points = rng.uniform(-3, 8, (5, 3))
    centres = rng.uniform(-3, 8, (7, 3))
    got = minimum_image_distances(points, centres, cell, pbc=True)
    n = np.arange(-4, 5)
    shifts = np.stack(np.meshgrid(n, n, n, indexing="ij"), -1).reshape(-1, 3) @ cell
    diff = centres[None, :, None, :] - points[:, None, None, :] + shifts[None, None]
    brute = np.linalg.norm(diff, axis=-1).min(-1)
    np.testing.assert_allclose(got, brute, rtol=0, atol=1e-12)


def test_core_centre_across_cell_boundary(tmp_path):
    """A 1s centre wrapped to the far side of the cell from its atom is still found."""
    (glycine,) = read_structures(shared_path(GLYCINE))
    cell = glycine.cell
    heavy = np.flatnonzero(glycine.numbers > 1)
    # translate so that heavy atom 0 sits just inside the a1 face, then put each 1s centre
    # 3e-4 Å from its nucleus, towards -a1, and wrap every particle into the cell
    frac0 = glycine.positions[heavy[0]] @ np.linalg.inv(cell)
    shift = (1e-5 - frac0[0]) * cell[0]
    positions = glycine.positions + shift
    pairs = glycine.pairs + shift
    direction = -cell[0] / np.linalg.norm(cell[0])
    cores = positions[heavy] + 3e-4 * direction

    def wrap(x):
        frac = x @ np.linalg.inv(cell)
        return (frac - np.floor(frac)) @ cell

    wrapped_cores = wrap(cores)
    crossing = np.linalg.norm(wrapped_cores - cores, axis=1) > 1.0
    assert crossing[0], "construction must put a core centre across the boundary"
    es = np.concatenate([wrapped_cores[:4], wrap(pairs), wrapped_cores[4:]])  # interleaved rows
    atoms = Atoms(
        numbers=np.concatenate([glycine.numbers, np.full(len(es), 99)]),
        positions=np.concatenate([positions, es]),
        cell=cell,
        pbc=True,
    )
    atoms.info["energy"] = glycine.energy
    path = tmp_path / "glycine_with_cores.xyz"
    ase.io.write(path, atoms, format="extxyz")

    (s,) = read_structures(path)
    assert s.n_pairs == 30
    np.testing.assert_allclose(s.pairs, np.round(wrap(pairs), 8), atol=1e-10)
    assert sorted(s.info["core_centre_rows"].tolist()) == [0, 1, 2, 3, 34, 35, 36, 37, 38, 39]
    # the reference's non-periodic filter removes a valence pair instead of the crossed centre
    raw = ase.io.read(path)
    kept_reference = reference_filter_cores(
        raw.positions[raw.numbers == 99], raw.positions[raw.numbers != 99], glycine.numbers
    )
    es_rows = raw.positions[raw.numbers == 99]
    assert np.linalg.norm(es_rows - positions[heavy[0]], axis=1).min() > 0.1
    wrong = len(kept_reference) != 30 or not np.allclose(kept_reference, s.pairs, atol=1e-6)
    assert wrong


def test_inner_shells_of_third_row_atom(tmp_path):
    """SiH4: Si (Z=14) folds 5 pairs into its core; 5 centres at the nucleus are removed."""
    si_h = 1.48 / np.sqrt(3)
    hs = si_h * np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=float)
    s = Structure(numbers=[14, 1, 1, 1, 1], positions=np.vstack([[0, 0, 0], hs]), pairs=0.6 * hs)
    path = tmp_path / "sih4.xyz"
    write_structures(path, s, convention="reference", core_centres=True)
    raw = ase.io.read(path)
    assert np.sum(raw.numbers == 99) == 9
    (back,) = read_structures(path)
    assert back.n_pairs == 4
    np.testing.assert_allclose(back.pairs, s.pairs, atol=1e-12)
    assert len(back.info["core_centres"]) == 5


def test_split_without_cores_keeps_everything():
    numbers = np.array([8, 1, 1])
    positions = np.array([[0, 0, 0], [0.96, 0, 0], [-0.24, 0.93, 0]])
    pairs = np.array([[0.5, 0, 0], [-0.1, 0.5, 0], [-0.2, -0.2, 0.3], [-0.2, -0.2, -0.3]])
    kept, removed = split_core_centres(numbers, positions, pairs)
    np.testing.assert_array_equal(kept, [0, 1, 2, 3])
    assert removed.size == 0
    with_core = np.vstack([pairs[:2], [[0.001, 0, 0]], pairs[2:]])
    kept, removed = split_core_centres(numbers, positions, with_core)
    np.testing.assert_array_equal(kept, [0, 1, 3, 4])
    np.testing.assert_array_equal(removed, [2])


def test_find_core_centres_errors():
    numbers = np.array([6, 6])
    positions = np.array([[0.0, 0, 0], [0.004, 0, 0]])
    with pytest.raises(StructureError, match="atoms 0 and 1 both claim electron-pair row 0"):
        find_core_centres(numbers, positions, np.array([[0.002, 0, 0], [3.0, 0, 0]]), source="x")
    with pytest.raises(StructureError, match=r"x: atom 1 \(Z=6\) has no 1s core centre"):
        find_core_centres(
            numbers, np.array([[0.0, 0, 0], [1.5, 0, 0]]), np.array([[0.0, 0, 0.001]]), source="x"
        )


def test_core_centre_tolerance_is_the_documented_0_01_angstrom():
    """docs/conventions.md: a 1s centre is removed when it lies within 0.01 Å of its C/N/O
    nucleus; 0.009 Å away it is removed; 0.011 Å away, with as many centres as valence + core
    pairs, the file is refused with the distance named."""
    from emlpack.io.cores import CORE_TOLERANCE

    assert CORE_TOLERANCE == 0.01
    numbers = np.array([8, 1, 1])
    positions = np.array([[0, 0, 0], [0.96, 0, 0], [-0.24, 0.93, 0]])
    pairs = np.array([[0.5, 0, 0], [-0.1, 0.5, 0], [-0.2, -0.2, 0.3], [-0.2, -0.2, -0.3]])
    direction = np.array([0.6, -0.8, 0.0])
    inside = np.vstack([pairs, 0.009 * direction])
    kept, removed = split_core_centres(numbers, positions, inside)
    np.testing.assert_array_equal(removed, [4])
    outside = np.vstack([pairs, 0.011 * direction])
    with pytest.raises(StructureError, match=r"atom 0 \(Z=8\) has no 1s core centre within"
                       r" 0.01 Å \(nearest electron-pair row is 0.011 Å away\)"):
        split_core_centres(numbers, positions, outside)

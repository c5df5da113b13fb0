"""Structure <-> ase.Atoms conversion used by the ASE calculator."""

from __future__ import annotations

import numpy as np
import pytest
from ase import Atoms

from emlpack.io import atoms_to_structure, structure_to_atoms
from emlpack.structure import Structure, StructureError

H_DIRS = 0.63 * np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=float)


def methane(**kw) -> Structure:
    return Structure(
        numbers=[6, 1, 1, 1, 1],
        positions=np.vstack([[0, 0, 0], H_DIRS]),
        pairs=0.55 * H_DIRS,
        **kw,
    )


def crystal() -> Structure:
    # H2 molecules in a triclinic box, one pair per molecule
    cell = np.array([[4.0, 0.0, 0.0], [0.5, 4.2, 0.0], [0.3, -0.2, 3.9]])
    return Structure(
        numbers=[1, 1],
        positions=[[0.1, 0.2, 0.3], [0.84, 0.2, 0.3]],
        pairs=[[0.47, 0.2, 0.3]],
        cell=cell,
        pbc=True,
        field=[0.01, 0.0, -0.02],
        energy=-31.0,
        forces=[[0.1, 0, 0], [-0.1, 0, 0]],
        pair_forces=[[0.0, 0.01, 0.0]],
        stress=np.array([[1e-3, 2e-4, 0], [2e-4, 2e-3, 0], [0, 0, 3e-3]]),
        info={"tag": "h2"},
    )


def test_structure_to_atoms_holds_cores_only():
    s = methane(field=[0.1, 0.2, 0.3], energy=-1100.0, forces=np.ones((5, 3)), charge=0.0)
    atoms = structure_to_atoms(s)
    assert len(atoms) == 5 and 99 not in atoms.numbers
    np.testing.assert_array_equal(atoms.info["electron_pairs"], s.pairs)
    np.testing.assert_array_equal(atoms.info["external_field"], [0.1, 0.2, 0.3])
    assert atoms.get_potential_energy() == -1100.0
    np.testing.assert_array_equal(atoms.get_forces(), np.ones((5, 3)))
    assert not atoms.pbc.any()


@pytest.mark.parametrize("make", [methane, crystal])
def test_round_trip(make):
    s = make()
    back = atoms_to_structure(structure_to_atoms(s))
    np.testing.assert_array_equal(back.numbers, s.numbers)
    np.testing.assert_array_equal(back.positions, s.positions)
    np.testing.assert_array_equal(back.pairs, s.pairs)
    np.testing.assert_array_equal(back.cell, s.cell)
    np.testing.assert_array_equal(back.field, s.field)
    assert back.pbc == s.pbc and back.charge == s.charge and back.energy == s.energy
    for name in ("forces", "pair_forces", "stress"):
        a, b = getattr(s, name), getattr(back, name)
        assert (a is None) == (b is None)
        if a is not None:
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-15)
    assert back.info.get("tag") == s.info.get("tag")


def test_stale_labels_are_dropped():
    atoms = structure_to_atoms(crystal())
    atoms.positions[0, 0] += 0.1  # the stored energy no longer belongs to these positions
    back = atoms_to_structure(atoms)
    assert back.energy is None and back.forces is None


def test_pairs_from_es_particles_with_core_centre():
    es = np.vstack([[0.0003, 0, 0], 0.55 * H_DIRS])
    atoms = Atoms(numbers=[6, 1, 1, 1, 1] + [99] * 5, positions=np.vstack([[0, 0, 0], H_DIRS, es]))
    s = atoms_to_structure(atoms)
    assert s.n_cores == 5 and s.n_pairs == 4
    np.testing.assert_array_equal(s.pairs, 0.55 * H_DIRS)


def test_explicit_arguments_and_errors():
    atoms = Atoms(numbers=[6, 1, 1, 1, 1], positions=np.vstack([[0, 0, 0], H_DIRS]))
    with pytest.raises(StructureError, match="no electron pairs"):
        atoms_to_structure(atoms)
    s = atoms_to_structure(atoms, pairs=0.55 * H_DIRS, field=[0, 0, 0.5], source="mine")
    np.testing.assert_array_equal(s.field, [0, 0, 0.5])
    assert s.source == "mine"
    with pytest.raises(StructureError, match="mine: 3 electron pairs"):
        atoms_to_structure(atoms, pairs=0.55 * H_DIRS[:3], source="mine")
    atoms.pbc = [True, False, False]
    with pytest.raises(StructureError, match="mixed periodicity"):
        atoms_to_structure(atoms, pairs=0.55 * H_DIRS)

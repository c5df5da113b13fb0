"""Invariance and covariance: rotation, translation, permutation, choice of unit cell,
periodic images, supercells; for every registered short-range family (the ``model`` fixture,
:data:`tests.nn.helpers.FAMILIES`)."""

from __future__ import annotations

import numpy as np
import pytest

from emlpack.structure import Structure
from tests.nn.helpers import (
    FAMILIES,
    all_forces,
    ammonium,
    glycine,
    methane,
    random_model,
    random_rotation,
    water_crystal,
    water_molecule,
)

FIELD = np.array([0.3, 0.2, -0.35])  # V/Å
E_TOL = 1e-10  # eV (energies are 10-100 eV)
F_TOL = 1e-10  # eV/Å

CRYSTALS = {
    "water_crystal": lambda: water_crystal(),
    "water_crystal_field": lambda: water_crystal(FIELD),
    "glycine_p3_field": lambda: glycine("p3"),
}


@pytest.fixture(scope="module", params=FAMILIES)
def model(request):
    return random_model(family=request.param)


def _moved(s: Structure, positions: np.ndarray, **changes) -> Structure:
    return s.copy(positions=positions[: s.n_cores], pairs=positions[s.n_cores :], **changes)


# ---------------------------------------------------------------------- molecules
@pytest.mark.parametrize("make", [methane, water_molecule, ammonium])
def test_molecule_rotation_with_field(model, make):
    s = make(FIELD)
    rot = random_rotation(3)
    rotated = _moved(s, s.all_positions @ rot.T, field=rot @ FIELD)
    a, b = model.evaluate(s), model.evaluate(rotated)
    assert b["energy"] == pytest.approx(a["energy"], abs=E_TOL)
    np.testing.assert_allclose(all_forces(b), all_forces(a) @ rot.T, atol=F_TOL)
    # rotating the molecule but not the field changes the energy (the test can fail)
    assert abs(model.evaluate(_moved(s, s.all_positions @ rot.T))["energy"] - a["energy"]) > 1e-3


def test_neutral_molecule_translation_with_field(model):
    s = water_molecule(FIELD)
    moved = _moved(s, s.all_positions + np.array([3.1, -7.2, 11.9]))
    a, b = model.evaluate(s), model.evaluate(moved)
    assert b["energy"] == pytest.approx(a["energy"], abs=E_TOL)
    np.testing.assert_allclose(all_forces(b), all_forces(a), atol=F_TOL)


def test_molecule_permutation_of_pairs_and_hydrogens(model):
    s = methane(FIELD)
    core_perm = np.array([0, 3, 1, 4, 2])
    pair_perm = np.array([2, 0, 3, 1])
    p = s.copy(positions=s.positions[core_perm], pairs=s.pairs[pair_perm])
    a, b = model.evaluate(s), model.evaluate(p)
    assert b["energy"] == pytest.approx(a["energy"], abs=E_TOL)
    np.testing.assert_allclose(b["forces"], a["forces"][core_perm], atol=F_TOL)
    np.testing.assert_allclose(b["pair_forces"], a["pair_forces"][pair_perm], atol=F_TOL)


# ---------------------------------------------------------------------- crystals
@pytest.mark.parametrize("name", list(CRYSTALS))
def test_crystal_translation(model, name):
    s = CRYSTALS[name]()
    moved = _moved(s, s.all_positions + np.array([0.77, -2.3, 1.45]))
    a, b = model.evaluate(s), model.evaluate(moved)
    assert b["energy"] == pytest.approx(a["energy"], abs=E_TOL)
    np.testing.assert_allclose(all_forces(b), all_forces(a), atol=F_TOL)
    np.testing.assert_allclose(b["stress"], a["stress"], atol=1e-12)


@pytest.mark.parametrize("name", list(CRYSTALS))
def test_crystal_rotation(model, name):
    s = CRYSTALS[name]()
    rot = random_rotation(8)
    rotated = _moved(s, s.all_positions @ rot.T, cell=s.cell @ rot.T, field=rot @ s.field)
    a, b = model.evaluate(s), model.evaluate(rotated)
    assert b["energy"] == pytest.approx(a["energy"], abs=E_TOL)
    np.testing.assert_allclose(all_forces(b), all_forces(a) @ rot.T, atol=F_TOL)
    np.testing.assert_allclose(b["virial"], rot @ a["virial"] @ rot.T, atol=1e-10)
    np.testing.assert_allclose(
        b["virial_including_field"], rot @ a["virial_including_field"] @ rot.T, atol=1e-10
    )


def _reduce(s: Structure, cell: np.ndarray) -> tuple[Structure, np.ndarray]:
    """The same crystal in ``cell``, every particle wrapped into it; also the displacements."""
    r = s.all_positions
    frac = r @ np.linalg.inv(cell)
    wrapped = (frac - np.floor(frac)) @ cell
    return _moved(s, wrapped, cell=cell), wrapped - r


UNIMODULAR = {
    "a1+a2": np.array([[1, 1, 0], [0, 1, 0], [0, 0, 1]]),
    "general": np.array([[2, 1, 0], [1, 1, 0], [0, -1, 1]]),  # det 1
}


@pytest.mark.parametrize("transform", list(UNIMODULAR))
@pytest.mark.parametrize("name", list(CRYSTALS))
def test_choice_of_unit_cell(model, name, transform):
    """An equivalent cell (unimodular transform, particles wrapped into it) gives the same
    forces and stress, and the same energy up to the field term of the moved images,
    -sum_i q_i (Δr_i . E)."""
    m = UNIMODULAR[transform]
    assert round(abs(np.linalg.det(m))) == 1
    s = CRYSTALS[name]()
    other, shift = _reduce(s, m @ s.cell)
    assert np.abs(shift).max() > 1.0  # particles really moved to other images
    a, b = model.evaluate(s), model.evaluate(other)
    field_change = -np.sum(s.charges * (shift @ s.field))
    assert b["energy"] - a["energy"] == pytest.approx(field_change, abs=E_TOL)
    np.testing.assert_allclose(all_forces(b), all_forces(a), atol=F_TOL)
    np.testing.assert_allclose(b["stress"], a["stress"], atol=1e-12)
    assert b["energy_long_range"] == pytest.approx(a["energy_long_range"], abs=1e-11)


@pytest.mark.parametrize("name", list(CRYSTALS))
def test_wrapping_one_particle(model, name):
    s = CRYSTALS[name]()
    a = model.evaluate(s)
    r = s.all_positions
    for i, n in ((0, [1, 0, -1]), (s.n_cores + 1, [0, -2, 1])):
        moved = r.copy()
        moved[i] += np.array(n) @ s.cell
        b = model.evaluate(_moved(s, moved))
        expected = -s.charges[i] * (np.array(n) @ s.cell) @ s.field
        assert b["energy"] - a["energy"] == pytest.approx(expected, abs=E_TOL)
        np.testing.assert_allclose(all_forces(b), all_forces(a), atol=F_TOL)
        np.testing.assert_allclose(b["stress"], a["stress"], atol=1e-12)


def _supercell(s: Structure, reps=(2, 1, 1)) -> Structure:
    shifts = np.array([[i, j, k] for i in range(reps[0]) for j in range(reps[1])
                       for k in range(reps[2])]) @ s.cell
    cores = np.concatenate([s.positions + t for t in shifts])
    pairs = np.concatenate([s.pairs + t for t in shifts])
    return s.copy(
        numbers=np.tile(s.numbers, len(shifts)),
        positions=cores,
        pairs=pairs,
        cell=np.diag(reps) @ s.cell,
        charge=s.charge * len(shifts),
    )


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("gcut", [None, 1.2])
@pytest.mark.parametrize("name", list(CRYSTALS))
def test_supercell_doubles_energy(name, gcut, family):
    """2x1x1 supercell: exactly twice the energy, the same forces and stress, for any gcut.

    The supercell's k set (same |k| cutoff) contains every k of the cell, where its structure
    factor is twice the cell's, plus new k at which the structure factor vanishes, so the
    Ewald sum doubles exactly, not only at convergence."""
    model = random_model(family=family) if gcut is None else random_model(family=family,
                                                                           gcut=gcut)
    s = CRYSTALS[name]()
    sup = _supercell(s)
    a, b = model.evaluate(s), model.evaluate(sup)
    n_small = model.graph(s).kvec_n.shape[0]
    n_large = model.graph(sup).kvec_n.shape[0]
    assert n_large > n_small
    for key in ("energy", "energy_short_range", "energy_long_range", "energy_field"):
        assert b[key] == pytest.approx(2 * a[key], abs=2e-10), key
    fa = all_forces(a)
    fb = np.concatenate([b["forces"], b["pair_forces"]])
    nc = s.n_cores
    expected = np.concatenate([a["forces"], a["forces"], a["pair_forces"], a["pair_forces"]])
    assert fb.shape == (2 * len(fa), 3)
    np.testing.assert_allclose(fb, expected, atol=F_TOL)
    assert nc == len(a["forces"])
    np.testing.assert_allclose(b["stress"], a["stress"], atol=1e-12)

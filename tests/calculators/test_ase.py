"""The ASE calculator: Born-Oppenheimer forces, stress, dipole, caching and warm starts."""

from __future__ import annotations

import numpy as np
import pytest
from ase.calculators.calculator import CalculationFailed

from emlpack.calculators.ase import EMLPCalculator
from emlpack.io import read_structures, structure_to_atoms
from tests.conftest import shared_path
from tests.legacy.test_reference_fixtures import load_model
from tests.nn.helpers import FAMILIES

FMAX = 1e-7  # tight relaxation so finite differences of the BO energy are clean


@pytest.fixture(scope="module")
def model():
    return load_model("small")


@pytest.fixture()
def methane():
    s = read_structures(shared_path("data/eqm7_pbe0_subset.xyz"), index=63)[0]
    return structure_to_atoms(s)


def calc(model, **kw):
    from emlpack.pairs.relax import RelaxOptions

    return EMLPCalculator(model, relax_options=RelaxOptions(fmax=FMAX), **kw)


def test_born_oppenheimer_forces_are_gradients_of_relaxed_energy(model, methane):
    methane.calc = calc(model)
    forces = methane.get_forces()
    assert np.abs(methane.calc.results["pair_forces"]).max() < 1e-6
    h = 1e-4
    for atom, axis in [(0, 0), (1, 2), (3, 1)]:
        e = []
        for sign in (1, -1):
            a = methane.copy()
            a.info = dict(methane.info)
            a.positions[atom, axis] += sign * h
            a.calc = calc(model)
            e.append(a.get_potential_energy())
        assert -(e[0] - e[1]) / (2 * h) == pytest.approx(forces[atom, axis], abs=2e-6)


def test_dipole_is_minus_field_derivative_of_relaxed_energy(model, methane):
    methane.calc = calc(model)
    dipole = methane.get_dipole_moment()
    h = 1e-3  # V/Å
    field0 = np.asarray(methane.info["external_field"], float)
    for axis in range(3):
        e = []
        for sign in (1, -1):
            f = field0.copy()
            f[axis] += sign * h
            methane.info["external_field"] = f
            e.append(methane.get_potential_energy())  # a field change invalidates the cache
        assert -(e[0] - e[1]) / (2 * h) == pytest.approx(dipole[axis], abs=1e-6)


def test_static_model_and_warm_start(model, methane):
    s = read_structures(shared_path("data/eqm7_pbe0_subset.xyz"), index=63)[0]
    methane.calc = calc(model, relax_pairs=False)
    ref = model.evaluate(s)
    assert methane.get_potential_energy() == pytest.approx(ref["energy"], abs=1e-12)
    np.testing.assert_allclose(methane.get_forces(), ref["forces"], atol=1e-12)
    np.testing.assert_allclose(methane.calc.results["pair_forces"], ref["pair_forces"], atol=1e-12)

    methane.calc = calc(model)
    methane.get_potential_energy()
    first = methane.calc.relax_result.n_evaluations
    methane.positions += np.array([0.02, -0.01, 0.01])  # a small move: warm start
    methane.positions[1] += 0.01
    methane.get_potential_energy()
    assert methane.calc.relax_result.n_evaluations < first
    assert methane.calc.relax_result.converged


def test_results_cached_until_something_changes(model, methane):
    methane.calc = calc(model)
    e0 = methane.get_potential_energy()
    evals = methane.calc.relax_result
    assert methane.get_potential_energy() == e0
    assert methane.calc.relax_result is evals
    methane.info["external_field"] = np.array([0.05, 0.0, 0.0])
    assert methane.get_potential_energy() != e0


def test_periodic_stress_matches_model(model):
    s = read_structures(shared_path("data/beta_glycine_pbe_wannier.xyz"))[0]
    atoms = structure_to_atoms(s)
    atoms.calc = calc(model, relax_pairs=False)
    ref = model.evaluate(s)
    stress = atoms.get_stress(voigt=False)
    np.testing.assert_allclose(stress, 0.5 * (ref["stress"] + ref["stress"].T), atol=1e-12)
    assert "dipole" not in atoms.calc.results


def test_missing_pairs_are_guessed(model, methane):
    """Without pairs the calculator starts from emlpack.pairs.guess.guess_pairs (Boys or Lewis)."""
    given = np.array(methane.info.pop("electron_pairs"))
    methane.calc = calc(model, relax_pairs=False)
    methane.get_potential_energy()
    guessed = methane.calc.results["electron_pairs"]
    assert guessed.shape == given.shape
    # each guessed pair lies within 0.5 Å of a pair of the given (relaxed) set
    d = np.linalg.norm(guessed[:, None] - given[None], axis=-1)
    assert d.min(axis=1).max() < 0.5


def test_broken_pairs_are_reported(model, methane):
    pairs = np.array(methane.info["electron_pairs"])
    pairs[1] = pairs[0] + 1e-3  # two pairs on top of each other
    methane.info["electron_pairs"] = pairs
    methane.calc = calc(model)
    methane.calc.relax_options.max_iterations = 3
    with pytest.raises(CalculationFailed, match="relaxation failed"):
        methane.get_potential_energy()


def test_periodic_stress_is_the_strain_derivative_of_the_energy(model):
    """Independent of the model's stress code: sigma = (1/V) dE/d(eps) by central differences
    of the calculator's energy, cores, pairs and cell strained together (ASE sign, eV/Å^3)."""
    s = read_structures(shared_path("data/beta_glycine_pbe_wannier.xyz"))[0]
    s = s.copy(field=np.zeros(3))
    atoms = structure_to_atoms(s)
    atoms.calc = calc(model, relax_pairs=False)
    stress = atoms.get_stress(voigt=False)
    assert np.abs(stress).max() > 1e-3  # a stressed cell: the check is not about zeros
    h = 1e-5
    for i, j in [(0, 0), (2, 2), (0, 1), (1, 2)]:
        e = []
        for sign in (1, -1):
            eps = np.zeros((3, 3))
            eps[i, j] += sign * h / 2
            eps[j, i] += sign * h / 2
            deform = np.eye(3) + eps
            strained = structure_to_atoms(s.copy(positions=s.positions @ deform,
                                                 pairs=s.pairs @ deform, cell=s.cell @ deform))
            strained.calc = calc(model, relax_pairs=False)
            e.append(strained.get_potential_energy())
        fd = (e[0] - e[1]) / (2 * h) / atoms.get_volume()
        assert stress[i, j] == pytest.approx(fd, abs=1e-7 * np.abs(stress).max() + 1e-9), (i, j)


@pytest.mark.parametrize("family", FAMILIES)
def test_every_family_gives_born_oppenheimer_forces_and_dipole(family):
    """EMLPCalculator with a random model of every short-range family: the forces are minus
    the gradient of the relaxed energy (central differences), the dipole minus its field
    derivative, and the relaxed pair forces vanish."""
    from tests.nn.helpers import random_model, water_molecule

    model = random_model(family=family)
    atoms = structure_to_atoms(water_molecule(np.array([0.05, -0.02, 0.03])))
    atoms.calc = calc(model)
    forces, dipole = atoms.get_forces(), atoms.get_dipole_moment()
    assert np.abs(atoms.calc.results["pair_forces"]).max() < 1e-6

    def relaxed_energy(positions=None, field=None):
        a = atoms.copy()
        a.info = {**atoms.info, "external_field": atoms.info["external_field"]
                  if field is None else field}
        if positions is not None:
            a.positions = positions
        a.calc = calc(model)
        return a.get_potential_energy()

    h = 1e-4
    for atom, axis in [(0, 0), (2, 1)]:
        e = []
        for sign in (1, -1):
            p = atoms.positions.copy()
            p[atom, axis] += sign * h
            e.append(relaxed_energy(positions=p))
        assert -(e[0] - e[1]) / (2 * h) == pytest.approx(forces[atom, axis], abs=2e-6)
    field0 = np.asarray(atoms.info["external_field"], float)
    for axis in range(3):
        e = []
        for sign in (1, -1):
            f = field0.copy()
            f[axis] += sign * 1e-3
            e.append(relaxed_energy(field=f))
        assert -(e[0] - e[1]) / 2e-3 == pytest.approx(dipole[axis], abs=1e-6)

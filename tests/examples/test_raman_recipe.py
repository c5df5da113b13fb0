"""examples/raman/aziridine_dft.py end to end with a fake labeler whose dipole responds to the
field through ASE's bond polarizability model: its finite fields, mode differences, files
(resumable, the plan checked) and JSON, against ASE's PlaczekStatic on the same Hessian and
polarizability model."""

from __future__ import annotations

import importlib.util
from types import SimpleNamespace

import numpy as np
import pytest

from tests.conftest import ROOT


def _load_recipe():
    spec = importlib.util.spec_from_file_location(
        "aziridine_dft", ROOT / "examples" / "raman" / "aziridine_dft.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class BondPolarizabilityLabeler:
    """A labeler whose dipole (e·Å) is ``mu0 + alpha(x) F`` with ``alpha`` of ASE's
    ``BondPolarizability`` (e²Å²/eV = e·Å²/V) at the nuclei; counts its calls."""

    def __init__(self):
        from ase.calculators.bond_polarizability import BondPolarizability

        self.model, self.calls = BondPolarizability(), 0

    def __call__(self, numbers, positions, field, **kwargs):
        from ase import Atoms

        self.calls += 1
        alpha = self.model(Atoms(numbers=numbers, positions=positions))
        return SimpleNamespace(ok=True, error="", dipole=np.array([0.1, -0.2, 0.3]) + alpha @ field,
                               wall_time=0.01, scf_cycles=1)


def test_recipe_matches_ase_placzek_static_and_resumes(tmp_path):
    from ase import Atoms
    from ase.calculators.bond_polarizability import BondPolarizability
    from ase.calculators.harmonic import HarmonicCalculator, HarmonicForceField
    from ase.vibrations.placzek import PlaczekStatic
    from ase.vibrations.raman import StaticRamanCalculator

    az = _load_recipe()
    numbers, positions, hessian, origin = az.reference_geometry()
    step = 2e-3
    plan = az.make_plan(numbers, positions, hessian, origin, "fake", step, 2e-3)
    labeler = BondPolarizabilityLabeler()
    data = az.run(tmp_path / "work", plan, labeler, log=lambda _: None)
    assert labeler.calls == 216 and data["complete"] and data["scf_count"] == 216
    assert len(list((tmp_path / "work").glob("*/field_*.npz"))) == 216
    # ASE: Cartesian displacements of the same atoms, forces of the same Hessian
    atoms = Atoms(numbers=numbers, positions=positions)
    atoms.calc = HarmonicCalculator(HarmonicForceField(atoms.copy(), hessian_x=hessian))
    name = str(tmp_path / "ase")
    StaticRamanCalculator(atoms, BondPolarizability, name=name, delta=step, txt=None).run()
    placzek = PlaczekStatic(atoms, name=name, delta=step, txt=None)
    order = np.argsort(np.real(placzek.get_energies()))[-18:]
    np.testing.assert_allclose(np.real(placzek.get_energies())[order] / 1.239841984332e-4,
                               data["frequencies_cm-1"], rtol=1e-6)
    activities = np.asarray(data["activities_A4_per_amu"])
    # ASE does not project the rigid-body motions out of this finite-difference Hessian (its
    # rigid-body couplings are ~1e-4 of the largest element): its modes differ at that level
    np.testing.assert_allclose(placzek.get_absolute_intensities()[order], activities,
                               rtol=1e-3, atol=1e-5 * activities.max())
    # resumed: nothing computed again; a plan of another step is refused
    again = az.run(tmp_path / "work", plan, labeler, modes=[0, 3], reverse=True,
                   log=lambda _: None)
    assert labeler.calls == 216 and again["modes"] == [0, 3] and not again["complete"]
    np.testing.assert_allclose(again["activities_A4_per_amu"], activities[[0, 3]], rtol=1e-12)
    other = az.make_plan(numbers, positions, hessian, origin, "fake", 2 * step, 2e-3)
    with pytest.raises(az.PlanError, match="another geometry, level or step"):
        az.run(tmp_path / "work", other, labeler)

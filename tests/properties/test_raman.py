"""Harmonic Raman spectra: ASE's conventions (invariants, PlaczekStatic), finite differences of
the model's own relaxed polarizability, rotational invariance, and the selection rules of a
molecule with an inversion centre."""

from __future__ import annotations

import numpy as np
import pytest

from emlpack.geometry import CENTRAL_DIFFERENCES
from emlpack.pairs.relax import relax_pairs
from emlpack.properties.hessian import extended_hessian
from emlpack.properties.ir import ir_from_hessian
from emlpack.properties.optimize import optimize
from emlpack.properties.raman import (
    STEP,
    depolarization_ratios,
    polarizability_derivatives,
    raman_activities,
    raman_invariants,
    raman_spectrum,
)
from emlpack.properties.response import polarizability_from_hessian
from emlpack.structure import Structure
from emlpack.units import COULOMB_EV_A
from tests.nn.helpers import random_rotation, water_molecule
from tests.properties.toy import spring_model


@pytest.fixture(scope="module")
def water():
    """Water with a small random SchNet + springs at its minimum (cores and pairs)."""
    s = water_molecule()
    model = spring_model(s)
    res = optimize(model, s, fmax=1e-10)
    assert res.converged and res.min_curvature > 0, res.reason
    return model, res.structure


def _relaxed_alpha(model, s: Structure) -> np.ndarray:
    """Clamped-core polarizability (Å³) with the pairs relaxed at ``s``'s cores."""
    r = relax_pairs(model, s, fmax=1e-11)[0]
    assert not r.failed, r.reason
    s = s.copy(pairs=r.pairs)
    return polarizability_from_hessian(extended_hessian(model, s)[1].numpy(), s) * COULOMB_EV_A


def test_invariants_are_ases():
    """a'^2, gamma'^2 of ASE's RamanData._invariants (Long), and their textbook limits: an
    isotropic derivative is polarised (rho 0), a traceless one depolarised (rho 3/4, 6/7)."""
    from ase.vibrations.raman import RamanData

    rng = np.random.default_rng(3)
    d = rng.normal(size=(5, 3, 3))
    d = d + np.swapaxes(d, 1, 2)  # polarizability derivatives are symmetric
    ase_mean, ase_aniso, _ = RamanData._invariants(None, d)
    mean_sq, aniso_sq = raman_invariants(d)
    np.testing.assert_allclose(mean_sq, ase_mean, rtol=1e-13)
    np.testing.assert_allclose(aniso_sq, ase_aniso, rtol=1e-13)
    np.testing.assert_allclose(raman_activities(d), 45 * ase_mean + 7 * ase_aniso, rtol=1e-13)
    limits = np.array([np.eye(3), np.diag([1.0, -1.0, 0.0]), [[0, 1, 0], [1, 0, 0], [0, 0, 0]]])
    np.testing.assert_allclose(raman_invariants(limits)[0], [1.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(raman_invariants(limits)[1], [0.0, 3.0, 3.0], atol=1e-15)
    np.testing.assert_allclose(raman_activities(limits), [45.0, 21.0, 21.0])
    np.testing.assert_allclose(depolarization_ratios(limits), [0.0, 0.75, 0.75], atol=1e-15)
    np.testing.assert_allclose(depolarization_ratios(limits, natural=True), [0.0, 6 / 7, 6 / 7],
                               atol=1e-15)
    silent = depolarization_ratios(np.array([np.eye(3), np.zeros((3, 3))]))
    assert silent[0] == 0.0 and np.isnan(silent[1])  # an inactive mode has no ratio


def test_activities_match_ase_placzek_static(water, tmp_path):
    """ASE's static Raman (Cartesian displacements, forces from EMLPCalculator, the model's
    polarizability with the pairs relaxed at every displaced geometry) gives our wavenumbers
    and activities: one convention, and our mode differences along the linear pair response
    equal differences of the fully relaxed polarizability."""
    from ase.vibrations.placzek import PlaczekStatic
    from ase.vibrations.raman import StaticRamanCalculator

    from emlpack.calculators.ase import EMLPCalculator
    from emlpack.io import structure_to_atoms
    from emlpack.pairs.relax import RelaxOptions

    model, s = water
    ours = raman_spectrum(model, s)

    class ModelPolarizability:
        """ASE's exobj: the polarizability in e²Å²/eV (= e·Å²/V) at the atoms' positions."""

        def __call__(self, atoms):
            return _relaxed_alpha(model, s.copy(positions=atoms.positions)) / COULOMB_EV_A

    atoms = structure_to_atoms(s)
    atoms.calc = EMLPCalculator(model, relax_options=RelaxOptions(fmax=1e-10))
    delta = 2.5e-4  # ASE's 2-point differences: O(delta^2) ~ 1e-5 relative on this toy
    name = str(tmp_path / "raman")
    StaticRamanCalculator(atoms, ModelPolarizability, name=name, delta=delta, txt=None).run()
    placzek = PlaczekStatic(atoms, name=name, delta=delta, txt=None)
    ase_freq = np.real(placzek.get_energies()) / 1.239841984332e-4  # eV -> cm^-1
    ase_act = placzek.get_absolute_intensities()
    order = np.argsort(ase_freq)[-len(ours.frequencies):]  # the 3N - 6 vibrations
    np.testing.assert_allclose(ase_freq[order], ours.frequencies, rtol=1e-5)
    np.testing.assert_allclose(ase_act[order], ours.activities, rtol=3e-4)
    assert ours.activities.min() > 1e-3 * ours.activities.max()  # every mode is checked


def test_derivatives_equal_differences_of_the_relaxed_polarizability(water):
    """Along each normal mode: our derivatives (pairs along their linear response, no
    relaxation) = 4-point differences of the polarizability with the pairs relaxed at every
    displaced geometry; a 2-point stencil of a small step agrees too."""
    model, s = water
    _, h = extended_hessian(model, s)
    h = h.numpy()
    ir = ir_from_hessian(h, s)
    step = 1e-3
    ours = polarizability_derivatives(model, s, h, ir.modes, ir.masses, step=step)
    offsets, weights = CENTRAL_DIFFERENCES[4]
    sqrt_m = np.sqrt(ir.masses)[:, None]
    for k, mode in enumerate(ir.modes):
        fd = sum(w * _relaxed_alpha(model, s.copy(positions=s.positions + o * step * mode))
                 for o, w in zip(offsets, weights, strict=True)) / step
        fd /= np.linalg.norm(mode * sqrt_m)  # d/ds -> d/dQ_k, Q_k = s |M^1/2 c_k|
        np.testing.assert_allclose(ours[k], fd, atol=2e-5 * np.abs(fd).max())
    two_point = polarizability_derivatives(model, s, h, ir.modes, ir.masses, step=1e-4,
                                           points=2)
    np.testing.assert_allclose(two_point, ours, atol=5e-5 * np.abs(ours).max())


def test_raman_spectrum_is_invariant_under_rotation(water):
    """Rotating the molecule (cores and pairs) leaves wavenumbers, activities and
    depolarisation ratios as they were; each derivative tensor rotates as R A R^T."""
    model, s = water
    a = raman_spectrum(model, s)
    rot = random_rotation(5)
    centre = s.positions.mean(axis=0)
    b = raman_spectrum(model, s.copy(positions=(s.positions - centre) @ rot.T,
                                     pairs=(s.pairs - centre) @ rot.T))
    np.testing.assert_allclose(b.frequencies, a.frequencies, rtol=1e-9)
    np.testing.assert_allclose(b.activities, a.activities, rtol=1e-7)
    np.testing.assert_allclose(b.depolarization_ratios, a.depolarization_ratios, rtol=1e-7)
    for k in range(len(a.frequencies)):
        sign = np.sign(np.sum(b.modes[k] * (a.modes[k] @ rot.T)))  # a mode's sign is free
        np.testing.assert_allclose(sign * b.polarizability_derivatives[k],
                                   rot @ a.polarizability_derivatives[k] @ rot.T,
                                   atol=1e-7 * np.abs(a.polarizability_derivatives).max())


def ethylene() -> Structure:
    """Planar ethylene (D2h, inversion centre at the origin) with its six valence pairs: four
    C-H and the C=C double bond as two pairs above and below the plane."""
    cc, ch, angle = 1.33, 1.08, np.deg2rad(121.5)
    hx, hy = cc / 2 - ch * np.cos(angle), ch * np.sin(angle)
    cores = np.array([[cc / 2, 0, 0], [-cc / 2, 0, 0], [hx, hy, 0], [hx, -hy, 0], [-hx, hy, 0],
                      [-hx, -hy, 0]])
    ch_pairs = [0.6 * cores[h] + 0.4 * cores[c] for h, c in ((2, 0), (3, 0), (4, 1), (5, 1))]
    pairs = np.array([*ch_pairs, [0.0, 0.0, 0.45], [0.0, 0.0, -0.45]])
    return Structure([6, 6, 1, 1, 1, 1], cores, pairs)


def test_inversion_centre_makes_ir_and_raman_mutually_exclusive():
    """Ethylene (D2h) with a random SchNet + springs, optimised keeping its symmetry (a
    symmetric stationary point): the 6 modes even under inversion (3 Ag, 1 B1g, 2 B2g) are
    Raman active and IR inactive, the 6 odd ones Raman inactive (5 IR active, the Au torsion
    silent); the 3 totally symmetric modes are polarised (rho < 3/4), the other even ones
    depolarised (rho = 3/4)."""
    s = ethylene()
    model = spring_model(s, core_cutoff=3.2)
    res = optimize(model, s, fmax=1e-9)
    assert res.converged, res.reason
    s = res.structure
    partner = [int(np.argmin(np.linalg.norm(s.positions + p, axis=1))) for p in s.positions]
    assert np.abs(s.positions + s.positions[partner]).max() < 1e-6  # still centrosymmetric
    r = raman_spectrum(model, s)
    assert len(r.frequencies) == 12
    parity = np.array([np.sum(c * -c[partner]) for c in r.modes])  # +1 even (g), -1 odd (u)
    np.testing.assert_allclose(np.abs(parity), 1.0, atol=1e-6)
    even = parity > 0
    raman, ir = r.activities / r.activities.max(), r.ir_intensities / r.ir_intensities.max()
    assert even.sum() == 6
    assert np.all(raman[~even] < 1e-10) and np.all(ir[even] < 1e-10)  # mutual exclusion
    assert np.all(raman[even] > 1e-4)
    assert np.sum(ir[~even] > 1e-4) == 5  # and one silent odd mode (Au)
    rho = r.depolarization_ratios[even]
    assert np.sum(rho < 0.7) == 3
    np.testing.assert_allclose(rho[rho >= 0.7], 0.75, atol=1e-8)
    assert np.all(np.isnan(r.depolarization_ratios[~even]))


def test_default_step_is_the_command_lines():
    """``emlp raman --step`` defaults to the library's step (its parser never imports torch)."""
    from emlpack.cli.properties import RAMAN_STEP

    assert RAMAN_STEP == STEP

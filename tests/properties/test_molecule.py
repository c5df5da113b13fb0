"""Molecular response: polarizability (toy closed form, finite fields), IR spectra (finite
differences of Born-Oppenheimer forces and dipoles, ase.vibrations)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import erf

from emlpack.geometry import normal_modes
from emlpack.pairs.relax import relax_pairs
from emlpack.properties.hessian import extended_hessian
from emlpack.properties.ir import ir_from_hessian, lorentzian
from emlpack.properties.optimize import optimize
from emlpack.properties.response import (
    born_oppenheimer_blocks,
    molecule_response,
    polarizability_from_hessian,
)
from emlpack.units import COULOMB_EV_A, REFERENCE_GAMMA
from tests.nn.helpers import (
    FAMILIES,
    STENCIL_OFFSETS,
    STENCIL_WEIGHTS,
    random_model,
    water_molecule,
)
from tests.properties.toy import spring_model, toy_atom, toy_atom_polarizability

FIELD_STEP = 2e-3  # V/Å


def _gaussian_coulomb_hessian(d: np.ndarray, gamma: float, eps: float = 1e-10) -> np.ndarray:
    """Hessian (1/Å³) of f(|d|) = erf(gamma r)/(r + eps) (the model's pair kernel)."""
    r = np.linalg.norm(d)
    u = d / r
    g = 2 * gamma / np.sqrt(np.pi) * np.exp(-(gamma * r) ** 2)
    f1 = g / (r + eps) - erf(gamma * r) / (r + eps) ** 2
    f2 = -2 * gamma**2 * r * g / (r + eps) - 2 * g / (r + eps) ** 2 + 2 * erf(gamma * r) / (
        r + eps) ** 3
    return f2 * np.outer(u, u) + f1 / r * (np.eye(3) - np.outer(u, u))


def test_toy_atom_polarizability_closed_form():
    """Core (+2) and pair (-2) on a spring k: alpha = 4 (k I - 4 k_e grad grad f(d))^-1."""
    k = 5.0
    model, s = toy_atom(k)
    d = np.array([0.06, -0.03, 0.08])
    s = s.copy(pairs=s.positions + d)
    alpha = molecule_response(model, s, relax_cores=False).polarizability
    curvature = k * np.eye(3) - 4.0 * COULOMB_EV_A * _gaussian_coulomb_hessian(d, REFERENCE_GAMMA)
    np.testing.assert_allclose(alpha, 4.0 * np.linalg.inv(curvature), rtol=1e-10, atol=1e-12)
    # near the minimum (d -> 0) the isotropic closed form 4/(k + 16 k_e gamma^3/(3 sqrt(pi)));
    # at d = 0.02 Å the corrections are O((gamma d)^2) and the kernel's 1e-10 Å regulariser
    s0 = s.copy(pairs=s.positions + np.array([2e-2, 0.0, 0.0]))
    alpha0 = molecule_response(model, s0, relax_cores=False).polarizability
    np.testing.assert_allclose(alpha0, toy_atom_polarizability(k) * np.eye(3), rtol=1e-3,
                               atol=1e-12)


@pytest.fixture(scope="module")
def water_setup():
    """Water with a small random SchNet + springs, fully optimised (cores and pairs)."""
    s = water_molecule()
    model = spring_model(s)
    res = optimize(model, s, fmax=1e-9)
    assert res.converged, res.reason
    assert res.min_curvature > 0
    s = res.structure
    _, h = extended_hessian(model, s)
    model.chord = {"hessian": res.hessian, "hessian_every": 0}  # for the perturbed relaxations
    return model, s, h.numpy()


def _relaxed_pairs(model, s, fmax=1e-10):
    r = relax_pairs(model, s, fmax=fmax)[0]
    assert not r.failed, r.reason
    return s.copy(pairs=r.pairs)


def test_polarizability_matches_finite_field_relaxed_dipole(water_setup):
    """alpha_ij = d mu_i / d F_j by central differences (4th order) of the relaxed dipole."""
    model, s, h = water_setup
    alpha = polarizability_from_hessian(h, s)
    alpha_rel = polarizability_from_hessian(h, s, relax_cores=True)
    fd, fd_rel = np.zeros((3, 3)), np.zeros((3, 3))
    for j in range(3):
        for o, w in zip(STENCIL_OFFSETS, STENCIL_WEIGHTS, strict=True):
            field = np.zeros(3)
            field[j] = o * FIELD_STEP
            sf = s.copy(field=field)
            fd[:, j] += w * _relaxed_pairs(model, sf).dipole() / FIELD_STEP
            res = optimize(model, sf, fmax=1e-10, **model.chord)
            assert res.converged, res.reason
            fd_rel[:, j] += w * res.structure.dipole() / FIELD_STEP
    np.testing.assert_allclose(alpha, fd, rtol=1e-5, atol=1e-6 * np.abs(alpha).max())
    np.testing.assert_allclose(alpha_rel, fd_rel, rtol=1e-5, atol=1e-6 * np.abs(alpha_rel).max())
    # relaxing the cores can only increase the response (positive semi-definite difference)
    assert np.linalg.eigvalsh(alpha_rel - alpha).min() > -1e-10


def _bo_forces_and_dipoles(model, s, displacements):
    out_f, out_mu = [], []
    for disp in displacements:
        sd = _relaxed_pairs(model, s.copy(positions=s.positions + disp))
        out_f.append(model.evaluate(sd)["forces"].reshape(-1))
        out_mu.append(sd.dipole())
    return np.array(out_f), np.array(out_mu)


def test_bo_hessian_and_dipole_derivatives_match_finite_differences(water_setup):
    model, s, h = water_setup
    k_bo, dmu, _ = born_oppenheimer_blocks(h, s)
    step = 2e-4
    nc = s.n_cores
    disps = []
    for i in range(nc):
        for a in range(3):
            for o in STENCIL_OFFSETS:
                d = np.zeros((nc, 3))
                d[i, a] = o * step
                disps.append(d)
    f, mu = _bo_forces_and_dipoles(model, s, disps)
    f = f.reshape(3 * nc, 4, -1)
    mu = mu.reshape(3 * nc, 4, 3)
    k_fd = -np.einsum("rkv,k->rv", f, STENCIL_WEIGHTS) / step
    dmu_fd = (np.einsum("rkv,k->rv", mu, STENCIL_WEIGHTS) / step).T
    np.testing.assert_allclose(k_bo, k_fd, atol=1e-6 * np.abs(k_bo).max())
    np.testing.assert_allclose(dmu, dmu_fd, atol=1e-6 * np.abs(dmu).max())
    # the spectrum from the finite-difference matrices
    ir = ir_from_hessian(h, s)
    evals, _ = normal_modes(k_fd, s.positions, ir.masses)
    assert len(ir.frequencies) == 3 * nc - 6
    np.testing.assert_allclose(np.sort(evals), np.sort(np.sign(ir.frequencies) * (
        ir.frequencies / 521.4708983725066) ** 2), rtol=1e-5)


def test_ir_matches_ase_vibrations_and_infrared(water_setup, tmp_path):
    """Frequencies and intensities against ase.vibrations.Infrared through EMLPCalculator
    (BO-relaxed pairs at every displacement, serving get_dipole_moment())."""
    from ase.vibrations import Infrared

    from emlpack.calculators.ase import EMLPCalculator
    from emlpack.io import structure_to_atoms
    from emlpack.pairs.relax import RelaxOptions

    model, s, h = water_setup
    ir = ir_from_hessian(h, s)
    atoms = structure_to_atoms(s)
    atoms.calc = EMLPCalculator(model, relax_options=RelaxOptions(fmax=1e-10))
    vib = Infrared(atoms, name=str(tmp_path / "ir"), delta=2e-3, nfree=4)
    vib.run()
    freqs = np.real(vib.get_frequencies())
    # ASE: (D/Å)^2/amu, 42.255 km/mol each; the 3N-6 largest modes are the vibrations
    ase_freq = np.sort(freqs)[-len(ir.frequencies):]
    order = np.argsort(freqs)[-len(ir.frequencies):]
    ase_int = vib.intensities[order] * 42.255
    np.testing.assert_allclose(ase_freq, ir.frequencies, rtol=1e-4)
    np.testing.assert_allclose(ase_int, ir.intensities, rtol=1e-3, atol=1e-4 * ir.intensities.max())


def test_lorentzian_integrates_to_intensity():
    grid = np.linspace(-5000, 7000, 1_200_001)
    curve = lorentzian(grid, np.array([1000.0, 1500.0]), np.array([2.0, 3.0]), 10.0)
    assert abs(np.trapezoid(curve, grid) - 5.0) < 0.01
    peak = lorentzian(np.array([1000.0]), np.array([1000.0]), np.array([1.0]), 10.0)
    np.testing.assert_allclose(peak, 1.0 / (np.pi * 5.0))


def test_an_optimum_with_merged_pairs_is_a_failure():
    """A stiff spring of rest length 0 between two of water's pairs (beside the toy springs
    that hold the molecule) makes an optimum with those pairs on one point: the optimiser
    converges there, and the result says it is broken instead of converged."""
    from tests.properties.toy import SpringModel

    s = water_molecule()
    model = spring_model(s)
    nc = s.n_cores
    springs = model.springs + [(nc, nc + 1, (0, 0, 0), 2000.0, 0.0)]
    merged = SpringModel(model.config, springs).double()
    merged.load_state_dict(model.state_dict())
    res = optimize(merged, s, fmax=1e-4)
    assert np.linalg.norm(res.structure.pairs[0] - res.structure.pairs[1]) < 0.1
    assert res.max_force < 1e-4  # converged by its forces ...
    assert not res.converged  # ... but not an optimum of a molecule
    assert "pairs 0 and 1 are" in res.pair_check and "(merged;" in res.pair_check
    assert res.pair_check in res.reason
    assert res.iterations < 100
    healthy = optimize(model, s, fmax=1e-4)
    assert healthy.converged and healthy.pair_check == "" and healthy.reason == ""


@pytest.mark.parametrize("family", FAMILIES)
def test_pair_polarizability_of_every_family_matches_finite_fields(family):
    """A plain EMLP of every short-range family (the fast extended Hessian: SchNet's closed
    form, other families' short range by reverse over reverse): the polarizability at fixed
    cores equals d mu / d F of the relaxed pairs by 4th-order central differences."""
    model = random_model(family=family)
    s = _relaxed_pairs(model, water_molecule())
    alpha = molecule_response(model, s, relax_cores=False).polarizability
    fd = np.zeros((3, 3))
    for j in range(3):
        for o, w in zip(STENCIL_OFFSETS, STENCIL_WEIGHTS, strict=True):
            field = np.zeros(3)
            field[j] = o * FIELD_STEP
            fd[:, j] += w * _relaxed_pairs(model, s.copy(field=field)).dipole() / FIELD_STEP
    assert np.abs(alpha).max() > 0.1
    np.testing.assert_allclose(alpha, fd, rtol=1e-5, atol=1e-6 * np.abs(alpha).max())
    np.testing.assert_allclose(alpha, alpha.T, atol=1e-10 * np.abs(alpha).max())


#: hexatriyne at its PBE0/def2-SVP optimum (PySCF, ASE BFGS to 0.01 eV/Å): exactly linear, Å
HEXATRIYNE_Z = [-4.27007141, -3.19531633, -1.97686763, -0.61293370, 0.61293370, 1.97686763,
                3.19531633, 4.27007141]


def test_a_linear_molecules_pair_rotation_about_its_axis_is_projected_out():
    """At fixed cores on a line, turning every pair about the axis is a symmetry: a zero mode
    of the relaxed pair Hessian. Where the pairs break the cylindrical symmetry (a
    perpendicular dipole) it couples to the field, and the plain inverse turns it into noise
    (here ~100x the polarizability along one axis). The clamped polarizability relaxes the
    pairs in every other direction: the limit of an ever stiffer spring on the rotation, a
    positive tensor, with the same response to a field along the axis."""
    from ase import Atoms

    from emlpack.calculators.ensemble import load_pretrained
    from emlpack.geometry import core_fixed_rotations, schur_complement
    from emlpack.pairs.guess import guess_pairs
    from emlpack.properties.response import pair_minimum_problem
    from emlpack.structure import Structure

    atoms = Atoms("HC6H", positions=[[0.0, 0.0, z] for z in HEXATRIYNE_Z])
    model = load_pretrained("mini-eqm7").members[1].model
    s = Structure(atoms.numbers, atoms.positions, guess_pairs(atoms, "auto"))
    r = relax_pairs(model, s, fmax=1e-6)[0]
    assert not r.failed, r.reason
    s = s.copy(pairs=r.pairs)
    h = extended_hessian(model, s)[1].numpy()
    n = s.n_cores + s.n_pairs
    pairs, field = np.arange(3 * s.n_cores, 3 * n), np.arange(3 * n, 3 * n + 3)
    rotation = core_fixed_rotations(s.positions, s.pairs)
    assert rotation.shape[1] == 1
    h_pp = h[np.ix_(pairs, pairs)]
    assert abs(float(rotation[:, 0] @ h_pp @ rotation[:, 0])) < 1e-4  # a zero mode, eV/Å²
    alpha = polarizability_from_hessian(h, s)
    stiff = h.copy()
    stiff[np.ix_(pairs, pairs)] += 1e8 * rotation @ rotation.T
    np.testing.assert_allclose(alpha, -schur_complement(stiff, field, pairs), atol=1e-6)
    assert np.linalg.eigvalsh(alpha)[0] > 0 and pair_minimum_problem(h, s) == ""
    plain = -schur_complement(h, field, pairs)
    assert np.linalg.eigvalsh(plain)[-1] > 30 * np.linalg.eigvalsh(alpha)[-1]
    assert alpha[2, 2] == pytest.approx(plain[2, 2], rel=1e-3)  # the axis: no coupling

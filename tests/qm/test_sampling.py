"""Samplers: statistics of normal-mode sampling, rigid torsions, dimer distances, fields."""

from __future__ import annotations

import numpy as np
import pytest

from emlpack.geometry import rigid_body_modes
from emlpack.qm.sampling import (
    PROBES,
    SamplingError,
    cell_normal_mode_sample,
    dimer_sample,
    masses_of,
    molecule_from_smiles,
    normal_mode_sample,
    normal_modes,
    random_field,
    torsion_sample,
)
from emlpack.units import BOLTZMANN_EV_K, FIELD_AU_IN_V_PER_A
from tests.conftest import shared_path


def _synthetic_hessian(positions, seed=0):
    """A random positive Hessian (eV/Å^2) with exact translational/rotational zero modes."""
    rng = np.random.default_rng(seed)
    n = 3 * len(positions)
    a = rng.normal(size=(n, n))
    a = a @ a.T / n * 20.0 + 5.0 * np.eye(n)
    q = rigid_body_modes(positions)  # unweighted rigid-body directions
    p = np.eye(n) - q @ q.T
    return p @ a @ p


@pytest.fixture(scope="module")
def ethanol():
    return molecule_from_smiles("[H]OC([H])([H])C([H])([H])[H]", name="ethanol", seed=3)


def test_nms_mean_harmonic_energy_is_kT_over_2_per_mode(ethanol):
    h = _synthetic_hessian(ethanol.positions)
    k, modes = normal_modes(ethanol.numbers, ethanol.positions, h)
    assert len(k) == 3 * 9 - 6 and np.all(k > 0)
    rng = np.random.default_rng(7)
    t = 600.0
    n_vib = len(k)
    energies = []
    for _ in range(2000):
        s = normal_mode_sample(ethanol.numbers, ethanol.positions, h, t, rng, n_modes=n_vib,
                               min_force_constant=0.0, modes=(k, modes))
        dx = (s.positions - ethanol.positions).ravel()
        energies.append(0.5 * dx @ h @ dx)  # Cartesian harmonic energy
        assert abs(energies[-1] - s.harmonic_energy) < 1e-9
    mean, expected = np.mean(energies), 0.5 * n_vib * BOLTZMANN_EV_K * t
    # the energy is (k_B T / 2) chi^2_{n_vib}: standard error of the mean is expected*sqrt(2/n)/63
    assert abs(mean - expected) < 4 * expected * np.sqrt(2.0 / n_vib) / np.sqrt(2000)


def test_nms_random_subsets_and_no_rigid_motion(ethanol):
    h = _synthetic_hessian(ethanol.positions)
    rng = np.random.default_rng(1)
    modes = normal_modes(ethanol.numbers, ethanol.positions, h)
    counts, energies = [], []
    m = masses_of(ethanol.numbers)
    for _ in range(2000):
        s = normal_mode_sample(ethanol.numbers, ethanol.positions, h, 800.0, rng,
                               min_force_constant=0.0, modes=modes)
        counts.append(len(s.modes))
        energies.append(s.harmonic_energy)
        dx = s.positions - ethanol.positions
        assert np.allclose(m @ dx, 0.0, atol=1e-10)  # centre of mass fixed
    counts = np.array(counts)
    assert counts.min() == 1 and counts.max() == 21  # uniform in 1..n_vib
    assert abs(counts.mean() - 11.0) < 0.5
    expected = 0.5 * BOLTZMANN_EV_K * 800.0 * counts.mean()
    assert abs(np.mean(energies) - expected) < 0.1 * expected


def test_nms_is_reproducible_with_a_seed(ethanol):
    h = _synthetic_hessian(ethanol.positions)
    a = normal_mode_sample(ethanol.numbers, ethanol.positions, h, 600, np.random.default_rng(5))
    b = normal_mode_sample(ethanol.numbers, ethanol.positions, h, 600, np.random.default_rng(5))
    np.testing.assert_array_equal(a.positions, b.positions)


def test_nms_rejects_a_saddle_point(ethanol):
    h = -_synthetic_hessian(ethanol.positions)
    with pytest.raises(SamplingError, match="negative curvature"):
        normal_mode_sample(ethanol.numbers, ethanol.positions, h, 600, np.random.default_rng(0))


def _bond_lengths(mol, pos):
    return np.array([np.linalg.norm(pos[i] - pos[j]) for i, j, _ in mol.bonds])


def _all_distances(pos):
    return np.linalg.norm(pos[:, None] - pos[None], axis=2)


def test_torsion_keeps_bonds_and_fragments_rigid(ethanol):
    rng = np.random.default_rng(2)
    heavy = {tuple(sorted(ethanol.numbers[[i, j]])) for i, j in ethanol.rotatable_bonds()}
    assert heavy == {(6, 6), (6, 8)}  # C-C and C-O
    changed = 0
    for _ in range(50):
        new, bond = torsion_sample(ethanol, ethanol.positions, rng)
        assert bond is not None
        np.testing.assert_allclose(_bond_lengths(ethanol, new), _bond_lengths(ethanol,
                                   ethanol.positions), atol=1e-10)
        changed += not np.allclose(_all_distances(new), _all_distances(ethanol.positions))
    assert changed >= 45  # the dihedral really changes


def test_torsion_without_rotatable_bond_and_ring():
    benzene_like = molecule_from_smiles("C1CC1", name="cyclopropane")
    assert benzene_like.rotatable_bonds() == []
    new, bond = torsion_sample(benzene_like, benzene_like.positions, np.random.default_rng(0))
    assert bond is None and np.array_equal(new, benzene_like.positions)


def test_dimer_distances_uniform_in_range(ethanol):
    probe = molecule_from_smiles(PROBES["H2O"], name="H2O")
    rng = np.random.default_rng(4)
    ds = []
    for _ in range(300):
        placed, d = dimer_sample(ethanol.positions, probe.positions, rng)
        ds.append(d)
        # the probe is rigid
        np.testing.assert_allclose(_all_distances(placed), _all_distances(probe.positions),
                                   atol=1e-10)
    ds = np.array(ds)
    assert ds.min() >= 0.9 - 1e-8 and ds.max() <= 6.0 + 1e-8
    assert abs(ds.mean() - 3.45) < 0.25 and abs(ds.std() - 4.9 / np.sqrt(12)) < 0.2


@pytest.mark.parametrize("distribution, mean, below_half", [("ball", 0.0075, 0.125),
                                                            ("magnitude", 0.005, 0.5)])
def test_random_field_bounds_and_isotropy(distribution, mean, below_half):
    """Ball: mean |E| = 3/4 R and P(|E| < R/2) = 1/8; magnitude: R/2 and 1/2."""
    rng = np.random.default_rng(0)
    fields = np.array([random_field(rng, 0.01, distribution) for _ in range(5000)])
    fields /= FIELD_AU_IN_V_PER_A
    mag = np.linalg.norm(fields, axis=1)
    assert mag.max() <= 0.01 and abs(mag.mean() - mean) < 2e-4
    assert abs((mag < 0.005).mean() - below_half) < 0.015
    unit = fields / mag[:, None]
    assert np.all(np.abs(unit.mean(axis=0)) < 0.05)


def test_default_field_distribution_is_the_authors():
    """The shared eQM7 frames (the authors' data) have mean |E| 0.00746 au and 14.5 % below
    0.005 au: the ball, which the default recipe draws; a recipe without the key (written
    before it existed) keeps the magnitude-uniform draws it was labeled with."""
    from emlpack.qm.recipe import LEGACY_FIELD_DISTRIBUTION, default_recipe

    assert default_recipe()["field_distribution"] == "ball"
    assert LEGACY_FIELD_DISTRIBUTION == "magnitude"
    from emlpack.io import read_structures

    shared = shared_path("data/eqm7_pbe0_subset.xyz")
    mag = np.array([np.linalg.norm(s.field) for s in read_structures(shared)])
    mag /= FIELD_AU_IN_V_PER_A
    assert mag.max() <= 0.01 + 1e-6 and abs(mag.mean() - 0.0075) < 3e-4
    assert abs((mag < 0.005).mean() - 0.125) < 0.03


def test_qm7_radicals_are_restored_to_closed_shell():
    mol = molecule_from_smiles("[H]O[N][C]([H])C([H])([H])[H]", name="oxime")
    assert (mol.bonds[:, 2] == 2).sum() == 1  # the C=N double bond
    assert int(mol.numbers.sum()) % 2 == 0
    with pytest.raises(SamplingError, match="out of scope"):
        molecule_from_smiles("CS", name="methanethiol")


def test_cell_nms_statistics_and_rigid_body_free():
    rng = np.random.default_rng(0)
    pos = rng.uniform(0, 4, size=(4, 3))
    cell = np.diag([4.0, 4.5, 5.0])
    n = 3 * 4 + 9
    a = rng.normal(size=(n, n))
    a = a @ a.T / n + np.eye(n)
    # zero the 6 rigid-body directions of the extended coordinates
    zero = [np.concatenate([np.tile(ax, 4), np.zeros(9)]) for ax in np.eye(3)]
    zero += [np.concatenate([np.cross(ax, pos).ravel(), np.cross(ax, cell).ravel()])
             for ax in np.eye(3)]
    q, _ = np.linalg.qr(np.array(zero).T)
    p = np.eye(n) - q @ q.T
    h = p @ a @ p
    t = 600.0
    energies = []
    for _ in range(3000):
        new_pos, new_cell = cell_normal_mode_sample([6] * 4, pos, cell, lambda p_, c_: h, t, rng)
        d = np.concatenate([(new_pos - pos).ravel(), (new_cell - cell).ravel()])
        energies.append(0.5 * d @ h @ d)
        assert np.allclose(q.T @ d, 0.0, atol=1e-10)
    expected = 0.5 * (n - 6) * BOLTZMANN_EV_K * t
    assert abs(np.mean(energies) - expected) < 0.05 * expected


def test_soft_modes_are_floored_at_the_minimum_force_constant(ethanol):
    """docs/labeling.md: force constants below 0.06 eV/Å²/amu are raised to it, so a nearly
    free mode gets the amplitude of a 0.06 eV/Å²/amu mode, not a huge one."""
    from emlpack.qm.sampling import MIN_MODE_FORCE_CONSTANT

    assert MIN_MODE_FORCE_CONSTANT == 0.06
    h = _synthetic_hessian(ethanol.positions)
    k, modes = normal_modes(ethanol.numbers, ethanol.positions, h)
    soft = k.copy()
    soft[0] = 1e-4  # a nearly free rotor
    t, n = 600.0, 4000
    rng = np.random.default_rng(3)
    q = []
    for _ in range(n):
        s = normal_mode_sample(ethanol.numbers, ethanol.positions, h, t, rng, n_modes=len(k),
                               modes=(soft, modes))
        dx = (s.positions - ethanol.positions).ravel() * np.repeat(
            np.sqrt(masses_of(ethanol.numbers)), 3)
        q.append(modes[:, 0] @ dx)  # mass-weighted amplitude of the soft mode
    var, expected = np.var(q), BOLTZMANN_EV_K * t / 0.06
    assert abs(var - expected) < 5 * expected * np.sqrt(2.0 / n), (var, expected)
    assert var < 1e-2 * BOLTZMANN_EV_K * t / 1e-4  # far below the unfloored variance


def test_magnitude_fields_are_the_draws_of_recipes_without_the_key():
    """The labeled configurations of a stored recipe without ``field_distribution`` must be
    regenerated bit for bit on resume: ``magnitude`` repeats the original formula."""
    a, b = np.random.default_rng(7), np.random.default_rng(7)
    for _ in range(50):
        direction = a.normal(size=3)
        direction /= np.linalg.norm(direction)
        original = direction * a.uniform(0.0, 0.01) * FIELD_AU_IN_V_PER_A
        assert np.array_equal(random_field(b, 0.01, "magnitude"), original)

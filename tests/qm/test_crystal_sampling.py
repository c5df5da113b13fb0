"""Crystal sampling: field and stress sets, reproducible per sample, random displacements and
strains within their bounds, cell-extended NMS from a Hessian (eigenvalue floor)."""

from __future__ import annotations

import numpy as np
import pytest

from emlpack.qm.crystal_sampling import (
    crystal_tasks,
    hessian_sample,
    random_displacement_sample,
    sample_rng,
)
from emlpack.qm.sampling import SamplingError
from emlpack.structure import Structure
from emlpack.units import BOLTZMANN_EV_K, FIELD_AU_IN_V_PER_A

CELL = np.array([[4.6, 0.0, 0.0], [0.9, 4.9, 0.0], [-0.7, 0.6, 5.3]])


def _crystal() -> Structure:
    """Two water molecules (cores O, H, H; 4 pairs each) in a triclinic cell."""
    mol = np.array([[0.0, 0.0, 0.0], [0.757, 0.586, 0.0], [-0.757, 0.586, 0.0]])
    pairs = np.array([[0.38, 0.30, 0.02], [-0.37, 0.31, -0.01], [0.0, -0.25, 0.30],
                      [0.02, -0.24, -0.31]])
    shift = np.array([2.0, 2.5, 2.7])
    return Structure([8, 1, 1, 8, 1, 1], np.vstack([mol + 1.0, mol + shift]),
                     np.vstack([pairs + 1.0, pairs + shift]), cell=CELL, pbc=True)


def test_field_and_stress_sets():
    ref = _crystal()
    tasks = crystal_tasks(ref, {"field": 30, "stress": 20}, seed=3)
    field = [t for t in tasks if t.key.split("/")[1] == "field"]
    stress = [t for t in tasks if t.key.split("/")[1] == "stress"]
    assert len(field) == 30 and len(stress) == 20
    assert not any(t.stress for t in field) and all(t.stress for t in stress)
    norms = np.array([np.linalg.norm(t.structure.field) for t in field])
    assert norms.max() <= 0.01 * FIELD_AU_IN_V_PER_A and norms.min() > 0
    assert all(not np.any(t.structure.field) for t in stress)
    # field set keeps the reference cell, stress set is strained
    assert all(np.array_equal(t.structure.cell, ref.cell) for t in field)
    assert all(not np.allclose(t.structure.cell, ref.cell) for t in stress)
    # random directions: the mean unit vector is small
    unit = np.array([t.structure.field / np.linalg.norm(t.structure.field) for t in field])
    assert np.linalg.norm(unit.mean(axis=0)) < 0.5


def test_samples_are_reproducible_from_their_identity():
    ref = _crystal()
    a = crystal_tasks(ref, {"field": 4, "stress": 4}, seed=1, round_index=2)
    b = crystal_tasks(ref, {"field": 2, "stress": 6}, seed=1, round_index=2)
    by_key = {t.key: t.structure for t in b}
    for t in a:
        if t.key in by_key:
            np.testing.assert_array_equal(t.structure.positions, by_key[t.key].positions)
            np.testing.assert_array_equal(t.structure.field, by_key[t.key].field)
    c = crystal_tasks(ref, {"field": 4}, seed=2, round_index=2)
    assert not np.allclose(c[0].structure.positions, a[0].structure.positions)


def test_random_displacement_statistics_and_strain_bounds():
    ref = _crystal()
    sigma, max_strain = 0.05, 0.02
    disp, strains = [], []
    for i in range(400):
        s = random_displacement_sample(ref, sample_rng(0, 0, "stress", i), sigma, max_strain)
        deform = np.linalg.solve(ref.cell, s.cell)
        eps = deform - np.eye(3)
        np.testing.assert_allclose(eps, eps.T, atol=1e-12)  # symmetric: no rotation
        strains.append(eps)
        # displacement in the reference frame (strain removed)
        disp.append(s.positions @ np.linalg.inv(deform) - ref.positions)
    assert np.abs(strains).max() <= max_strain
    assert np.std(disp) == pytest.approx(sigma, rel=0.05)


def test_pairs_follow_cores_without_displacement():
    ref = _crystal()
    s = random_displacement_sample(ref, np.random.default_rng(0), sigma=0.0)
    np.testing.assert_allclose(s.pairs, ref.pairs, atol=1e-12)
    shifted = hessian_sample(ref, np.eye(3 * ref.n_cores + 9) * 1e12, np.random.default_rng(0))
    np.testing.assert_allclose(shifted.pairs, ref.pairs, atol=1e-4)


def test_hessian_sample_energy_and_eigenvalue_floor():
    """<E_harm> = (3n+3)/2 k_B T; a negative direction is refused unless floored, and then
    sampled with variance k_B T / floor."""
    ref = _crystal()
    n = 3 * ref.n_cores + 9
    rng = np.random.default_rng(0)
    a = rng.normal(size=(n, n))
    h = a @ a.T / n + 2.0 * np.eye(n)
    t = 600.0
    with pytest.raises(SamplingError):
        hessian_sample(ref, -h, rng, t)
    floor = 4.0
    d2 = []
    for i in range(800):
        s = hessian_sample(ref, -h, sample_rng(0, 1, "stress", i), t, min_eigenvalue=floor)
        d = np.concatenate([(s.positions - ref.positions).ravel(), (s.cell - ref.cell).ravel()])
        d2.append(d @ d)
    # all 3n+3 internal directions get k_B T / floor
    expected = (n - 6) * BOLTZMANN_EV_K * t / floor
    assert np.mean(d2) == pytest.approx(expected, rel=0.05)

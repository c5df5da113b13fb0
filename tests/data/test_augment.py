"""Augmentation invariants (paper appendix B): zero net force, torque = d' x E for molecules,
labels change only for augmented configurations, singular cases, PBC, seeded reproducibility."""

from __future__ import annotations

import numpy as np
import pytest

from emlpack.data.augment import AugmentationConfig, augment
from emlpack.data.dataset import Collater
from emlpack.data.references import ConstantReference
from emlpack.geometry import minimum_image
from emlpack.io import read_structures
from emlpack.structure import Structure
from emlpack.units import AUGMENTATION_K_EV_A2, HARTREE
from tests.conftest import shared_path

ALWAYS = AugmentationConfig(enabled=True, probability=1.0)


@pytest.fixture(scope="module")
def eqm7():
    frames = read_structures(shared_path("data/eqm7_pbe0_subset.xyz"), index="::25")
    return frames


def _all_forces(s: Structure) -> np.ndarray:
    pf = s.pair_forces if s.pair_forces is not None else np.zeros_like(s.pairs)
    return np.concatenate([s.forces, pf])


def test_spring_constant_is_two_hartree_per_square_angstrom():
    assert AUGMENTATION_K_EV_A2 == pytest.approx(2.0 * HARTREE)


def test_energy_restoring_force_and_zero_net_force(eqm7):
    for n, s in enumerate(eqm7):
        a, info = augment(s, np.random.default_rng(n), ALWAYS)
        assert info.augmented and not info.singular
        d = info.displacement
        assert 0.06 <= np.linalg.norm(d) <= 0.12
        assert a.energy - s.energy == pytest.approx(0.5 * ALWAYS.k * (d @ d), rel=1e-12)
        np.testing.assert_allclose(a.pairs[info.pair], s.pairs[info.pair] + d)
        moved = np.delete(np.arange(s.n_pairs), info.pair)
        np.testing.assert_array_equal(a.pairs[moved], s.pairs[moved])
        added = _all_forces(a) - _all_forces(s)
        np.testing.assert_allclose(added.sum(0), 0.0, atol=1e-10)
        # the restoring force -k dR on the displaced pair (its own balance share is zero)
        np.testing.assert_allclose(added[s.n_cores + info.pair], -ALWAYS.k * d, atol=1e-12)


def test_torque_matches_field_torque_of_the_new_dipole(eqm7):
    """sum r' x f' - sum r x f = (d' - d) x E: the torque condition of appendix B."""
    for n, s in enumerate(eqm7):
        a, info = augment(s, np.random.default_rng(100 + n), ALWAYS)
        torque = (np.cross(a.all_positions, _all_forces(a)).sum(0)
                  - np.cross(s.all_positions, _all_forces(s)).sum(0))
        expected = np.cross(a.dipole() - s.dipole(), s.field)
        np.testing.assert_allclose(torque, expected, atol=1e-9)
        assert np.linalg.norm(s.field) > 0  # the field term is really exercised


def test_forces_vanish_beyond_cutoff_and_decay_with_distance(eqm7):
    s = eqm7[-1]
    cfg = AugmentationConfig(enabled=True, probability=1.0, cutoff=2.0, cutoff_transition=0.5)
    a, info = augment(s, np.random.default_rng(5), cfg)
    centre = a.pairs[info.pair]
    r = np.linalg.norm(a.all_positions - centre, axis=1)
    added = np.linalg.norm(_all_forces(a) - _all_forces(s), axis=1)
    assert np.all(added[r >= 2.0] == 0.0)
    assert np.any(added[(r < 1.5) & (r > 0)] > 0)


def test_labels_change_only_for_augmented_configurations(eqm7):
    cfg = AugmentationConfig(enabled=True, probability=0.4)
    n_aug = 0
    for n, s in enumerate(eqm7):
        a, info = augment(s, np.random.default_rng(n), cfg)
        if info.augmented:
            n_aug += 1
            assert a.energy != s.energy
        else:
            assert a is s
    assert 0 < n_aug < len(eqm7)


def test_seeded_reproducibility_through_the_collater(eqm7):
    cfg = AugmentationConfig(enabled=True, probability=0.5)
    items = list(enumerate(eqm7))
    ref = ConstantReference(0.0)
    c1, c2 = (Collater(ref, 4.0, 1.0, augmentation=cfg, seed=3) for _ in range(2))
    b1, b2 = c1(items), c2(items)
    assert b1.n_augmented > 0
    assert np.array_equal(b1.graph.positions.numpy(), b2.graph.positions.numpy())
    assert np.array_equal(b1.forces.numpy(), b2.forces.numpy())
    # independent of the batch composition: configuration k gets the same augmentation
    b3 = c1(items[::-1])
    assert sorted(b3.energy.tolist()) == sorted(b1.energy.tolist())
    c2.epoch = 1
    assert not np.array_equal(c2(items).energy.numpy(), b1.energy.numpy())


def test_collinear_neighbours_fall_back_to_force_only_solution():
    h2 = Structure(numbers=[1, 1], positions=[[0.0, 0, 0], [0.74, 0, 0]],
                   pairs=[[0.37, 0, 0]], energy=-31.8, forces=np.zeros((2, 3)),
                   field=[0.0, 0.1, 0.0])
    a, info = augment(h2, np.random.default_rng(0), ALWAYS)
    assert info.augmented and info.singular
    added = _all_forces(a) - _all_forces(h2)
    np.testing.assert_allclose(added.sum(0), 0.0, atol=1e-12)
    assert np.all(np.isfinite(added))


def test_no_neighbour_within_cutoff_leaves_the_configuration_unchanged():
    far = Structure(numbers=[1, 1], positions=[[0.0, 0, 0], [0.74, 0, 0]],
                    pairs=[[0.37, 0, 0]], energy=-31.8, forces=np.zeros((2, 3)))
    cfg = AugmentationConfig(enabled=True, probability=1.0, cutoff=0.2, cutoff_transition=0.1)
    a, info = augment(far, np.random.default_rng(0), cfg)
    assert info.skipped and not info.augmented and a is far


def test_periodic_minimum_image_and_zero_net_force():
    cell = np.diag([5.0, 6.0, 7.0])
    # an H2 molecule straddling the cell face: its partner is near only via the image
    s = Structure(numbers=[1, 1, 1, 1], positions=[[0.1, 1, 1], [4.7, 1, 1], [2.5, 4, 4],
                                                  [3.2, 4, 4]],
                  pairs=[[4.95, 1, 1], [2.85, 4, 4]], cell=cell, pbc=True, energy=-63.6,
                  forces=np.zeros((4, 3)))
    np.testing.assert_allclose(minimum_image(np.array([[4.8, 0, 0]]), cell), [[-0.2, 0, 0]])
    cfg = AugmentationConfig(enabled=True, probability=1.0, cutoff=2.0, cutoff_transition=0.5)
    for seed in range(20):
        a, info = augment(s, np.random.default_rng(seed), cfg)
        if info.pair == 0:
            break
    assert info.pair == 0
    added = _all_forces(a) - _all_forces(s)
    np.testing.assert_allclose(added.sum(0), 0.0, atol=1e-12)
    # the core at x=0.1 is 0.15 Å away through the boundary: it takes most of the balance
    assert np.linalg.norm(added[0]) > np.linalg.norm(added[1]) > 0
    assert np.all(added[2:4] == 0) and np.all(added[5] == 0)


def test_an_augmented_configuration_loses_its_polarizability_label(eqm7):
    """The label is DFT's response about its own centres: a displaced pair is not there."""
    s = eqm7[0].copy(polarizability=np.eye(3))
    moved, info = augment(s, np.random.default_rng(0), ALWAYS)
    assert info.augmented and moved.polarizability is None
    kept, info = augment(s, np.random.default_rng(0), AugmentationConfig(probability=0.0))
    assert not info.augmented and kept.polarizability is not None

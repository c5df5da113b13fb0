"""geometry.py: minimum image on skewed cells (vs a brute-force image search) and pairs carried
with their cores and cell."""

from __future__ import annotations

import itertools

import numpy as np

from emlpack.geometry import carry_pairs, minimum_image, nearest_cores

SKEWED = np.array([[5.0, 0.0, 0.0], [4.6, 1.2, 0.0], [4.3, 0.9, 1.1]])  # far from reduced


def _brute_force(v, cell, reach=14):
    images = np.array(list(itertools.product(range(-reach, reach + 1), repeat=3))) @ cell
    cand = v[:, None, :] + images[None]
    return cand[np.arange(len(v)), np.argmin(np.linalg.norm(cand, axis=-1), axis=1)]


def test_minimum_image_of_a_skewed_cell_is_the_shortest_image():
    rng = np.random.default_rng(0)
    v = rng.uniform(-8, 8, size=(200, 3))
    mic = minimum_image(v, SKEWED)
    np.testing.assert_allclose(np.linalg.norm(mic, axis=1),
                               np.linalg.norm(_brute_force(v, SKEWED), axis=1), atol=1e-12)
    # the difference is a lattice vector
    frac = np.linalg.solve(SKEWED.T, (mic - v).T).T
    np.testing.assert_allclose(frac, np.round(frac), atol=1e-9)
    # a 27-image search (neighbouring cells only) misses shorter images of this cell
    near = _brute_force(v, SKEWED, reach=1)
    assert np.max(np.linalg.norm(near, axis=1) - np.linalg.norm(mic, axis=1)) > 0.5
    np.testing.assert_array_equal(minimum_image(v, None), v)
    np.testing.assert_array_equal(minimum_image(v, SKEWED, pbc=[False] * 3), v)


def test_nearest_core_across_the_boundary():
    cores = np.array([[0.2, 0.1, 0.1], [2.5, 0.6, 0.5]])
    pair = cores[0] + SKEWED[0] + SKEWED[2] - np.array([0.1, 0.0, 0.05])  # image of core 0
    assert nearest_cores([pair], cores, SKEWED)[0] == 0
    assert nearest_cores([pair], cores)[0] == 1  # without PBC the other core is nearer


def test_carried_pairs_keep_their_offsets_and_follow_the_cell():
    rng = np.random.default_rng(1)
    cores = rng.uniform(0, 3, size=(4, 3))
    pairs = cores[[0, 1, 1, 3]] + rng.normal(scale=0.3, size=(4, 3))
    moved = cores + rng.normal(scale=0.05, size=cores.shape)
    out = carry_pairs(pairs, cores, moved)
    np.testing.assert_allclose(out - moved[[0, 1, 1, 3]], pairs - cores[[0, 1, 1, 3]])
    # a pure cell deformation with the cores at fixed fractional coordinates keeps the pairs'
    # fractional coordinates
    new_cell = SKEWED @ (np.eye(3) + 0.02 * np.array([[1, 0.3, 0], [0.3, -1, 0], [0, 0, 0.5]]))
    frac_cores = np.linalg.solve(SKEWED.T, cores.T).T
    out = carry_pairs(pairs, cores, frac_cores @ new_cell, SKEWED, new_cell)
    np.testing.assert_allclose(np.linalg.solve(new_cell.T, out.T).T,
                               np.linalg.solve(SKEWED.T, pairs.T).T, atol=1e-12)

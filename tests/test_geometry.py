"""geometry.py: minimum image on skewed cells (vs a brute-force image search, also through its
callers in io/cores, qm/cp2k and data/augment), pairs carried with their cores and cell,
Voigt strain, rigid-body modes, normal modes, Schur complement and the cosine cutoff."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from emlpack.geometry import (
    STRAIN_BASIS,
    VOIGT,
    carry_pairs,
    cosine_cutoff,
    internal_basis,
    minimum_image,
    minimum_image_distances,
    nearest_cores,
    normal_modes,
    piezo_from_voigt,
    rigid_body_modes,
    schur_complement,
    voigt_piezo,
    voigt_strain,
)

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


# ------------------------------------------------- callers that had a 27-image search by hand
#: a valid but strongly skewed cell (Minkowski-reduced: 2.8, 2.9, 3.4 Å edges), where wrapping
#: the fractional vector into [-1/2, 1/2) and searching the 27 neighbouring images (the former
#: code of io/cores.py, data/augment.py and qm/cp2k/output.py) misses the shortest image
VERY_SKEWED = np.array([[5.0, 0.0, 0.0], [12.0, 2.0, 0.0], [3.0, 1.0, 2.5]])
#: a vector whose minimum image is 1.241 Å long; the former search returned 2.267 Å
SHORT = np.array([2.1, 0.8, 0.3])


def _wrapped_27_images(d, cell):
    """The former hand-written minimum image (wrap, then the 27 neighbouring images)."""
    frac = d @ np.linalg.inv(cell)
    frac -= np.round(frac)
    cand = (frac[:, None, :] + np.array(list(itertools.product((-1, 0, 1), repeat=3)))) @ cell
    return cand[np.arange(len(d)), np.argmin(np.linalg.norm(cand, axis=-1), axis=1)]


def test_the_former_27_image_search_fails_on_the_skewed_cell():
    true = np.linalg.norm(_brute_force(SHORT[None], VERY_SKEWED), axis=1)[0]
    assert true == pytest.approx(1.2409673645990857, abs=1e-12)
    assert np.linalg.norm(minimum_image(SHORT, VERY_SKEWED)) == pytest.approx(true, abs=1e-12)
    assert np.linalg.norm(_wrapped_27_images(SHORT[None], VERY_SKEWED)) > true + 1.0


def test_minimum_image_distances_of_the_skewed_cell():
    """io/cores.py (and the pair checks of relax.py) distances: the 27-image search gave 2.27 Å
    for SHORT; core centres themselves (within 0.01 Å of a nucleus) were never affected."""
    rng = np.random.default_rng(5)
    points = rng.uniform(-3, 8, (4, 3))
    centres = np.concatenate([points[:1] + SHORT, rng.uniform(-3, 8, (6, 3))])
    d = minimum_image_distances(points, centres, VERY_SKEWED, pbc=True)
    assert d[0, 0] == pytest.approx(1.2409673645990857, abs=1e-12)
    brute = np.linalg.norm(_brute_force((centres[None] - points[:, None]).reshape(-1, 3),
                                        VERY_SKEWED), axis=1).reshape(d.shape)
    np.testing.assert_allclose(d, brute, atol=1e-12)
    np.testing.assert_allclose(minimum_image_distances(points, centres),
                               np.linalg.norm(centres[None] - points[:, None], axis=-1))


def test_cp2k_centres_map_to_the_core_nearest_by_minimum_image():
    """qm/cp2k/output.py: the centre is 1.24 Å from core 0 (through a far image) and 1.40 Å
    from core 1; the 27-image search saw 2.27 Å to core 0 and picked core 1."""
    from emlpack.qm.cp2k import map_centres_to_cores

    cores = np.array([[0.0, 0.0, 0.0], [3.5, 0.8, 0.3]])
    mapped, core = map_centres_to_cores(SHORT[None], cores, VERY_SKEWED)
    assert core.tolist() == [0]
    np.testing.assert_allclose(mapped, [minimum_image(SHORT, VERY_SKEWED)], atol=1e-12)
    old = _wrapped_27_images(SHORT[None] - cores, VERY_SKEWED)
    assert np.argmin(np.linalg.norm(old, axis=1)) == 1


def test_augmentation_balances_a_neighbour_seen_through_a_far_image():
    """data/augment.py: the only neighbour is 1.24 Å away through a far image, inside the 2 Å
    cutoff; the 27-image search put it at 2.27 Å (no neighbour: augmentation skipped)."""
    from emlpack.data.augment import AugmentationConfig, augment
    from emlpack.structure import Structure

    s = Structure(numbers=[1], positions=[SHORT], pairs=[[0.0, 0.0, 0.0]], cell=VERY_SKEWED,
                  pbc=True, charge=-1, energy=-1.0, forces=np.zeros((1, 3)),
                  pair_forces=np.zeros((1, 3)))
    cfg = AugmentationConfig(enabled=True, probability=1.0, cutoff=2.0, cutoff_transition=0.5)
    a, info = augment(s, np.random.default_rng(0), cfg)
    assert info.augmented and not info.skipped
    restoring = -cfg.k * info.displacement
    np.testing.assert_allclose(a.forces[0], -restoring, atol=1e-12)  # zero net force


# ------------------------------------------------- Voigt, rigid-body modes, Schur, cutoff
def test_strain_basis_is_symmetric_with_engineering_shear():
    eps = voigt_strain([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    np.testing.assert_allclose(eps, [[1.0, 3.0, 2.5], [3.0, 2.0, 2.0], [2.5, 2.0, 3.0]])
    for big, (i, j) in enumerate(VOIGT):
        assert STRAIN_BASIS[big, i, j] == STRAIN_BASIS[big, j, i] == (1.0 if i == j else 0.5)
    c = np.random.default_rng(2).normal(size=(3, 3, 3))
    e = c + c.transpose(0, 2, 1)
    np.testing.assert_allclose(piezo_from_voigt(voigt_piezo(e)), e)


def test_rigid_body_modes_and_the_internal_basis():
    rng = np.random.default_rng(3)
    pos = rng.normal(size=(5, 3))
    masses = rng.uniform(1, 16, 5)
    for m in (None, masses):
        rb = rigid_body_modes(pos, m)
        assert rb.shape == (15, 6)
        np.testing.assert_allclose(rb.T @ rb, np.eye(6), atol=1e-12)
        q = internal_basis(rb)
        assert q.shape == (15, 9)
        np.testing.assert_allclose(rb.T @ q, 0.0, atol=1e-12)
    # a small rotation of the mass-weighted coordinates lies in the span
    sqm = np.sqrt(masses)[:, None]
    rot = (pos + 1e-6 * np.cross([0.3, -0.2, 0.9], pos) + 1e-6) * sqm - pos * sqm
    rb = rigid_body_modes(pos, masses)
    np.testing.assert_allclose(rb @ (rb.T @ rot.ravel()), rot.ravel(), atol=1e-18)
    assert rigid_body_modes(np.outer(np.arange(4.0), [1, 2, 3])).shape[1] == 5  # linear
    assert rigid_body_modes(pos, rotations=False).shape[1] == 3
    # extended (positions, cell): rotations turn the cell too
    cell = np.diag([4.0, 5.0, 6.0])
    rb = rigid_body_modes(pos, cell=cell)
    assert rb.shape == (24, 6)
    turn = np.concatenate([np.cross([0, 0, 1.0], pos).ravel(), np.cross([0, 0, 1.0], cell).ravel()])
    np.testing.assert_allclose(rb @ (rb.T @ turn), turn, atol=1e-12)


def test_normal_modes_of_a_harmonic_diatomic():
    """Two masses on a spring k: one mode, omega^2 = k (1/m1 + 1/m2), rigid modes removed."""
    k, m = 3.0, np.array([1.0, 16.0])
    u = np.array([1.0, 0.0, 0.0])
    block = k * np.outer(u, u)
    h = np.block([[block, -block], [-block, block]])
    w, v = normal_modes(h, [[0, 0, 0], [1.1, 0, 0]], m)
    np.testing.assert_allclose(w, [k * (1 / m[0] + 1 / m[1])])
    w_all, _ = normal_modes(h, [[0, 0, 0], [1.1, 0, 0]], m, project=False)
    assert len(w_all) == 6


def test_schur_complement_is_the_relaxed_curvature():
    rng = np.random.default_rng(4)
    a = rng.normal(size=(6, 6))
    h = a @ a.T + 6 * np.eye(6)
    keep, elim = np.array([0, 1]), np.array([2, 3, 4, 5])
    # minimising 1/2 x^T H x over the eliminated block at fixed kept x gives x_k^T S x_k / 2
    x_k = np.array([0.3, -0.7])
    x_e = -np.linalg.solve(h[np.ix_(elim, elim)], h[np.ix_(elim, keep)] @ x_k)
    x = np.concatenate([x_k, x_e])
    s = schur_complement(h, keep, elim)
    assert x @ h @ x == pytest.approx(x_k @ s @ x_k)
    np.testing.assert_allclose(schur_complement(h, keep, elim, np.eye(4)), s)


def test_cosine_cutoff_is_one_formula_for_numpy_and_torch():
    import torch

    from emlpack.nn.short_range.common import cosine_cutoff as torch_cutoff

    r = np.linspace(0.0, 5.0, 101)
    f = cosine_cutoff(r, 4.0, 0.5)
    assert np.all(f[r <= 3.5] == 1.0) and np.all(f[r >= 4.0] == 0.0)
    np.testing.assert_allclose(f[(r > 3.5) & (r < 4.0)],
                               0.5 * (1 + np.cos(np.pi * (r[(r > 3.5) & (r < 4.0)] - 3.5) / 0.5)))
    np.testing.assert_array_equal(torch_cutoff(torch.tensor(r), 4.0, 0.5).numpy(), f)


def test_rotations_that_leave_the_cores_in_place():
    """None for a bent molecule, the axial one for a linear molecule (moving the other
    particles about the axis, to first order), all three about a single core."""
    from emlpack.geometry import core_fixed_rotations

    rng = np.random.default_rng(3)
    others = rng.normal(size=(5, 3))
    line = np.array([[0.0, 0.0, -1.2], [0.0, 0.0, 0.1], [0.0, 0.0, 1.3]])
    assert core_fixed_rotations(line + [[0.1, 0, 0], [0, 0, 0], [0, 0, 0]], others).shape == (
        15, 0)
    (axial,) = core_fixed_rotations(line, others).T
    centre = line.mean(axis=0)
    expected = np.cross([0.0, 0.0, 1.0], others - centre).ravel()
    assert abs(abs(axial @ expected) - np.linalg.norm(expected)) < 1e-12
    assert core_fixed_rotations(line[:1], others).shape == (15, 3)
    # nearly linear: within the tolerance given
    bent = line + [[1e-5, 0, 0], [0, 0, 0], [0, 0, 0]]
    assert core_fixed_rotations(bent, others).shape[1] == 0
    assert core_fixed_rotations(bent, others, rtol=1e-3).shape[1] == 1

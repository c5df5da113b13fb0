"""Geometry shared by the package (torch-free): the one home of

* the minimum image (:func:`minimum_image`, :func:`minimum_image_distances`) and pairs carried
  with their cores (:func:`carry_pairs`);
* Voigt notation (:data:`VOIGT` order xx yy zz yz xz xy, engineering shear) and the strain
  basis (:data:`STRAIN_BASIS`, :func:`voigt_strain`), Voigt matrices of tensors;
* rigid-body modes, the internal basis orthogonal to them, normal modes of a Hessian and the
  Schur complement (eliminating relaxed coordinates from a Hessian);
* the cosine cutoff of the model (:func:`cosine_cutoff`, numpy or torch).

Minimum-image vectors come from :func:`ase.geometry.find_mic`, which reduces the cell first
and is exact for any triclinic cell (a hand-written 27-image search is not for skewed cells).
Units: Å for positions and cells, eV/Å² for Hessians, amu for masses.
"""

from __future__ import annotations

import math
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np
import scipy.linalg
from ase.geometry import find_mic

if TYPE_CHECKING:
    from typing import TypeVar

    import torch
    from numpy.typing import ArrayLike

    #: a numpy array or a torch tensor, the same type in and out
    _ArrayT = TypeVar("_ArrayT", np.ndarray, torch.Tensor)


def minimum_image(
    vectors: ArrayLike, cell: ArrayLike | None = None, pbc: ArrayLike | None = None
) -> np.ndarray:
    """Shortest periodic images of ``vectors`` (Å), shape (..., 3); unchanged without PBC.

    ``cell`` rows are the lattice vectors (Å); ``pbc`` three booleans (default: all periodic
    when a non-zero cell is given).
    """
    v = np.asarray(vectors, dtype=float)
    if cell is None or not np.any(cell):
        return v
    pbc = np.ones(3, dtype=bool) if pbc is None else np.asarray(pbc, dtype=bool)
    if not np.any(pbc):
        return v
    mic, _ = find_mic(v.reshape(-1, 3), np.asarray(cell, dtype=float), pbc)
    return mic.reshape(v.shape)


def minimum_image_distances(
    points: ArrayLike, centres: ArrayLike, cell: ArrayLike | None = None, pbc: ArrayLike = False
) -> np.ndarray:
    """Distances (Å) between every point and every centre, shape (n_points, n_centres):
    to the nearest periodic image of the centre under ``pbc`` (``cell`` rows, Å)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    diff = centres[None, :, :] - points[:, None, :]
    if np.any(pbc):
        diff = minimum_image(diff, np.asarray(cell, dtype=np.float64).reshape(3, 3),
                             np.broadcast_to(np.asarray(pbc, dtype=bool), 3))
    return np.linalg.norm(diff, axis=-1)


def nearest_cores(
    pairs: ArrayLike, cores: ArrayLike, cell: ArrayLike | None = None, pbc: ArrayLike | None = None
) -> np.ndarray:
    """Index of the nearest core of every pair (minimum image under PBC), shape (n_pairs,)."""
    pairs = np.asarray(pairs, dtype=float).reshape(-1, 3)
    cores = np.asarray(cores, dtype=float).reshape(-1, 3)
    d = minimum_image(pairs[:, None, :] - cores[None, :, :], cell, pbc)
    return np.argmin(np.linalg.norm(d, axis=-1), axis=1)


def carry_pairs(pairs: ArrayLike, old_cores: ArrayLike, new_cores: ArrayLike,
                old_cell: ArrayLike | None = None, new_cell: ArrayLike | None = None,
                pbc: ArrayLike | None = None) -> np.ndarray:
    """Electron pairs (Å) moved rigidly with their nearest core from ``old_cores`` to
    ``new_cores``; with cells, first affinely with the cell (same fractional coordinates).

    This is the warm start of a relaxation after the cores (and cell) moved, e.g. between MD
    steps, optimisation steps or samples of a crystal.
    """
    pairs = np.asarray(pairs, dtype=float).reshape(-1, 3)
    old_cores = np.asarray(old_cores, dtype=float).reshape(-1, 3)
    new_cores = np.asarray(new_cores, dtype=float).reshape(-1, 3)
    nearest = nearest_cores(pairs, old_cores, old_cell, pbc)
    if old_cell is not None and new_cell is not None and np.any(old_cell):
        affine = np.linalg.solve(np.asarray(old_cell, float), np.asarray(new_cell, float))
        pairs = pairs @ affine
        old_cores = old_cores @ affine
    return pairs + (new_cores - old_cores)[nearest]


# ---------------------------------------------------------------------- Voigt notation, strain
#: Voigt index pairs: xx yy zz yz xz xy
VOIGT = ((0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1))

#: symmetric strain basis in Voigt order, engineering shear: ``eps = sum_J S_J B_J``
#: (``S_4 = 2 eps_yz``), shape (6, 3, 3)
STRAIN_BASIS = np.zeros((6, 3, 3))
for _k, (_i, _j) in enumerate(VOIGT):
    STRAIN_BASIS[_k, _i, _j] = STRAIN_BASIS[_k, _j, _i] = 1.0 if _i == _j else 0.5
STRAIN_BASIS.flags.writeable = False


def voigt_strain(voigt_vector: ArrayLike) -> np.ndarray:
    """Symmetric 3x3 strain ``eps = sum_J S_J B_J`` of a Voigt vector (engineering shear);
    a cell deforms as ``A -> A (I + eps)`` (rows = lattice vectors)."""
    return np.einsum("k,kij->ij", np.asarray(voigt_vector, dtype=float), STRAIN_BASIS)


def voigt_stiffness(c: np.ndarray) -> np.ndarray:
    """6x6 Voigt matrix of a 3x3x3x3 stiffness, symmetrised over ij, kl and (ij)<->(kl)."""
    c = 0.25 * (c + c.transpose(1, 0, 2, 3) + c.transpose(0, 1, 3, 2) + c.transpose(1, 0, 3, 2))
    out = np.array([[c[i, j, k, l] for (k, l) in VOIGT] for (i, j) in VOIGT])
    return 0.5 * (out + out.T)


def voigt_piezo(e: np.ndarray) -> np.ndarray:
    """3x6 Voigt matrix ``e_iJ = (e_ijk + e_ikj)/2`` of a 3x3x3 piezoelectric tensor."""
    return np.array([[0.5 * (e[i, j, k] + e[i, k, j]) for (j, k) in VOIGT] for i in range(3)])


def strain_constants_voigt(e_voigt: np.ndarray, c_voigt: np.ndarray) -> np.ndarray:
    """Piezoelectric strain constants ``d = e : C^-1`` in Voigt form (engineering shear):
    e_iJ (e/Å²) and C_IJ (eV/Å³) give d_iJ in Å/V."""
    return np.asarray(e_voigt) @ np.linalg.inv(c_voigt)


def piezo_from_voigt(e_voigt: np.ndarray, strain_like: bool = False) -> np.ndarray:
    """3x3x3 tensor from a 3x6 Voigt matrix; ``strain_like`` halves the shear components
    (for ``d``, whose Voigt shears carry the engineering factor 2)."""
    out = np.zeros((3, 3, 3))
    for big, (j, k) in enumerate(VOIGT):
        factor = 0.5 if strain_like and j != k else 1.0
        out[:, j, k] = out[:, k, j] = factor * e_voigt[:, big]
    return out


class VoigtViews:
    """Voigt views of a class's ``stiffness`` C_ijkl (3x3x3x3) and proper ``piezo`` e_ijk
    (3x3x3) tensors (mixin of the model's and the reference's crystal tensors)."""

    @property
    def stiffness_voigt(self) -> np.ndarray:
        """C_IJ, 6x6."""
        return voigt_stiffness(self.stiffness)

    @property
    def piezo_voigt(self) -> np.ndarray:
        """e_iJ, 3x6."""
        return voigt_piezo(self.piezo)

    @property
    def strain_constants_voigt(self) -> np.ndarray:
        """d_iJ = e_iK (C^-1)_KJ, engineering shear (factor 2 on J = 4, 5, 6)."""
        return strain_constants_voigt(self.piezo_voigt, self.stiffness_voigt)

    @property
    def strain_constants(self) -> np.ndarray:
        """d_ijk as a tensor (shear components halved from Voigt)."""
        return piezo_from_voigt(self.strain_constants_voigt, strain_like=True)


# ---------------------------------------------------------------------- rigid-body projection
def rigid_body_modes(positions: ArrayLike, masses: ArrayLike | None = None,
                     rotations: bool = True, cell: ArrayLike | None = None,
                     rtol: float = 1e-6) -> np.ndarray:
    """Orthonormal columns spanning the rigid translations (and rotations) of particles at
    ``positions`` (N, 3), in the flattened 3N coordinates.

    ``masses`` (amu): mass-weighted coordinates ``sqrt(m) x`` (default: Cartesian).
    ``cell`` (3, 3): extended coordinates (positions, then the 9 cell components, rows =
    lattice vectors); translations move the positions only, rotations also turn the cell.
    Directions with singular value below ``rtol`` times the largest are dropped (rank 5 for a
    linear molecule).
    """
    pos = np.asarray(positions, dtype=float).reshape(-1, 3)
    n = len(pos)
    sqm = np.ones(n) if masses is None else np.sqrt(np.asarray(masses, dtype=float))
    r = pos - (sqm**2 @ pos) / np.sum(sqm**2)  # about the centre of mass (any origin spans)
    vecs = [(sqm[:, None] * axis[None, :]).ravel() for axis in np.eye(3)]
    if rotations:
        vecs += [(sqm[:, None] * np.cross(axis, r)).ravel() for axis in np.eye(3)]
    if cell is not None:
        cell = np.asarray(cell, dtype=float).reshape(3, 3)
        rot_cell = [np.cross(axis, cell).ravel() for axis in np.eye(3)] if rotations else []
        vecs = [np.concatenate([v, rot_cell[k - 3] if k >= 3 else np.zeros(9)])
                for k, v in enumerate(vecs)]
    u, s, _ = np.linalg.svd(np.array(vecs).T, full_matrices=False)
    return u[:, s > rtol * s.max()]


def core_fixed_rotations(cores: ArrayLike, particles: ArrayLike,
                         rtol: float = 1e-6) -> np.ndarray:
    """Orthonormal columns (3P) spanning the rigid rotations of a molecule that leave its
    ``cores`` (Nc, 3) in place, as displacements of its other ``particles`` (P, 3; Å): none for
    three or more cores off one line, the rotation about the axis of a linear molecule, all
    three for a single core. At fixed cores they are symmetries of the energy, so zero modes
    of the particles' Hessian. A core axis counts as a line when the cores' rotation about it
    is below ``rtol`` times their largest one (as :func:`rigid_body_modes`)."""
    cores = np.asarray(cores, dtype=float).reshape(-1, 3)
    particles = np.asarray(particles, dtype=float).reshape(-1, 3)
    centre = cores.mean(axis=0)
    rc = cores - centre
    moves = np.array([np.cross(axis, rc).ravel() for axis in np.eye(3)]).T  # [3Nc, 3 axes]
    _, s, vt = np.linalg.svd(moves, full_matrices=True)
    scale = float(np.linalg.norm(rc))
    axes = vt[s <= rtol * scale] if scale > 0 else np.eye(3)
    if not len(axes) or not len(particles):
        return np.zeros((3 * len(particles), 0))
    rp = particles - centre
    vecs = np.array([np.cross(axis, rp).ravel() for axis in axes]).T  # [3P, k]
    u, sv, _ = np.linalg.svd(vecs, full_matrices=False)
    return u[:, sv > rtol * max(float(np.linalg.norm(rp)), 1e-300)]


def internal_basis(rigid: np.ndarray) -> np.ndarray:
    """Orthonormal basis (columns) of the complement of the columns of ``rigid``."""
    return scipy.linalg.null_space(np.asarray(rigid).T)


def normal_modes(hessian: ArrayLike, positions: ArrayLike, masses: ArrayLike,
                 project: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Vibrational modes of a Cartesian Hessian (eV/Å²) of particles with ``masses`` (amu).

    Returns ``(k, modes)``: mass-weighted force constants ``omega^2`` (eV/(Å² amu)),
    ascending, and the mass-weighted orthonormal eigenvectors (3N, n_modes). With ``project``
    the rigid translations/rotations are projected out and their directions dropped
    (``3N - 6`` modes, ``3N - 5`` for a linear molecule); otherwise all ``3N``.
    """
    m = np.asarray(masses, dtype=float)
    inv_sqm = np.repeat(1.0 / np.sqrt(m), 3)
    h = np.asarray(hessian, dtype=float)
    h = 0.5 * (h + h.T) * inv_sqm[:, None] * inv_sqm[None, :]
    if not project:
        return np.linalg.eigh(h)
    rb = rigid_body_modes(positions, m)
    proj = np.eye(len(h)) - rb @ rb.T
    w, v = np.linalg.eigh(proj @ h @ proj)
    # drop the rigid-body directions (the eigenvectors with the largest overlap with rb)
    overlap = np.sum((rb.T @ v) ** 2, axis=0)
    keep = np.sort(np.argsort(overlap)[: len(h) - rb.shape[1]])
    return w[keep], v[:, keep]


def schur_complement(hessian: ArrayLike, keep: np.ndarray, eliminate: np.ndarray,
                     basis: np.ndarray | None = None) -> np.ndarray:
    """``H_kk - H_ke B (B^T H_ee B)^-1 B^T H_ek``: second derivatives in ``keep`` with the
    ``eliminate`` variables relaxed within the span of ``basis`` (columns; default: all)."""
    h = np.asarray(hessian, dtype=float)
    h = 0.5 * (h + h.T)
    h_kk = h[np.ix_(keep, keep)]
    h_ke = h[np.ix_(keep, eliminate)]
    h_ee = h[np.ix_(eliminate, eliminate)]
    if basis is not None:
        h_ke = h_ke @ basis
        h_ee = basis.T @ h_ee @ basis
    return h_kk - h_ke @ np.linalg.solve(h_ee, h_ke.T)


#: central finite differences by number of points: (offsets in steps, weights) with
#: f'(0) ~ sum_k w_k f(o_k h) / h, error O(h^2) (2 points) or O(h^4) (4 points)
CENTRAL_DIFFERENCES = {
    2: (np.array([-1.0, 1.0]), np.array([-0.5, 0.5])),
    4: (np.array([-2.0, -1.0, 1.0, 2.0]), np.array([1.0, -8.0, 8.0, -1.0]) / 12.0),
}


# ---------------------------------------------------------------------- cutoff
def cosine_cutoff(r: _ArrayT, cutoff: float, transition: float, xp: ModuleType = np) -> _ArrayT:
    """1 below ``cutoff - transition``, ``(1 + cos(pi x)) / 2`` with
    ``x = (r - cutoff + transition) / transition`` up to ``cutoff``, 0 beyond (Å).

    ``r`` is a numpy array (``xp=numpy``) or a torch tensor (``xp=torch``, differentiable).
    """
    x = ((r - (cutoff - transition)) / transition).clip(0.0, 1.0)
    return 0.5 * (1.0 + xp.cos(math.pi * x))

"""beta-glycine (P2_1, unique axis b): the proper piezoelectric tensor has exactly the 8
nonzero Voigt components e14, e16, e21, e22, e23, e25, e34, e36 (paper), the dielectric and
stiffness tensors the monoclinic form, for any eMLP (E(3)-invariant) on a symmetric cell."""

from __future__ import annotations

import numpy as np
import pytest

from emlpack.io import read_structures
from emlpack.properties.response import crystal_response
from tests.conftest import shared_path
from tests.properties.toy import spring_model

#: 2_1 screw along b in fractional coordinates: (x, y, z) -> (-x, y + 1/2, -z) + origin shift
ROTATION = np.diag([-1.0, 1.0, -1.0])


def symmetrized_glycine():
    """The shared beta-glycine cell made exactly P2_1: monoclinic cell with b along y, every
    particle averaged with the screw image of its partner."""
    s = read_structures(shared_path("data/beta_glycine_pbe_wannier.xyz"))[0]
    lengths = np.linalg.norm(s.cell, axis=1)
    a, c = s.cell[0], s.cell[2]
    beta = np.arccos(a @ c / (lengths[0] * lengths[2]))
    cell = np.array([[lengths[0], 0, 0], [0, lengths[1], 0],
                     [lengths[2] * np.cos(beta), 0, lengths[2] * np.sin(beta)]])
    inv = np.linalg.inv(s.cell)

    def axis(frac):
        """Origin shift of the screw axis in x and z (from the first particle's partner)."""
        img = frac @ ROTATION + np.array([0.0, 0.5, 0.0])
        d0 = frac[None, :, :] - img[:, None, :]
        for j in range(len(frac)):
            t = d0[0, j] - np.round(d0[0, j])
            t[1] = 0.0
            trial = img + t
            dd = frac[None] - trial[:, None]
            dd -= np.round(dd)
            if np.all(np.linalg.norm(dd @ cell, axis=-1).min(axis=1) < 0.15):
                return t
        raise AssertionError("no 2_1 screw axis found")

    def sym(frac, shift_xz):
        """Average every particle with the screw image of its partner (one common axis)."""
        img = frac @ ROTATION + np.array([0.0, 0.5, 0.0]) + shift_xz
        dd = frac[None] - img[:, None]  # [i, j]: frac_j - image_i
        wrap = np.round(dd)
        partner = np.argmin(np.linalg.norm((dd - wrap) @ cell, axis=-1), axis=1)
        assert sorted(partner) == list(range(len(frac)))
        # image of i sits at frac[partner[i]] - wrap; average each particle with its image's
        # preimage: frac_new[p] = (frac[p] + image_i + wrap) / 2 for p = partner[i]
        new = frac.copy()
        for i, p in enumerate(partner):
            new[p] = 0.5 * (frac[p] + img[i] + wrap[i, p])
        return new

    shift = axis(s.positions @ inv)
    cores = sym(s.positions @ inv, shift) @ cell
    pairs = sym(s.pairs @ inv, shift) @ cell
    return s.copy(positions=cores, pairs=pairs, cell=cell)


NONZERO = {(0, 3), (0, 5), (1, 0), (1, 1), (1, 2), (1, 4), (2, 3), (2, 5)}


@pytest.mark.filterwarnings("ignore")
def test_beta_glycine_piezo_has_the_eight_p21_components():
    s = symmetrized_glycine()
    # random SchNet + springs at their (symmetric) current lengths: a positive-definite
    # Hessian, so the Schur complements are well conditioned
    model = spring_model(s, core_cutoff=3.0, pair_cutoff=1.6)
    resp = crystal_response(model, s)
    e = resp.piezo_voigt
    scale = np.abs(e).max()
    zero = [(i, j) for i in range(3) for j in range(6) if (i, j) not in NONZERO]
    assert max(abs(e[i, j]) for i, j in zero) < 1e-8 * scale
    assert min(abs(e[i, j]) for i, j in NONZERO) > 1e-4 * scale
    # monoclinic (unique axis y) dielectric and stiffness tensors
    for eps in (resp.dielectric_clamped, resp.dielectric_relaxed):
        assert abs(eps[0, 1]) + abs(eps[1, 2]) < 1e-8 * np.abs(eps).max()
    c = resp.stiffness_voigt
    for i, j in ((0, 3), (0, 5), (1, 3), (1, 5), (2, 3), (2, 5), (3, 4), (4, 5)):
        assert abs(c[i, j]) < 1e-8 * np.abs(c).max()

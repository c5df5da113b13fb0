"""The labeler's speed-ups (AO cache, XC gradient through the occupied orbitals, max_memory,
reused heap) give the labels of plain PySCF within the campaign's tolerances (1e-5 eV,
1e-4 eV/Å, 1e-4 Å)."""

from __future__ import annotations

import numpy as np
import pytest

from emlpack.io.extxyz import read_reference_frames as read_frames
from emlpack.qm.levels import PAPER, Level
from emlpack.qm.pyscf_labeler import PySCFLabeler, caching_numint
from emlpack.qm.relabel import match_centres
from emlpack.units import FIELD_AU_IN_V_PER_A
from tests.conftest import shared_path

#: the campaign's tolerances: stored labels stay valid when the settings change within them
TOL_E, TOL_F, TOL_C = 1e-5, 1e-4, 1e-4

#: settings of PySCF as it comes (the labeler before the speed-ups)
PLAIN = {"ao_cache_mb": 0, "max_memory_mb": None, "fast_xc_gradient": False, "reuse_heap": False}

METHANOL = (
    np.array([6, 8, 1, 1, 1, 1]),
    np.array([[-0.047, 0.664, 0.0], [-0.047, -0.758, 0.0], [-1.092, 0.952, 0.02],
              [0.43, 1.08, 0.89], [0.45, 1.07, -0.87], [0.86, -1.06, 0.05]]),
)
FIELD = np.array([0.004, -0.006, 0.003]) * FIELD_AU_IN_V_PER_A


def _differences(a, b) -> tuple[float, float, float]:
    """|dE| (eV), max |dF| (eV/Å), max centre distance (Å) after one-to-one matching (starts
    with spreads equal to rounding may list the same centres in another order)."""
    assert a.ok and b.ok, (a.error, b.error)
    return (abs(a.energy - b.energy), float(np.abs(a.forces - b.forces).max()),
            match_centres(a.centres, b.centres)[1])


def test_fast_settings_match_plain_pyscf():
    """Methanol in a field at PBE0/6-31+G*: defaults vs plain PySCF, and a cache that holds
    only part of the grid (the rest evaluated per cycle)."""
    level = Level(basis="6-31+g*")
    numbers, pos = METHANOL
    plain = PySCFLabeler(level, **PLAIN)(numbers, pos, FIELD)
    fast = PySCFLabeler(level)(numbers, pos, FIELD)
    # max_memory 1 MB: PySCF's smallest grid blocks (224 points), of which 20 MB hold a part
    partial = PySCFLabeler(level, ao_cache_mb=20, max_memory_mb=1)(numbers, pos, FIELD)
    for other in (fast, partial):
        d_e, d_f, d_c = _differences(plain, other)
        assert d_e < TOL_E and d_f < TOL_F and d_c < TOL_C, (d_e, d_f, d_c)
        assert d_e < 1e-8 and d_f < 1e-7, (d_e, d_f)  # equal up to rounding in fact
        assert other.scf_cycles == plain.scf_cycles


def test_caching_numint_blocks_equal_plain_blocks():
    """Second and third passes give the blocks of the first (cached part and evaluated tail)."""
    from pyscf import dft, gto

    numbers, pos = METHANOL
    mol = gto.M(atom=[(int(z), tuple(r)) for z, r in zip(numbers, pos, strict=True)],
                basis="6-31g", verbose=0)
    grids = dft.gen_grid.Grids(mol)
    grids.level = 1
    grids.build(with_non0tab=True)
    plain = dft.numint.NumInt()
    reference = [(ao.copy(), w.copy()) for ao, _, w, _ in
                 plain.block_loop(mol, grids, mol.nao, 1, max_memory=1, blksize=None)]
    blocks = len(reference)
    assert blocks > 2
    per_block = reference[0][0].nbytes / 1e6
    ni = caching_numint(budget_mb=per_block * (blocks // 2) + 1e-3)
    for _ in range(3):
        got = [(ao.copy(), w.copy()) for ao, _, w, _ in
               ni.block_loop(mol, grids, mol.nao, 1, max_memory=1)]
        assert len(got) == blocks
        for (ao_r, w_r), (ao_g, w_g) in zip(reference, got, strict=True):
            np.testing.assert_array_equal(w_g, w_r)
            np.testing.assert_array_equal(ao_g, ao_r)
    assert 0 < len(ni._blocks) < blocks
    ni.clear()
    assert not ni._blocks


@pytest.mark.slow
def test_fast_settings_match_plain_pyscf_at_paper_level():
    """Ethanol frame 0 of the eQM7 subset (own field) at the paper's level (~2 min CPU)."""
    (frame,) = read_frames(shared_path("data/eqm7_pbe0_subset.xyz"), "400:401")
    args = (frame.numbers, frame.positions, frame.field)
    plain = PySCFLabeler(PAPER, **PLAIN)(*args)
    fast = PySCFLabeler(PAPER)(*args)
    d_e, d_f, d_c = _differences(plain, fast)
    print(f"ethanol paper level: |dE| {d_e:.1e} eV, |dF| {d_f:.1e} eV/Å, centres {d_c:.1e} Å")
    assert d_e < TOL_E and d_f < TOL_F and d_c < TOL_C, (d_e, d_f, d_c)

"""bonding.py: the largest bonded molecule of a configuration (a model's size domain)."""

from __future__ import annotations

import numpy as np
from ase.build import molecule

from emlpack.bonding import largest_molecule


def test_largest_molecule_counts_the_heavy_atoms_of_the_largest_fragment():
    ethanol = molecule("CH3CH2OH")
    assert largest_molecule(ethanol.numbers, ethanol.positions) == 3
    # a hydrogen-bonded water beside it is another molecule
    water = molecule("H2O")
    o = int(np.flatnonzero(ethanol.numbers == 8)[0])
    water.positions += ethanol.positions[o] + np.array([0.0, 0.0, 2.9]) - water.positions[0]
    dimer = ethanol + water
    assert largest_molecule(dimer.numbers, dimer.positions) == 3
    # a broken C-C bond splits propane into a methyl and an ethyl
    propane = molecule("C3H8")
    c = np.flatnonzero(propane.numbers == 6)
    d = np.linalg.norm(propane.positions[c][:, None] - propane.positions[c][None], axis=-1)
    end = c[int(np.argmax(d.sum(1)))]  # a terminal carbon and its hydrogens move away
    near = np.linalg.norm(propane.positions - propane.positions[end], axis=1) < 1.2
    propane.positions[near] += 1.5 * (propane.positions[end] - propane.positions[c].mean(0))
    assert largest_molecule(propane.numbers, propane.positions) == 2
    h2 = molecule("H2")
    assert largest_molecule(h2.numbers, h2.positions) == 0

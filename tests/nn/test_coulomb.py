"""Molecular Gaussian-charge Coulomb: all pairs without truncation, and the self energy."""

from __future__ import annotations

import math

import numpy as np
import pytest

from emlpack.structure import Structure
from emlpack.units import COULOMB_EV_A, REFERENCE_GAMMA, SQRT_PI
from tests.nn.helpers import ammonium, hydroxide, random_model, water_molecule


def numpy_coulomb(positions, charges, gamma=REFERENCE_GAMMA, eps=1e-10) -> float:
    """k_e [sum_{i<j} q_i q_j erf(gamma r)/(r + eps) + gamma/sqrt(pi) sum q^2]."""
    e = gamma / SQRT_PI * float(charges @ charges)
    for i in range(len(charges)):
        for j in range(i + 1, len(charges)):
            r = float(np.linalg.norm(positions[j] - positions[i]))
            e += charges[i] * charges[j] * math.erf(gamma * r) / (r + eps)
    return COULOMB_EV_A * e


def test_self_energy_of_a_proton():
    model = random_model()
    s = Structure([1], [[0.3, -0.2, 0.1]], np.zeros((0, 3)), charge=1.0)
    out = model.evaluate(s)
    assert out["energy_long_range"] == pytest.approx(COULOMB_EV_A * REFERENCE_GAMMA / SQRT_PI)
    assert out["energy_long_range"] == pytest.approx(3.191459, abs=1e-6)


def test_molecular_coulomb_matches_numpy_all_pairs():
    model = random_model()
    s = water_molecule()
    out = model.evaluate(s)
    assert out["energy_long_range"] == pytest.approx(
        numpy_coulomb(s.all_positions, s.charges), abs=1e-11
    )


def _pair(separation: float, direction=(0.3, -0.5, 0.8)) -> tuple[Structure, Structure, Structure]:
    a = ammonium()
    b = hydroxide()
    u = np.asarray(direction) / np.linalg.norm(direction)
    shift = separation * u
    combined = Structure(
        np.concatenate([a.numbers, b.numbers]),
        np.vstack([a.positions, b.positions + shift]),
        np.vstack([a.pairs, b.pairs + shift]),
        charge=0.0,
    )
    return a, b.copy(positions=b.positions + shift, pairs=b.pairs + shift), combined


@pytest.mark.parametrize("separation", [20.0, 35.0])
def test_distant_fragments_interact_with_full_coulomb_tail(separation):
    """NH4+ and OH- beyond the reference's 16.5 Å: no truncation; the SchNet parts (4 Å)
    are additive, the interaction is the Gaussian-charge sum, ~ -k_e/R."""
    model = random_model()
    a, b, ab = _pair(separation)
    ea, eb, eab = (model.evaluate(s) for s in (a, b, ab))
    assert eab["energy_short_range"] == pytest.approx(
        ea["energy_short_range"] + eb["energy_short_range"], abs=1e-12
    )
    interaction = eab["energy"] - ea["energy"] - eb["energy"]
    qa, qb = a.charges, b.charges
    ra, rb = a.all_positions, b.all_positions
    r = np.linalg.norm(rb[None, :, :] - ra[:, None, :], axis=-1)
    expected = COULOMB_EV_A * np.sum(
        qa[:, None] * qb[None, :] * np.vectorize(math.erf)(REFERENCE_GAMMA * r) / (r + 1e-10)
    )
    assert interaction == pytest.approx(expected, abs=1e-11)
    # monopole term dominates; dipole corrections are a few percent at these distances
    assert interaction == pytest.approx(-COULOMB_EV_A / separation, rel=0.1)
    # forces: the fragments attract along the line between them (Newton's third law)
    fa = eab["forces"][: a.n_cores].sum(0) + eab["pair_forces"][: a.n_pairs].sum(0)
    fb = eab["forces"][a.n_cores :].sum(0) + eab["pair_forces"][a.n_pairs :].sum(0)
    np.testing.assert_allclose(fa, -fb, atol=1e-12)
    u = (b.positions[0] - a.positions[0]) / np.linalg.norm(b.positions[0] - a.positions[0])
    assert fa @ u == pytest.approx(COULOMB_EV_A / separation**2, rel=0.15)

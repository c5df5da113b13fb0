"""Forces, pair forces and stress against finite differences; the external-field term.

Finite differences use a 4th-order central stencil (h = 2e-4 Å or 5e-5 strain, reduced so
that no edge crosses a kink of the cosine cutoff at 3.5 or 4 Å) with the topology of the
undisplaced structure held fixed, as in the model's derivatives. Their error in float64 is
~1e-9 eV/Å (round-off of energies ~1e-13 eV; truncation ~1e-11). Forces and stress are checked
for every registered short-range family (:data:`tests.nn.helpers.FAMILIES`).
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from tests.nn.helpers import (
    FAMILIES,
    all_forces,
    ammonium,
    eqm7_molecule,
    fd_forces,
    fd_virial,
    glycine,
    hydroxide,
    methane,
    random_model,
    reference_model,
    water_crystal,
    water_molecule,
    zero_short_range,
)

FIELD = np.array([0.25, -0.4, 0.3])  # V/Å

MOLECULES = {
    "methane_field": lambda: methane(FIELD),
    "water_field": lambda: water_molecule(FIELD),
    "ammonium_field": lambda: ammonium(FIELD),
    "c2h6o_fixture": eqm7_molecule,
}
CRYSTALS = {
    "water_crystal": water_crystal,
    "water_crystal_field": lambda: water_crystal(FIELD),
    "glycine_p1": lambda: glycine("p1"),
    "glycine_p3_field": lambda: glycine("p3"),
}
# particles checked in beta-glycine (20 cores, then 30 pairs): C, N, O, H cores and pairs
GLYCINE_PARTICLES = [0, 2, 4, 9, 19, 20, 27, 38, 49]


def _particles(s):
    n = s.n_cores + s.n_pairs
    return list(range(n)) if n <= 20 else GLYCINE_PARTICLES


def _models(name, family):
    yield random_model(family=family)
    if family == "schnet" and name.startswith(("c2h6o", "glycine")):
        yield reference_model()


# ---------------------------------------------------------------------- forces
@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("name", list(MOLECULES) + list(CRYSTALS))
def test_forces_match_finite_differences(name, family):
    s = {**MOLECULES, **CRYSTALS}[name]()
    idx = _particles(s)
    for model in _models(name, family):
        out = model.evaluate(s, stress=False)
        forces = all_forces(out)[idx]
        fd = fd_forces(model, s, idx)
        scale = np.abs(forces).max()
        assert scale > 0.5
        np.testing.assert_allclose(forces, fd, atol=1e-8 * max(scale, 1.0), rtol=0)
        # the pairs feel forces too, and they are part of what was compared
        assert np.abs(out["pair_forces"]).max() > 0.1


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("name", ["methane_field", "water_crystal", "glycine_p1"])
def test_short_range_forces_match_finite_differences(name, family):
    """The short-range forces alone (model minus the same model with its short range zeroed),
    to make sure the comparison above is not dominated by the electrostatics."""
    s = {**MOLECULES, **CRYSTALS}[name]()
    idx = _particles(s)
    model = random_model(family=family)
    bare = zero_short_range(copy.deepcopy(model))
    sr = all_forces(model.evaluate(s, stress=False)) - all_forces(bare.evaluate(s, stress=False))
    fd = fd_forces(model, s, idx, part="energy_short_range")
    assert np.abs(sr[idx]).max() > 0.05
    np.testing.assert_allclose(sr[idx], fd, atol=1e-8, rtol=0)


# ---------------------------------------------------------------------- stress
@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("name", list(CRYSTALS))
def test_stress_matches_finite_strain(name, family):
    s = CRYSTALS[name]()
    for model in _models(name, family):
        out = model.evaluate(s, stress=True)
        volume = abs(np.linalg.det(s.cell))
        # dE/d(eps) of the total energy and of the energy without the field term
        full, no_field = fd_virial(
            model, s, parts=("energy", ("energy_short_range", "energy_long_range"))
        )
        scale = np.abs(full).max()
        assert scale > 0.05
        tol = 1e-10 * max(scale, 100.0)  # measured: <= 5.5e-9 eV for |W| up to 356 eV
        np.testing.assert_allclose(out["virial_including_field"], full, atol=tol, rtol=0)
        np.testing.assert_allclose(out["virial"], no_field, atol=tol, rtol=0)
        np.testing.assert_allclose(out["stress"], out["virial"] / volume, rtol=1e-14, atol=0)
        # the stress excludes exactly the field part: dE_field/d(eps) = -mu (x) E
        mu = s.dipole()
        np.testing.assert_allclose(
            out["virial"], out["virial_including_field"] + np.outer(mu, s.field), atol=1e-12
        )
        # rotation invariance of E_sr + E_lr: the virial without the field term is symmetric
        np.testing.assert_allclose(out["virial"], out["virial"].T, atol=1e-12 * max(scale, 1))


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("length", [3.5, 4.0])
def test_energy_and_forces_continuous_as_an_image_edge_crosses_a_kink(family, length):
    """A pair moved along an image edge (core 0 - pair 13 of the neighbouring cell) across
    ``cutoff - transition`` (3.5 Å) or the cutoff (4 Å, where the neighbour list rebuilt at each
    point drops the edge): the energy is C1 there. The pair force jumps by O(delta) (a jump
    of the force itself would not shrink with delta), and the energy difference across equals
    the trapezoid of the forces to O(delta^2) (the cutoff's second derivative jumps there)."""
    model = random_model(family=family)
    s = water_crystal()
    pos, q, shift = s.all_positions, 13, np.array([-1, 0, 0]) @ s.cell
    u = pos[q] + shift - pos[0]
    u /= np.linalg.norm(u)

    def at(r):
        p = pos.copy()
        p[q] = pos[0] - shift + r * u  # the edge (0, 13, -1 0 0) of length r
        out = model.evaluate(s.copy(pairs=p[s.n_cores :]), stress=False)
        return out["energy"], out["pair_forces"][q - s.n_cores] @ u

    jumps, misses = {}, {}
    for delta in (1e-4, 1e-5):
        (e0, f0), (e1, f1) = at(length - delta), at(length + delta)
        jumps[delta] = abs(f1 - f0)
        misses[delta] = abs(e1 - e0 + (f0 + f1) * delta) / abs(e1 - e0)
    assert 8.0 < jumps[1e-4] / jumps[1e-5] < 12.0, jumps  # measured: 10.00 (+-3e-4)
    assert misses[1e-5] < 1e-4, misses  # measured: <= 7e-6


def test_stress_does_not_depend_on_the_field():
    """Same geometry, field on or off: the stress (field part excluded) is identical; the
    virial including the field differs by exactly -mu (x) E (not symmetric)."""
    model = random_model()
    off = model.evaluate(water_crystal(), stress=True)
    s = water_crystal(FIELD)
    on = model.evaluate(s, stress=True)
    np.testing.assert_allclose(on["stress"], off["stress"], atol=1e-13)
    diff = on["virial_including_field"] - off["virial_including_field"]
    np.testing.assert_allclose(diff, -np.outer(s.dipole(), FIELD), atol=1e-12)
    assert np.abs(diff - diff.T).max() > 1e-3
    np.testing.assert_allclose(off["virial_including_field"], off["virial"], atol=0)


# ---------------------------------------------------------------------- field
@pytest.mark.parametrize(
    "make, charge",
    [(methane, 0.0), (water_molecule, 0.0), (ammonium, 1.0), (hydroxide, -1.0)],
)
def test_net_force_is_total_charge_times_field(make, charge):
    model = random_model()
    s = make(FIELD)
    assert s.charges.sum() == charge
    on = model.evaluate(s)
    off = model.evaluate(make())
    np.testing.assert_allclose(all_forces(on).sum(0), charge * FIELD, atol=1e-12)
    np.testing.assert_allclose(all_forces(off).sum(0), 0.0, atol=1e-12)
    # every particle feels q_i E in addition
    np.testing.assert_allclose(
        all_forces(on) - all_forces(off), s.charges[:, None] * FIELD[None, :], atol=1e-12
    )
    # field energy -mu . E, and it is the only field dependence of the energy
    mu = s.dipole()
    assert on["energy_field"] == pytest.approx(-mu @ FIELD, abs=1e-13)
    assert on["energy"] - off["energy"] == pytest.approx(-mu @ FIELD, abs=1e-12)


def test_charged_molecule_translation_in_field():
    """E(r + t) - E(r) = -Q t . E for a charged molecule; zero for a neutral one."""
    model = random_model()
    t = np.array([1.3, -0.7, 2.2])
    for make in (ammonium, methane):
        s = make(FIELD)
        moved = s.copy(positions=s.positions + t, pairs=s.pairs + t)
        q = s.charges.sum()
        de = model.evaluate(moved)["energy"] - model.evaluate(s)["energy"]
        assert de == pytest.approx(-q * t @ FIELD, abs=1e-11)


def test_net_force_vanishes_for_crystals_in_a_field():
    model = random_model()
    for s in (water_crystal(FIELD),):
        out = model.evaluate(s)
        np.testing.assert_allclose(all_forces(out).sum(0), 0.0, atol=1e-11)
        assert out["energy_field"] == pytest.approx(-s.dipole() @ FIELD, abs=1e-13)
    s = glycine("p3")
    out = model.evaluate(s)
    assert np.linalg.norm(s.field) > 0.1
    np.testing.assert_allclose(all_forces(out).sum(0), 0.0, atol=1e-11)

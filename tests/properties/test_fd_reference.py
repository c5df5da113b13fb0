"""Finite-difference reference tensors (emlpack.properties.fd_reference) with an eMLP labeler agree
with the Hessian-based tensors of the same model (emlpack.properties.response): ion-clamped
dielectric, clamped-ion stiffness (at a stressed reference) and clamped-ion proper piezo; the
polarization change is free of polarization quanta and of the order of the centres."""

from __future__ import annotations

import numpy as np
import pytest

from emlpack.calculators.labeler import ModelLabeler
from emlpack.geometry import voigt_piezo, voigt_stiffness
from emlpack.properties.fd_reference import (
    CrystalReferenceError,
    FDSettings,
    compute_reference_tensors,
    fractional_dipole_change,
    reference_tasks,
)
from emlpack.properties.optimize import optimize
from emlpack.properties.response import crystal_response
from tests.nn.helpers import water_crystal
from tests.properties.toy import spring_model


@pytest.fixture(scope="module")
def crystal():
    """Two water molecules in a triclinic cell (springs keep the random model stable),
    internal coordinates relaxed at the fixed (stressed) cell."""
    s = water_crystal()
    model = spring_model(s, core_cutoff=3.5, pair_cutoff=2.0)
    res = optimize(model, s, fmax=1e-9)
    assert res.converged, res.reason
    return model, res.structure


@pytest.fixture(scope="module")
def fd_and_analytic(crystal):
    model, s = crystal
    settings = FDSettings(field_step=1e-3, strain_step=1e-4, points=4)
    fd = compute_reference_tensors(ModelLabeler(model, fmax=1e-10), s, settings)
    return fd, crystal_response(model, s)


def test_reference_has_stress(fd_and_analytic):
    """The check below is only meaningful if the stress-correction terms matter."""
    fd, _ = fd_and_analytic
    assert np.abs(fd.stress0).max() > 1e-3  # eV/Å^3 (> 0.1 GPa)


def test_fd_dielectric_equals_ion_clamped_hessian_dielectric(fd_and_analytic):
    fd, an = fd_and_analytic
    chi = an.dielectric_clamped - np.eye(3)
    np.testing.assert_allclose(fd.dielectric - np.eye(3), chi, atol=1e-6 * np.abs(chi).max())


def test_fd_stiffness_equals_clamped_ion_hessian_stiffness(fd_and_analytic):
    fd, an = fd_and_analytic
    c = voigt_stiffness(an.stiffness_clamped)
    np.testing.assert_allclose(fd.stiffness_voigt, c, atol=1e-6 * np.abs(c).max())


def test_fd_proper_piezo_equals_clamped_ion_hessian_piezo(fd_and_analytic):
    fd, an = fd_and_analytic
    e = voigt_piezo(an.piezo_clamped)
    np.testing.assert_allclose(fd.piezo_voigt, e, atol=1e-6 * np.abs(e).max())
    # and the strain constants follow from the same contraction as the analytic ones
    d = e @ np.linalg.inv(voigt_stiffness(an.stiffness_clamped))
    np.testing.assert_allclose(fd.strain_constants_voigt, d, atol=1e-5 * np.abs(d).max())


def test_dipole_change_ignores_images_and_order(crystal):
    """Moving centres by lattice vectors and shuffling them leaves dp unchanged; a real
    displacement of one pair by dx changes dp by q dx A^-1."""
    _, s = crystal
    rng = np.random.default_rng(0)
    images = rng.integers(-2, 3, size=(s.n_pairs, 3)) @ s.cell
    shuffled = s.copy(pairs=(s.pairs + images)[rng.permutation(s.n_pairs)],
                      positions=s.positions + rng.integers(-1, 2, (s.n_cores, 3)) @ s.cell)
    np.testing.assert_allclose(fractional_dipole_change(s, shuffled), 0.0, atol=1e-12)
    moved = s.pairs.copy()
    dx = np.array([0.01, -0.02, 0.015])
    moved[3] += dx
    np.testing.assert_allclose(fractional_dipole_change(s, shuffled.copy(pairs=moved)),
                               -2.0 * dx @ np.linalg.inv(s.cell), atol=1e-12)


def test_ambiguous_centre_mapping_is_refused(crystal):
    _, s = crystal
    far = s.pairs + 0.3 * s.cell.sum(axis=0) / np.linalg.norm(s.cell.sum(axis=0))
    with pytest.raises(CrystalReferenceError, match="ambiguous"):
        fractional_dipole_change(s, s.copy(pairs=far), max_shift=0.2)


def test_task_layout():
    s = water_crystal()
    tasks = reference_tasks(s, FDSettings())
    assert len(tasks) == 19
    assert sum(t.stress for t in tasks) == 13
    assert all(not np.any(t.structure.field) for t in tasks if t.stress)
    assert len({t.key for t in tasks}) == 19


def test_fd_relaxed_ion_tensors_with_a_relax_callable(crystal):
    """Cores relaxed at every perturbation (``relax``) give the relaxed-ion tensors."""
    model, s = crystal
    res0 = optimize(model, s, fmax=1e-10)
    chord = {"hessian": res0.hessian, "hessian_every": 0}

    def relax(x):
        r = optimize(model, x, fmax=1e-10, **chord)
        assert r.converged, r.reason
        return r.structure

    settings = FDSettings(field_step=1e-3, strain_step=1e-4, points=2)
    fd = compute_reference_tensors(ModelLabeler(model, fmax=1e-10), s, settings, relax=relax)
    an = crystal_response(model, s)
    assert fd.relaxed_ions
    chi = an.dielectric_relaxed - np.eye(3)
    np.testing.assert_allclose(fd.dielectric - np.eye(3), chi, atol=1e-4 * np.abs(chi).max())
    c = an.stiffness_voigt
    np.testing.assert_allclose(fd.stiffness_voigt, c, atol=1e-4 * np.abs(c).max())
    e = an.piezo_voigt
    np.testing.assert_allclose(fd.piezo_voigt, e, atol=1e-4 * np.abs(e).max())

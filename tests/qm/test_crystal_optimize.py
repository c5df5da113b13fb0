"""Crystal optimisation with a labeler (ASE BFGS + FrechetCellFilter): the minimum of a model
labeler agrees with the model's own BO cell optimisation, every step is stored, and an
interrupted run resumes by replaying the stored steps."""

from __future__ import annotations

import numpy as np
import pytest
from ase.geometry import cell_to_cellpar

from emlpack.calculators.labeler import ModelLabeler
from emlpack.data.store import DatasetStore
from emlpack.properties.optimize import optimize
from emlpack.qm.crystal_optimize import (
    CrystalOptimizationError,
    optimize_crystal,
    symmetrized_start,
)
from emlpack.units import EV_PER_A3_IN_GPA
from tests.nn.helpers import water_crystal
from tests.properties.toy import spring_model


@pytest.fixture(scope="module")
def setup():
    s = water_crystal()
    return spring_model(s, core_cutoff=3.5, pair_cutoff=2.0), s


class Counting:
    def __init__(self, labeler):
        self.labeler, self.calls = labeler, 0

    def __call__(self, structure, *, stress=False):
        self.calls += 1
        return self.labeler(structure, stress=stress)


def test_minimum_agrees_with_model_cell_optimisation(setup, tmp_path):
    """From a strained, displaced start next to the model's BO cell minimum (Newton with exact
    Hessians, emlpack.properties.optimize), BFGS on the labeler's energy/forces/stress returns to
    it."""
    model, s = setup
    ref = optimize(model, s, cell=True, fmax=1e-6, smax=1e-8, max_iterations=100)
    assert ref.converged
    rng = np.random.default_rng(0)
    deform = np.eye(3) + np.diag([0.01, -0.01, 0.005])
    start = ref.structure.copy(
        positions=(ref.structure.positions + rng.normal(scale=0.03, size=(s.n_cores, 3)))
        @ deform, cell=ref.structure.cell @ deform, pairs=ref.structure.pairs @ deform)
    lab = Counting(ModelLabeler(model, fmax=1e-9))
    res = optimize_crystal(lab, start, fmax=1e-3, max_steps=200, symprec=None,
                           store_path=tmp_path / "opt.h5", log=lambda m: None)
    assert res.converged and res.max_force < 1e-3
    assert res.calculations == lab.calls == res.steps
    assert abs(res.structure.energy - ref.energy) < 1e-5
    # the toy crystal's cell modes are soft (a 1 % volume change costs ~1e-5 eV): same
    # minimum within that flatness
    par, par_ref = cell_to_cellpar(res.structure.cell), cell_to_cellpar(ref.structure.cell)
    np.testing.assert_allclose(par[:3], par_ref[:3], rtol=0.01)
    np.testing.assert_allclose(par[3:], par_ref[3:], atol=1.0)
    assert res.max_stress_gpa < 0.05
    assert res.history[-1][0] < res.history[0][0]
    with DatasetStore(tmp_path / "opt.h5") as store:
        assert store.keys() == [f"opt/{i:03d}" for i in range(res.steps)]
        last = store.structure(res.steps - 1)
    np.testing.assert_array_equal(last.positions, res.structure.positions)
    assert last.stress is not None and last.info["kind"] == "stress"


def test_resume_replays_stored_steps(setup, tmp_path):
    model, s = setup
    kwargs = dict(fmax=1e-3, symprec=None, log=lambda m: None)
    full = optimize_crystal(ModelLabeler(model, fmax=1e-9), s, max_steps=40, **kwargs)
    store = tmp_path / "opt.h5"
    first = Counting(ModelLabeler(model, fmax=1e-9))
    part = optimize_crystal(first, s, max_steps=5, store_path=store, **kwargs)
    assert not part.converged and first.calls == part.steps
    second = Counting(ModelLabeler(model, fmax=1e-9))
    rest = optimize_crystal(second, s, max_steps=40, store_path=store, **kwargs)
    assert second.calls == rest.steps - part.steps  # the stored steps are not recomputed
    assert rest.steps == full.steps
    np.testing.assert_allclose(rest.structure.positions, full.structure.positions, atol=1e-10)
    np.testing.assert_allclose(rest.structure.cell, full.structure.cell, atol=1e-10)
    # other settings: a new trajectory from the same start; its steps are numbered on
    other = optimize_crystal(ModelLabeler(model, fmax=1e-9), s, max_steps=3, maxstep=0.005,
                             store_path=store, fmax=1e-3, symprec=None, log=lambda m: None)
    with DatasetStore(store) as st:
        keys = st.keys()
    n_new = other.steps - 1  # all but the (stored) start
    assert other.calculations == n_new > 0 and len(keys) == rest.steps + n_new
    assert keys[-1] == f"opt/{rest.steps + n_new - 1:03d}"


def test_symmetry_is_kept():
    """The paper's P2_1 beta-glycine (P2_1 at 0.01 Å, P1 at 1e-5 Å) is symmetrised, and the
    optimisation keeps P2_1 although the labeler's forces and stress carry P1 noise."""
    from tests.conftest import require, shared_path

    require("spglib")
    from ase.spacegroup.symmetrize import check_symmetry

    from emlpack.io.extxyz import read_structures
    from emlpack.qm.crystal_optimize import to_atoms

    g = read_structures(shared_path("data/beta_glycine_pbe_wannier.xyz"))[0]
    assert check_symmetry(to_atoms(g), 1e-5).international == "P1"
    start = symmetrized_start(g, symprec=0.01)
    assert check_symmetry(to_atoms(start), 1e-6).international == "P2_1"
    rng = np.random.default_rng(0)
    target = start.positions + rng.normal(scale=0.05, size=start.positions.shape)

    def noisy(structure, *, stress=False):  # a P1 harmonic well plus P1 noise
        d = structure.positions - target
        noise = rng.normal(scale=1e-3, size=(3, 3))
        return structure.copy(energy=float(0.5 * (d**2).sum()),
                              forces=-d + rng.normal(scale=1e-3, size=d.shape),
                              stress=(noise + noise.T) / EV_PER_A3_IN_GPA)

    res = optimize_crystal(noisy, g, fmax=1e-2, max_steps=30, symprec=0.01, log=lambda m: None)
    assert res.steps > 1
    assert check_symmetry(to_atoms(res.structure), 1e-6).international == "P2_1"
    assert not np.allclose(res.structure.positions, start.positions, atol=1e-3)


def test_rejects_molecules(setup):
    model, s = setup
    with pytest.raises(CrystalOptimizationError, match="periodic"):
        optimize_crystal(ModelLabeler(model), s.copy(pbc=False), log=lambda m: None)

"""emlpack.pairs: the one check of relaxed pairs (minimum image, thresholds per caller) and the
solvers behind one interface (the warm-start solver's core forces are the model's)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from ase import Atoms

from emlpack.calculators.ase import EMLPCalculator
from emlpack.dynamics.md import Watchdog
from emlpack.pairs.checks import check_pairs
from emlpack.pairs.relax import RelaxOptions, relax_pairs
from emlpack.pairs.solvers import BatchedSolver, BoxedLBFGSB, PairSolver, WarmStartSolver
from emlpack.structure import Structure
from tests.nn.helpers import FAMILIES, water_molecule
from tests.properties.toy import spring_model

CELL = 5.0 * np.eye(3)


def test_check_pairs_uses_the_minimum_image():
    """Across a periodic boundary two pairs 0.03 Å apart have merged and a pair 0.2 Å from a
    core's image is at home; without the cell the pairs are 4.97 Å apart and one is stray."""
    cores = np.array([[0.1, 2.5, 2.5], [2.5, 2.5, 2.5]])
    pairs = np.array([[0.02, 2.0, 2.0], [4.99, 2.0, 2.0], [4.9, 2.5, 2.5]])
    periodic = check_pairs(pairs, cores, CELL, True)
    assert "pairs 0 and 1 are 0.03 Å apart (merged; threshold 0.1 Å)" in periodic
    assert "nearest core" not in periodic
    molecule = check_pairs(pairs, cores)
    assert "merged" not in molecule
    assert "pair 1 is 2.59 Å from the nearest core (threshold 2 Å)" in molecule


def test_thresholds_per_caller():
    """Relaxation: merged below 0.1 Å; MD's watchdog (docs/md.md): below 0.2 Å."""
    cores = np.zeros((1, 3))
    pairs = np.array([[0.5, 0.0, 0.0], [0.5, 0.15, 0.0]])
    assert RelaxOptions().min_pair_distance == 0.1
    assert check_pairs(pairs, cores) == ""
    assert "threshold 0.2 Å" in Watchdog().check(cores, pairs, {})
    assert "negative pair curvature" in check_pairs(pairs, cores, min_curvature=-1e-3)
    assert "no convergence to fmax=1e-05 eV/Å" in check_pairs(pairs, cores, converged=False,
                                                                fmax=1e-5)


def test_a_flat_valley_is_not_a_saddle():
    """The relaxation's check takes smallest curvatures above -flat_curvature (1e-3 eV/Å^2:
    the azimuth of a triple bond's pairs is flat) as a flat valley; a curvature at or below it
    is a saddle. MD's watchdog keeps the strict threshold (any curvature <= 0)."""
    cores = np.zeros((1, 3))
    pairs = np.array([[0.5, 0.0, 0.0], [-0.5, 0.0, 0.0]])
    flat = RelaxOptions().flat_curvature
    assert flat == 1e-3
    assert check_pairs(pairs, cores, min_curvature=-3e-4, flat_curvature=flat) == ""
    assert "saddle" in check_pairs(pairs, cores, min_curvature=-1e-3, flat_curvature=flat)
    assert "saddle" in check_pairs(pairs, cores, min_curvature=-3e-4)


@pytest.fixture(scope="module")
def water():
    torch.set_num_threads(1)
    s = water_molecule()
    return spring_model(s), s


def test_solvers_share_one_interface(water):
    model, s = water
    start = s.copy(pairs=s.pairs + 0.05)
    for solver in (BatchedSolver(RelaxOptions(fmax=1e-7)), WarmStartSolver(fmax=1e-7),
                   BoxedLBFGSB(fmax=1e-7)):
        assert isinstance(solver, PairSolver)
        r = solver.relax(model, start)
        assert r.converged and not r.reason, (type(solver).__name__, r.reason)
        ref = relax_pairs(model, start, fmax=1e-9)[0]
        np.testing.assert_allclose(r.pairs, ref.pairs, atol=1e-5)


def test_warm_start_core_forces_are_the_models(water):
    """The calculator takes the warm-start solver's core forces without evaluating again: they
    equal the model's forces at the returned pairs, over a few moved geometries."""
    model, s = water
    solver = WarmStartSolver(fmax=1e-8)
    atoms = Atoms(s.numbers, s.positions)
    atoms.calc = EMLPCalculator(model, pairs=s.pairs, pair_solver=solver, check_bonding=False)
    rng = np.random.default_rng(0)
    for _ in range(4):
        atoms.positions = s.positions + rng.normal(scale=0.02, size=s.positions.shape)
        forces = atoms.get_forces()
        pairs = atoms.calc.results["electron_pairs"]
        out = model.evaluate(Structure(s.numbers, atoms.positions, pairs), dtype=torch.float64)
        np.testing.assert_allclose(forces, out["forces"], atol=1e-9)
        assert atoms.get_potential_energy() == pytest.approx(out["energy"], abs=1e-10)
        assert np.abs(out["pair_forces"]).max() < 1e-7
    assert len(solver.history) == 4


@pytest.mark.parametrize("method", ["corrected", "warm"])
def test_first_residual_is_the_pair_force_at_the_predicted_pairs(water, method):
    """``diagnostics["first_residual"]`` (the predictor's error, eV/Å) is the largest pair-force
    component of the model at the pairs :meth:`WarmStartSolver.predict` gives for the new cores,
    before any relaxation step."""
    model, s = water
    solver = WarmStartSolver(method, fmax=1e-8)
    rng = np.random.default_rng(1)
    velocity = rng.normal(scale=0.002, size=s.positions.shape)
    for k in range(5):
        moved = s.copy(positions=s.positions + k * velocity, pairs=s.pairs)
        predicted = solver.predict(moved.positions) if solver.history else None
        solver.relax(model, moved)
    out = model.evaluate(moved.copy(pairs=predicted), dtype=torch.float64)
    residual = np.abs(out["pair_forces"]).max()
    assert solver.diagnostics["first_residual"] == pytest.approx(residual, rel=1e-9)
    assert solver.diagnostics["first_residual"] > solver.diagnostics["max_force"]


def test_corrected_pairs_meet_fmax_when_evaluated(water):
    """``"corrected"`` returns pairs moved by a final Newton step it does not evaluate; its stop
    rule (estimate below ``CORRECTED_MARGIN`` x fmax) must still leave the model's pair force
    at the returned pairs below fmax, step after step of a smooth trajectory."""
    model, s = water
    fmax = 1e-5
    solver = WarmStartSolver("corrected", fmax=fmax)
    rng = np.random.default_rng(2)
    velocity = rng.normal(scale=0.004, size=s.positions.shape)
    worst = 0.0
    for k in range(20):
        moved = s.copy(positions=s.positions + k * velocity + 0.01 * np.sin(0.5 * k), pairs=s.pairs)
        r = solver.relax(model, moved)
        assert r.converged, r.reason
        out = model.evaluate(moved.copy(pairs=r.pairs), dtype=torch.float64)
        worst = max(worst, float(np.abs(out["pair_forces"]).max()))
    assert worst < fmax, worst


def test_a_guess_restart_without_a_guess_is_a_failed_attempt(water, monkeypatch):
    """A "guess" restart whose guess fails (e.g. a distorted MD frame with neither a Boys nor
    a Lewis structure) is CalculationFailed, which the MD watchdog counts as a failed attempt,
    not an exception that ends the run."""
    from ase.calculators.calculator import CalculationFailed

    import emlpack.pairs.solvers as solvers
    from emlpack.qm.pyscf_labeler import LabelingError

    model, s = water
    solver = WarmStartSolver(fmax=1e-7)
    solver.relax(model, s)

    def no_guess(*args, **kwargs):
        raise LabelingError("guess_pairs: PySCF Foster-Boys guess failed: no core centre")

    monkeypatch.setattr(solvers, "guess_matched", no_guess)
    solver.restart = "guess"
    with pytest.raises(CalculationFailed, match="no fresh electron-pair guess.*Boys"):
        solver.relax(model, s)


def _autograd_position_hessian(model, s):
    g = model.graph(s, dtype=torch.float64)
    return torch.autograd.functional.hessian(
        lambda x: model.energy(g, x.reshape(-1, 3))[0], g.positions.reshape(-1)).numpy()


@pytest.mark.parametrize("family", FAMILIES)
def test_exact_blocks_equal_autograd_and_the_forward_differences(family):
    """MD's fresh-start blocks (pair-pair, core-pair) equal torch.autograd's position Hessian
    of a random EMLP of every short-range family on C2H6O under a field, with pairs off their
    minimum (SchNet: closed form; other families: their short range by reverse over reverse);
    the forward differences agree to their step's error. A toy model with its own energy
    term gets the exact pair rows (reverse over reverse of its whole energy), not
    differences."""
    from emlpack.pairs.solvers import difference_blocks, energy_gradient_function, exact_blocks
    from tests.nn.helpers import eqm7_molecule, random_model

    model = random_model(seed=2, family=family, elements=(1, 6, 8))
    s = eqm7_molecule()
    s = s.copy(pairs=s.pairs + 0.03 * np.sin(np.arange(s.pairs.size)).reshape(s.pairs.shape))
    hpp, hcp = exact_blocks(model, s)
    full = _autograd_position_hessian(model, s)
    k = 3 * s.n_cores
    scale = np.abs(full).max()
    np.testing.assert_allclose(hpp, full[k:, k:], rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(hcp, full[:k, k:], rtol=0, atol=1e-12 * scale)
    fd_pp, fd_cp = difference_blocks(energy_gradient_function(model, s)[0], s.pairs, s.n_cores)
    np.testing.assert_allclose(fd_pp, hpp, rtol=0, atol=1e-3 * scale)
    np.testing.assert_allclose(fd_cp, hcp, rtol=0, atol=1e-3 * scale)
    w = water_molecule()
    toy = spring_model(w)
    toy_pp, toy_cp = exact_blocks(toy, w)
    ref = _autograd_position_hessian(toy, w)
    k = 3 * w.n_cores
    scale = np.abs(ref).max()
    np.testing.assert_allclose(toy_pp, ref[k:, k:], rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(toy_cp, ref[:k, k:], rtol=0, atol=1e-12 * scale)


def test_floored_step_of_an_ill_conditioned_indefinite_model():
    """The warm-start step ``H^-1 g`` with H's eigenvalues floored, on the carried model of a
    real MD step where two pairs had merged (eqm7 study, a non-augmented model: curvatures of
    4e17 eV/Å^2 beside negative ones of -94). There a Cholesky factorisation can pass for an
    indefinite H (rounding), and the old fallback raised LinAlgError out of the MD: the step
    must be the eigendecomposition's. A well-conditioned positive definite model keeps the
    plain Newton step; a non-finite one is a failed relaxation."""
    from ase.calculators.calculator import CalculationFailed

    from emlpack.pairs.solvers import _CURVATURE_FLOOR, _floored_solve

    data = np.load(Path(__file__).parent / "fixtures" / "merging_pairs_model_hessian.npz")
    h, g = data["h"], data["g"]
    w, v = np.linalg.eigh(h)
    assert w[0] < -90 and w[-1] > 1e17
    floored = v @ ((v.T @ g) / np.maximum(w, _CURVATURE_FLOOR))
    np.testing.assert_allclose(_floored_solve(h, g), floored, rtol=0, atol=1e-12)
    rng = np.random.default_rng(0)
    a = rng.normal(size=(12, 12))
    spd = a @ a.T + 12 * np.eye(12)
    b = rng.normal(size=12)
    np.testing.assert_allclose(_floored_solve(spd, b), np.linalg.solve(spd, b), rtol=1e-12)
    with pytest.raises(CalculationFailed, match="non-finite"):
        _floored_solve(np.where(np.eye(12) > 0, np.nan, spd), b)

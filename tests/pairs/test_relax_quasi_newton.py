"""The default pair relaxation (analytic electrostatic pair Hessian + SR1 short-range model):
its analytic electrostatics equal autograd, and it reaches the exact-Newton minima."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import torch

import emlpack.pairs.relax.problem as problem_module
from emlpack.io import read_structures
from emlpack.nn.checkpoint import load_model as load_checkpoint
from emlpack.nn.electrostatics import coulomb_molecular, ewald_reciprocal
from emlpack.pairs.relax import pair_hessian, relax_pairs
from emlpack.pairs.relax.bond_rotations import BondRotations
from emlpack.pairs.relax.problem import CoulombPairs, PairProblem
from emlpack.structure import Structure
from tests.conftest import shared_path
from tests.legacy.test_reference_fixtures import load_model

TRAINED = Path(__file__).resolve().parents[2] / "benchmarks" / "fixtures" / "eqm7_small_trained.pt"


@pytest.fixture(scope="module")
def small():
    return load_model("small")


@pytest.fixture(scope="module")
def trained():
    model = load_checkpoint(TRAINED)
    model.eval()
    return model


def _electrostatic_reference(model, g, prob, x):
    c = model.config

    def energies(x):
        pos = g.positions.index_put((prob.pair_idx,), x)
        return (
            coulomb_molecular(pos, g.charges, g.coulomb_i, g.coulomb_j, g.batch, ~g.pbc,
                              g.n_structures, c.gamma, c.coulomb_eps)
            + ewald_reciprocal(pos, g.charges, g.batch, g.cell, g.kvec_n, g.kvec_batch, c.gamma)
        )

    def energy(x):
        return energies(x).sum()

    return energies(x), torch.func.grad(energy)(x), torch.func.hessian(energy)(x)


def test_analytic_electrostatic_pair_hessian_equals_autograd(small):
    """Molecules (Gaussian Coulomb) and a crystal (reciprocal Ewald) in one batch: the analytic
    pair gradient and every pair-pair 3x3 block equal autograd to 1e-10 relative, the energies
    the model's electrostatic energies to 1e-12 relative."""
    mol = read_structures(shared_path("data/eqm7_pbe0_subset.xyz"), index="60:62")
    crystal = read_structures(shared_path("data/beta_glycine_pbe_wannier.xyz"), index="0:1")
    g = small.graph(mol + crystal, dtype=torch.float64)
    prob = PairProblem(small, g)
    x = g.positions[prob.pair_idx].clone()
    x = x + 0.05 * torch.sin(torch.arange(x.numel(), dtype=x.dtype)).reshape(x.shape)
    grad, hess, energy = CoulombPairs(small, prob)(x, energy=True)
    e_ref, g_ref, h_ref = _electrostatic_reference(small, g, prob, x)
    assert torch.abs(energy - e_ref).max() <= 1e-12 * torch.abs(e_ref).max()
    assert torch.abs(grad - g_ref).max() <= 1e-10 * torch.abs(g_ref).max()
    n = len(x)
    dense = torch.zeros(n, 3, n, 3, dtype=x.dtype)
    for a in range(n):
        for b in range(n):
            if prob.pair_batch[a] == prob.pair_batch[b]:
                s, la, lb = prob.pair_batch[a], prob.local[a], prob.local[b]
                dense[a, :, b, :] = hess[s, 3 * la:3 * la + 3, 3 * lb:3 * lb + 3]
    # pairs of different structures do not interact
    assert torch.abs(dense - h_ref).max() <= 1e-10 * torch.abs(h_ref).max()


def _starts(index: str, amount: float = 0.05, seed: int = 0):
    rng = np.random.default_rng(seed)
    out = []
    for s in read_structures(shared_path("data/eqm7_pbe0_subset.xyz"), index=index):
        v = rng.normal(size=s.pairs.shape)
        out.append(s.copy(pairs=s.pairs + amount * v / np.linalg.norm(v, axis=1, keepdims=True)))
    return out


@pytest.mark.parametrize("which", ["small", "trained"])
def test_quasi_newton_reaches_the_exact_newton_minima(which, small, trained):
    """Same converged structures, energies within 1e-6 eV, on the fixture (random) weights and
    on the small trained model; the quasi-Newton computes no exact Hessian on the way."""
    model = small if which == "small" else trained
    starts = _starts("::75")  # 8 configurations spread over the 6 molecules
    qn = relax_pairs(model, starts, fmax=1e-6, check_curvature=False, newton_after=0)
    ref = relax_pairs(model, starts, fmax=1e-6, initial_hessian="exact", check_curvature=False)
    compared = 0
    for a, b in zip(qn, ref, strict=True):
        if b.failed:  # random weights merge some pairs; those are no minima to compare
            continue
        assert not a.failed, a.reason
        assert a.max_force < 1e-6
        assert a.energy == pytest.approx(b.energy, abs=1e-6)
        assert a.n_hessians == 0
        compared += 1
    assert compared >= (8 if which == "trained" else 2)


def test_float32_start_reaches_the_float64_minima(trained):
    """The float32 start phase (forced on for a small batch) ends at the float64 quasi-Newton
    minima: energies within 1e-6 eV, forces converged in float64."""
    starts = _starts("::75")
    f64 = relax_pairs(trained, starts, fmax=1e-6, check_curvature=False, float32_above=0)
    f32 = relax_pairs(trained, starts, fmax=1e-6, check_curvature=False, float32_min_pairs=0)
    for a, b in zip(f32, f64, strict=True):
        assert not a.failed, a.reason
        assert a.max_force < 1e-6
        assert a.energy == pytest.approx(b.energy, abs=1e-6)


def test_analytic_electrostatics_path_reaches_the_full_model_minima(trained):
    """A plain EMLP's evaluations leave the electrostatics to the analytic pair terms; a model
    class with its own ``energy_parts`` (same energy) is evaluated whole: same minima, energies
    within 1e-8 eV at fmax 1e-6, and the reported energies are the full model's."""
    import copy

    from emlpack.nn.potential import EMLP

    class OwnParts(EMLP):
        def energy_parts(self, *args, **kwargs):
            return super().energy_parts(*args, **kwargs)

    whole = copy.deepcopy(trained)
    whole.__class__ = OwnParts
    starts = _starts("::75")
    plain = relax_pairs(trained, starts, fmax=1e-6, check_curvature=False, float32_above=0)
    full = relax_pairs(whole, starts, fmax=1e-6, check_curvature=False)
    for a, b, s in zip(plain, full, starts, strict=True):
        assert not a.failed and not b.failed, (a.reason, b.reason)
        assert a.energy == pytest.approx(b.energy, abs=1e-8)
        exact = trained.evaluate(s.copy(pairs=a.pairs))["energy"]
        assert a.energy == pytest.approx(exact, abs=1e-10)


def test_bond_rotation_steps():
    """A tangential step turns a pair about the axis through its two nearest cores (both
    distances kept); a small step differs from the straight step by O(|s|^2 / rho); pairs near
    the axis and crystals take the straight step."""
    from emlpack.structure import Structure

    cores = np.array([[0.0, 0.0, 0.0], [1.2, 0.0, 0.0], [5.0, 0.0, 0.0], [9.0, 0.0, 0.0]])
    far = [[7.0, 3.0 * k, 0.0] for k in (1, 2, 3)]
    pairs = np.array([[0.6, 0.35, 0.0], [0.6, 0.05, 0.0]] + far)
    mol = Structure(np.array([6, 6, 1, 1]), cores, pairs)
    x = torch.as_tensor(pairs)
    turn = BondRotations([mol], x)
    tangential = torch.zeros_like(x)
    tangential[:2, 2] = 0.1
    new = turn(x, tangential).numpy()
    for c in cores[:2]:
        assert np.linalg.norm(new[0] - c) == pytest.approx(np.linalg.norm(pairs[0] - c), abs=1e-12)
    assert np.allclose(new[1], pairs[1] + tangential[1].numpy(), atol=1e-15)  # rho < 0.2 Å
    small_step = torch.zeros_like(x)
    small_step[0] = torch.tensor([1e-4, -2e-4, 3e-4])
    assert torch.abs(turn(x, small_step) - (x + small_step)).max() < 1e-6  # |s|^2 / rho
    crystal = Structure(np.array([6, 6, 1, 1]), cores, pairs, cell=12.0 * np.eye(3), pbc=True)
    straight = BondRotations([crystal], x)(x, tangential)
    assert torch.equal(straight, x + tangential)


def test_collective_rotation_turns_a_bonds_pairs_together():
    """The probe step turns every pair of a group about one bond by the same angle in the
    same sense, whichever of the two cores each pair is nearer (its own axis then points the
    other way); a lone pair about its bond and groups below ``min_pairs`` stay."""
    from emlpack.structure import Structure

    cores = np.array([[0.0, 0.0, 0.0], [1.2, 0.0, 0.0], [5.0, 0.0, 0.0], [6.1, 0.0, 0.0]])
    angles = np.deg2rad([10.0, 130.0, 250.0])
    ring = [[x, 0.5 * np.cos(a), 0.5 * np.sin(a)]
            for x, a in zip((0.55, 0.65, 0.58), angles, strict=True)]
    # one pair about the second bond, one on its axis (steps straight)
    pairs = np.array(ring + [[5.5, 0.0, 0.6], [6.5, 0.0, 0.1]])
    mol = Structure(np.array([6, 6, 1, 1]), cores, pairs)
    x = torch.as_tensor(pairs)
    turn = BondRotations([mol], x)
    arc = 0.05
    step = turn.collective(x, arc, 2)
    assert not torch.any(step[3:])
    new = turn(x, step).numpy()
    angle = arc / 0.5
    sense = np.sign(np.cross(pairs[0] - [pairs[0][0], 0, 0], new[0] - [pairs[0][0], 0, 0])[0])
    assert sense != 0 and np.linalg.norm(new[0] - pairs[0]) == pytest.approx(arc, rel=1e-3)
    for p, q in zip(pairs[:3], new[:3], strict=True):
        c, s = np.cos(sense * angle), np.sin(sense * angle)
        expect = [p[0], c * p[1] - s * p[2], s * p[1] + c * p[2]]
        assert np.allclose(q, expect, atol=1e-12)
    assert np.array_equal(new[3:], pairs[3:])
    assert not torch.any(turn.collective(x, arc, 4))


def test_rotation_probe_keeps_the_minima_and_saves_evaluations(trained):
    """Acetylene (the soft collective rotation of its triple-bond pairs): with the probe step
    (and with a lower floor after it) the same minima (energies within 1e-8 eV at fmax 1e-6)
    in fewer evaluations at the benchmark's fmax 1e-4 than without."""
    starts = _starts("300:400:15")
    assert all(sorted(s.numbers.tolist()) == [1, 1, 6, 6] for s in starts)
    probed = relax_pairs(trained, starts, fmax=1e-6, check_curvature=False)
    plain = relax_pairs(trained, starts, fmax=1e-6, check_curvature=False, rotation_probe=0)
    low = relax_pairs(trained, starts, fmax=1e-6, check_curvature=False, rotation_floor=3e-3)
    for a, b, c in zip(probed, plain, low, strict=True):
        assert not a.failed and not b.failed and not c.failed, (a.reason, b.reason, c.reason)
        assert a.energy == pytest.approx(b.energy, abs=1e-8)
        assert c.energy == pytest.approx(b.energy, abs=1e-8)
    probed = relax_pairs(trained, starts, check_curvature=False)
    plain = relax_pairs(trained, starts, check_curvature=False, rotation_probe=0)
    assert sum(r.n_evaluations for r in probed) < sum(r.n_evaluations for r in plain)


def test_bond_rotations_reach_the_straight_step_minima(trained):
    """Acetylene (the benchmark's slow soft rotation of the triple-bond pairs) and the other
    molecules: the same minima with and without bond-rotation steps, energies within 1e-8 eV
    at fmax 1e-6."""
    starts = _starts("::75")
    turned = relax_pairs(trained, starts, fmax=1e-6, check_curvature=False)
    straight = relax_pairs(trained, starts, fmax=1e-6, check_curvature=False,
                           bond_rotations=False)
    for a, b in zip(turned, straight, strict=True):
        assert not a.failed, a.reason
        assert a.max_force < 1e-6
        assert a.energy == pytest.approx(b.energy, abs=1e-8)


def test_exact_newton_finish_converges_what_the_quasi_newton_left(trained):
    """With ``newton_after=2`` unconverged structures switch to the exact-Hessian Newton method
    and reach the same minimum as the quasi-Newton alone."""
    starts = _starts("0:2")
    alone = relax_pairs(trained, starts, fmax=1e-7, newton_after=0, check_curvature=False)
    mixed = relax_pairs(trained, starts, fmax=1e-7, newton_after=2)
    for a, b in zip(alone, mixed, strict=True):
        assert a.converged and b.converged
        assert b.n_hessians >= 2  # at least one in the Newton finish, one for the curvature
        assert b.energy == pytest.approx(a.energy, abs=1e-8)
        assert b.min_curvature > 0


def test_unknown_method_is_refused(small):
    s = _starts("0:1")[0]
    with pytest.raises(ValueError, match="initial_hessian"):
        relax_pairs(small, s, initial_hessian="newton")


def test_overrides_do_not_change_the_callers_options():
    from emlpack.io import read_structures
    from emlpack.pairs.relax import RelaxOptions, relax_pairs
    from tests.conftest import shared_path
    from tests.legacy.test_reference_fixtures import load_model

    model = load_model("small")
    methane = read_structures(shared_path("data/eqm7_pbe0_subset.xyz"), index=63)[0]
    opts = RelaxOptions(fmax=1e-3)
    with pytest.raises(TypeError, match="unknown relaxation option"):
        relax_pairs(model, methane, opts, no_such_option=1)
    relax_pairs(model, methane, opts, fmax=1e-5, max_iterations=3)
    assert opts.fmax == 1e-3 and opts.max_iterations == 100


@contextmanager
def _frozen(model):
    """``model`` with every parameter frozen (held filters and tables need it), restored
    afterwards."""
    flags = [p.requires_grad for p in model.parameters()]
    for p in model.parameters():
        p.requires_grad_(False)
    try:
        yield model
    finally:
        for p, f in zip(model.parameters(), flags, strict=True):
            p.requires_grad_(f)


@pytest.mark.parametrize("which", ["small", "trained"])
def test_held_core_core_filters_equal_plain_evaluation(which, small, trained):
    """The relaxation's energy with the core-core SchNet filters computed once (cores fixed)
    equals the plain model energy, gradient and Hessian-vector product to 1e-12 relative in
    float64: molecules and a crystal (image shifts) in one batch."""
    model = small if which == "small" else trained
    mol = read_structures(shared_path("data/eqm7_pbe0_subset.xyz"), index="60:62")
    crystal = read_structures(shared_path("data/beta_glycine_pbe_wannier.xyz"), index="0:1")
    structures = mol + crystal if set(model.config.elements) >= {1, 6, 7, 8} else mol
    with _frozen(model):
        g = model.graph(structures, dtype=torch.float64)
        plain = PairProblem(model, g, hold_edges=False)
        held = PairProblem(model, g)
        assert plain.held is None and held.held is not None
        assert 0 < len(held.held.i) < len(g.edge_i)
        x = g.positions[plain.pair_idx].clone()
        x = x + 0.05 * torch.sin(torch.arange(x.numel(), dtype=x.dtype)).reshape(x.shape)
        e0, g0 = plain.energy_gradient(x)
        e1, g1 = held.energy_gradient(x)
        assert torch.abs(e1 - e0).max() <= 1e-12 * torch.abs(e0).max()
        assert torch.abs(g1 - g0).max() <= 1e-12 * torch.abs(g0).max()
        v = torch.cos(torch.arange(x.numel(), dtype=x.dtype)).reshape(x.shape)
        h0, h1 = plain.hvp(x, v), held.hvp(x, v)
        assert torch.abs(h1 - h0).max() <= 1e-12 * torch.abs(h0).max()


def test_tabulated_filters_reach_the_network_minima(trained, monkeypatch):
    """Energies and gradients with the pair edges' filters from the table equal the filter
    network's to 1e-10 and 1e-7 relative (a molecule batch and a crystal); relaxations with
    and without the table end at the same minima (energies within 1e-6 eV, converged); small
    batches keep the network."""
    mol = read_structures(shared_path("data/eqm7_pbe0_subset.xyz"), index="60:62")
    crystal = read_structures(shared_path("data/beta_glycine_pbe_wannier.xyz"), index="0:1")
    with _frozen(trained):
        g_small = trained.graph(mol[:1], dtype=torch.float64)
        assert PairProblem(trained, g_small, filter_table=1e-3).held_tabulated.table is None
        monkeypatch.setattr(problem_module, "TABLE_MIN_EDGES", 0)
        g = trained.graph(mol + crystal, dtype=torch.float64)
        network, table = PairProblem(trained, g), PairProblem(trained, g, filter_table=1e-3)
        assert table.held_tabulated.table is not None and table.held.table is None
        x = g.positions[network.pair_idx].clone()
        x = x + 0.05 * torch.sin(torch.arange(x.numel(), dtype=x.dtype)).reshape(x.shape)
        e0, g0 = network.energy_gradient(x)
        e1, g1 = table.energy_gradient(x)
        assert torch.abs(e1 - e0).max() <= 1e-10 * torch.abs(e0).max()
        assert torch.abs(g1 - g0).max() <= 1e-7 * torch.abs(g0).max()
        v = torch.cos(torch.arange(x.numel(), dtype=x.dtype)).reshape(x.shape)
        assert torch.equal(table.hvp(x, v), network.hvp(x, v))  # products keep the network
    starts = _starts("::75")
    off = relax_pairs(trained, starts, fmax=1e-6, check_curvature=False, filter_table=0)
    on = relax_pairs(trained, starts, fmax=1e-6, check_curvature=False, filter_table=1e-3)
    for a, b in zip(on, off, strict=True):
        assert not a.failed, a.reason
        assert a.max_force < 1e-6
        assert a.energy == pytest.approx(b.energy, abs=1e-6)


def test_collapsed_pairs_stop_early(small):
    """With the random fixture weights two pairs of these starts fall onto one point (closer
    than 1e-3 Å, where their distance has no direction): the relaxation stops there instead of
    spending its iteration budget (and the exact-Hessian retry's) on them, with the same
    merged-pair failure."""
    starts = _starts("::75")[2:5:2]
    stopped = relax_pairs(small, starts, check_curvature=False)
    ran_on = relax_pairs(small, starts, check_curvature=False, collapse_distance=0.0)
    for a, b in zip(stopped, ran_on, strict=True):
        assert a.failed and b.failed
        assert "(merged;" in a.reason and "(merged;" in b.reason, (a.reason, b.reason)
        assert a.iterations < 0.5 * b.iterations, (a.iterations, b.iterations)


def test_closest_pair_distance_uses_the_minimum_image():
    """Two pairs 0.2 Å apart across the face of a cubic 5 Å cell (4.8 Å within it), and a
    molecule's two pairs 0.3 Å apart; a structure with one pair has no pair distance (inf)."""
    four_h = np.array([[1.0, 1.0, 1.0], [2.0, 1.0, 1.0], [1.0, 3.0, 1.0], [2.0, 3.0, 1.0]])
    crystal = Structure(np.ones(4), four_h, np.array([[0.1, 2.0, 2.0], [4.9, 2.0, 2.0]]),
                        cell=5.0 * np.eye(3), pbc=True)
    molecule = Structure(np.ones(4), four_h, np.array([[1.2, 2.0, 1.0], [1.5, 2.0, 1.0]]))
    single = Structure(np.array([1, 1]), np.array([[0.0, 0.0, 0.0], [0.74, 0.0, 0.0]]),
                       np.array([[0.37, 0.0, 0.0]]))
    model = load_model("small")
    g = model.graph([crystal, molecule, single], dtype=torch.float64)
    prob = PairProblem(model, g, hold_edges=False)
    d = prob.closest_pair_distance(g.positions[prob.pair_idx])
    np.testing.assert_allclose(d[:2].numpy(), [0.2, 0.3], atol=1e-12)
    assert torch.isinf(d[2])


def test_curvature_check_equals_the_exact_pair_hessian(trained):
    """The smallest pair-Hessian eigenvalue at the result (Davidson on Hessian-vector products
    of the structures not yet converged, float32 products after the float32 phase of a batch
    of more than 128 pairs) equals the exact pair Hessian's, per structure."""
    starts = _starts("::25")  # 24 configurations, ~190 pairs: a float32 phase
    assert sum(s.n_pairs for s in starts) >= 128
    results = relax_pairs(trained, starts)
    for s, r in zip(starts, results, strict=True):
        assert not r.failed, r.reason
        exact = np.linalg.eigvalsh(pair_hessian(trained, s.copy(pairs=r.pairs)))[0]
        assert r.min_curvature == pytest.approx(exact, abs=1e-4, rel=1e-3)


def test_kept_graph_products_equal_fresh_ones_and_the_davidson_start_block(trained):
    """Products from one kept gradient graph (single and stacked) equal fresh Hessian-vector
    products, and Davidson with its start block in one stacked call gives the eigenvalues of
    the one-by-one start; one structure alone (the calculator's case) matches the exact pair
    Hessian."""
    from emlpack.pairs.relax import davidson_min_curvature

    starts = _starts("::100")
    results = relax_pairs(trained, starts)
    g = trained.graph([s.copy(pairs=r.pairs) for s, r in zip(starts, results, strict=True)],
                      dtype=torch.float64)
    prob = PairProblem(trained, g)
    x = g.positions[prob.pair_idx].clone()
    v = torch.randn(3, *x.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    product = prob.hvp_operator(x)
    fresh = torch.stack([prob.hvp(x, one) for one in v])
    torch.testing.assert_close(product(v), fresh, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(product(v[1]), fresh[1], rtol=1e-12, atol=1e-12)

    m = 3 * prob.n_max
    mask = torch.arange(m)[None, :] < 3 * g.n_pairs[:, None]
    model_h = prob.hessians(x) + 0.1 * torch.eye(m)  # a (nearly exact) preconditioner

    def padded(q: torch.Tensor) -> torch.Tensor:
        if q.dim() == 2:
            return prob.pad(product(prob.unpad(q)))
        return torch.stack([prob.pad(one) for one in product(
            torch.stack([prob.unpad(one) for one in q]))])

    one_by_one = davidson_min_curvature(padded, mask, model_h, m)
    stacked = davidson_min_curvature(padded, mask, model_h, m, batched_start=True)
    torch.testing.assert_close(stacked, one_by_one, rtol=1e-10, atol=1e-10)

    (alone,) = relax_pairs(trained, [starts[0]])
    exact = np.linalg.eigvalsh(pair_hessian(trained, starts[0].copy(pairs=alone.pairs)))[0]
    assert alone.min_curvature == pytest.approx(exact, abs=1e-4, rel=1e-3)


def test_fast_pair_hessians_equal_the_reverse_passes(small):
    """The closed-form SchNet pair blocks plus the analytic electrostatics equal one reverse
    pass per column, for molecules of different pair counts (padding) and a crystal (image
    shifts, reciprocal Ewald) in one batch, with pairs off their minimum."""
    mol = read_structures(shared_path("data/eqm7_pbe0_subset.xyz"), index="0:600:300")
    crystal = read_structures(shared_path("data/beta_glycine_pbe_wannier.xyz"), index="0:1")
    g = small.graph(mol + crystal, dtype=torch.float64)
    prob = PairProblem(small, g)
    assert len(set(g.n_pairs.tolist())) == 3
    x = g.positions[prob.pair_idx].clone()
    x = x + 0.05 * torch.sin(torch.arange(x.numel(), dtype=x.dtype)).reshape(x.shape)
    fast, reverse = prob.hessians(x), prob.hessians(x, method="reverse")
    scale = float(reverse.abs().max())
    torch.testing.assert_close(fast, reverse, rtol=0, atol=1e-11 * scale)
    with pytest.raises(ValueError, match="method"):
        prob.hessians(x, method="forward")


def test_exact_pair_hessians_equal_autograd(trained):
    """The padded pair-block Hessians of a batch (one reverse pass per column) equal
    torch.autograd's full Hessian of the summed energy, block by block."""
    starts = _starts("::150")
    g = trained.graph(starts, dtype=torch.float64)
    prob = PairProblem(trained, g)
    x = g.positions[prob.pair_idx].clone()
    h = prob.hessians(x)
    full = torch.autograd.functional.hessian(lambda y: prob.energy(y).sum(), x)
    full = full.reshape(x.numel(), x.numel())
    scale = float(full.abs().max())
    for b in range(g.n_structures):
        rows = torch.nonzero(prob.pair_batch == b).squeeze(1)
        idx = (3 * rows[:, None] + torch.arange(3)).reshape(-1)
        n = len(idx)
        block = full[idx][:, idx]
        torch.testing.assert_close(h[b, :n, :n], 0.5 * (block + block.T), rtol=0,
                                   atol=1e-12 * scale)
        assert torch.equal(h[b, n:, n:], torch.eye(3 * prob.n_max - n, dtype=h.dtype))

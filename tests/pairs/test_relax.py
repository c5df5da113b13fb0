"""Electron-pair relaxation: stationarity, box bounds, batching, failure diagnostics."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from emlpack.io import read_structures
from emlpack.pairs.relax import relax_pairs
from tests.conftest import shared_path
from tests.legacy.test_reference_fixtures import load_model
from tests.nn.helpers import FAMILIES


@pytest.fixture(scope="module")
def model():
    return load_model("small")


@pytest.fixture(scope="module")
def methanes():
    return read_structures(shared_path("data/eqm7_pbe0_subset.xyz"), index="60:64")


def test_batched_equals_one_by_one(model, methanes):
    batch = relax_pairs(model, methanes, fmax=1e-6)
    for s, rb in zip(methanes, batch, strict=True):
        r1 = relax_pairs(model, s, fmax=1e-6)[0]
        assert rb.converged and r1.converged
        assert rb.max_force < 1e-6
        assert rb.energy == pytest.approx(r1.energy, abs=1e-9)
        np.testing.assert_allclose(rb.pairs, r1.pairs, atol=1e-5)
        assert rb.min_curvature > 0


def test_relaxed_pairs_are_stationary_and_lower(model, methanes):
    s = methanes[0]
    r = relax_pairs(model, s, fmax=1e-6)[0]
    out = model.evaluate(s.copy(pairs=r.pairs))
    assert np.linalg.norm(out["pair_forces"], axis=1).max() < 1e-6
    assert out["energy"] == pytest.approx(r.energy, abs=1e-10)
    assert r.energy < model.evaluate(s)["energy"]


def test_box_bounds_are_respected(model, methanes):
    """With each coordinate boxed to +-0.02 Å around the start, no pair leaves its box and
    the result is a constrained minimum (projected gradient zero)."""
    s = methanes[1]
    free = relax_pairs(model, s, fmax=1e-6)[0]
    assert np.abs(free.pairs - s.pairs).max() > 0.05  # the box really constrains
    lo, hi = s.pairs - 0.02, s.pairs + 0.02
    r = relax_pairs(model, s, fmax=1e-6, bounds=[(lo, hi)])[0]
    assert np.all(r.pairs >= lo - 1e-12) and np.all(r.pairs <= hi + 1e-12)
    assert r.converged
    g = -r.pair_forces
    at_lo, at_hi = r.pairs <= lo + 1e-9, r.pairs >= hi - 1e-9
    assert np.any(at_lo | at_hi)
    free_grad = np.where((at_lo & (g > 0)) | (at_hi & (g < 0)), 0.0, g)
    assert np.abs(free_grad).max() < 1e-5
    assert r.energy > free.energy


def test_merged_pairs_are_reported(model, methanes):
    """A merge is forced: pairs 0 and 1 start 1e-3 Å apart and are boxed to +-0.02 Å around
    the same point, so they end at most 0.07 Å apart (< min_pair_distance 0.1 Å)."""
    s = methanes[2]
    pairs = s.pairs.copy()
    pairs[1] = pairs[0] + 1e-3
    lo, hi = pairs - 5.0, pairs + 5.0
    lo[:2], hi[:2] = pairs[0] - 0.02, pairs[0] + 0.02
    r = relax_pairs(model, s.copy(pairs=pairs), bounds=[(lo, hi)])[0]
    assert np.linalg.norm(r.pairs[0] - r.pairs[1]) < 0.07
    assert r.failed  # whether or not the boxed relaxation converged
    assert "pairs 0 and 1 are" in r.reason and "(merged;" in r.reason, r.reason


def test_escaped_pair_is_reported(model, methanes):
    s = methanes[3]
    pairs = s.pairs.copy()
    pairs[0] += 6.0
    r = relax_pairs(model, s.copy(pairs=pairs), max_iterations=1)[0]
    assert "from the nearest core" in r.reason and r.failed


def test_relaxed_pairs_are_stationary_with_a_graph_built_at_the_result(monkeypatch):
    """The relaxation builds its SchNet neighbour list at the start pairs. Two methanes 4 Å
    apart, with one pair pushed just beyond the 4 Å cutoff of a particle of the other
    molecule: relaxed back inside, that edge was missing, and on the model evaluated afresh
    the 'converged' pairs felt 0.2 eV/Å. A result whose neighbour list changed is relaxed
    again from there: stationary (< fmax) on a fresh evaluation, with its energy."""
    import emlpack.pairs.relax as relax_module
    from emlpack.nn.checkpoint import load_model as load_checkpoint
    from emlpack.structure import Structure
    from tests.pairs.test_relax_quasi_newton import TRAINED

    model = load_checkpoint(TRAINED)
    model.eval()
    m = read_structures(shared_path("data/eqm7_pbe0_subset.xyz"), index=0)[0]
    m = m.copy(pairs=relax_pairs(model, m, fmax=1e-6)[0].pairs)
    shift = np.array([4.0, 0.0, 0.0])
    dimer = Structure(np.r_[m.numbers, m.numbers], np.r_[m.positions, m.positions + shift],
                      np.r_[m.pairs, m.pairs + shift])
    dimer = dimer.copy(pairs=relax_pairs(model, dimer, fmax=1e-6)[0].pairs)
    pos, nc = dimer.all_positions, dimer.n_cores
    others = list(range(m.n_cores, nc)) + list(range(nc + m.n_pairs, len(pos)))
    d = np.linalg.norm(pos[nc:nc + m.n_pairs, None] - pos[None, others], axis=-1)
    p, o = np.argwhere((d > 3.7) & (d < 3.95))[0]  # a pair of A inside the cutoff of B
    u = (pos[nc + p] - pos[others[o]]) / d[p, o]
    start = dimer.copy(pairs=dimer.pairs + np.eye(dimer.n_pairs)[p][:, None]
                       * (4.07 - d[p, o]) * u)

    def fresh_max_force(r):
        out = model.evaluate(start.copy(pairs=r.pairs))
        return np.linalg.norm(out["pair_forces"], axis=1).max(), out["energy"]

    # without a rebuild: converged on the start's neighbour list, not on the model, and so
    # reported as failed
    monkeypatch.setattr(relax_module, "_MAX_GRAPH_REBUILDS", 0)
    stale = relax_pairs(model, start, fmax=1e-6)[0]
    assert stale.max_force < 1e-6 and fresh_max_force(stale)[0] > 1e-2
    assert stale.failed and "rebuilds of the neighbour list" in stale.reason
    monkeypatch.undo()
    r = relax_pairs(model, start, fmax=1e-6)[0]
    force, energy = fresh_max_force(r)
    assert not r.failed and force < 1e-6
    assert r.energy == pytest.approx(energy, abs=1e-9)


def test_missing_edges_are_found_in_molecules_and_through_the_cell_boundary(model):
    """A pair moved from 4.05 to 3.95 Å of a core gains an edge (molecule: direct distance;
    crystal: to the core's image across the face of a 10 Å cell); moved the other way, none
    is missing (an edge beyond the cutoff contributes zero)."""
    from emlpack.pairs.relax import _missing_edges
    from emlpack.structure import Structure

    assert model.config.cutoff == 4.0
    cores = np.array([[0.5, 5.0, 5.0], [1.24, 5.0, 5.0], [9.0, 9.0, 9.0], [9.74, 9.0, 9.0]])
    # x of the moving pair 3.95 Å / 4.05 Å from the core at x = 1.24 (molecule) or from the
    # image of the core at x = 0.5 beyond the face x = 10 (crystal); every other distance > 4.3
    for pbc, x_in, x_out in ((False, 5.19, 5.29), (True, 6.55, 6.45)):
        cell = 10.0 * np.eye(3) if pbc else np.zeros((3, 3))
        start = Structure(np.ones(4), cores, np.array([[0.87, 5.0, 5.0], [x_out, 5.0, 5.0]]),
                          cell=cell, pbc=pbc)
        inside = start.pairs.copy()
        inside[1, 0] = x_in
        assert _missing_edges(model, start, inside), pbc
        assert not _missing_edges(model, start.copy(pairs=inside), start.pairs), pbc


# ---------------------------------------------------------------------- every family
@pytest.mark.parametrize("family", FAMILIES)
def test_every_family_relaxes_to_a_stationary_minimum(family):
    """A random model of every short-range family (the generic paths for a family without
    SchNet's held filters, table and closed-form Hessian): a batch of water and methane
    relaxes to stationary pairs (the model's own forces), the same minima as one by one, with
    the smallest exact pair curvature positive; the exact-Newton method reaches them too."""
    from tests.nn.helpers import methane, random_model, water_molecule

    model = random_model(family=family)
    starts = [water_molecule(), methane()]
    batch = relax_pairs(model, starts, fmax=1e-7)
    exact = relax_pairs(model, starts, fmax=1e-7, initial_hessian="exact")
    for s, rb, re in zip(starts, batch, exact, strict=True):
        assert rb.converged and re.converged, (rb.reason, re.reason)
        out = model.evaluate(s.copy(pairs=rb.pairs))
        assert np.linalg.norm(out["pair_forces"], axis=1).max() < 1e-7
        assert out["energy"] == pytest.approx(rb.energy, abs=1e-10)
        assert rb.energy < model.evaluate(s)["energy"] - 1e-3
        assert rb.min_curvature > 0
        one = relax_pairs(model, s, fmax=1e-7)[0]
        for other in (re, one):  # the same minimum (the pairs possibly in another order)
            assert other.energy == pytest.approx(rb.energy, abs=1e-10)
            d = np.linalg.norm(other.pairs[:, None] - rb.pairs[None], axis=-1)
            assert d.min(1).max() < 1e-5 and d.min(0).max() < 1e-5


@pytest.mark.parametrize("family", FAMILIES)
def test_fast_pair_hessians_equal_the_reverse_passes_for_every_family(family):
    """``pair_hessian`` fast (the family's short-range block: SchNet's closed form, others by
    reverse over reverse on the short range, plus the analytic electrostatics) equals one
    reverse pass of the whole energy per column, off the minimum, molecule and crystal."""
    import torch

    from emlpack.pairs.relax.problem import PairProblem
    from tests.nn.helpers import random_model, water_crystal, water_molecule

    model = random_model(family=family)
    for p in model.parameters():
        p.requires_grad_(False)
    g = model.graph([water_molecule(), water_crystal()], dtype=torch.float64)
    prob = PairProblem(model, g)
    assert (prob.held is not None) == (family == "schnet")
    x = g.positions[prob.pair_idx].clone()
    x = x + 0.05 * torch.sin(torch.arange(x.numel(), dtype=x.dtype)).reshape(x.shape)
    fast, reverse = prob.hessians(x), prob.hessians(x, method="reverse")
    scale = float(reverse.abs().max())
    torch.testing.assert_close(fast, reverse, rtol=0, atol=1e-11 * scale)


@pytest.mark.parametrize("family", FAMILIES)
def test_the_float32_phase_reaches_the_float64_minima_for_every_family(family):
    """A batch of 128 pairs (32 waters) takes the float32 start (a family without the
    capability ``FrozenAnyDtype`` on a float32 copy of the model): the same minima as float64
    throughout."""
    from tests.nn.helpers import random_model, water_molecule

    model = random_model(family=family)
    starts = [water_molecule()] * 32
    assert sum(s.n_pairs for s in starts) >= 128
    mixed = relax_pairs(model, starts, fmax=1e-7, check_curvature=False)
    plain = relax_pairs(model, starts, fmax=1e-7, check_curvature=False, float32_above=0)
    for a, b in zip(mixed, plain, strict=True):
        assert a.converged and b.converged, (a.reason, b.reason)
        assert a.energy == pytest.approx(b.energy, abs=1e-9)
        np.testing.assert_allclose(a.pairs, b.pairs, atol=1e-5)
    assert next(model.parameters()).dtype == torch.float64  # the caller's model unchanged

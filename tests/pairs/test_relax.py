"""Electron-pair relaxation: stationarity, box bounds, batching, failure diagnostics."""

from __future__ import annotations

import numpy as np
import pytest

from emlpack.io import read_structures
from emlpack.pairs.relax import relax_pairs
from tests.conftest import shared_path
from tests.legacy.test_reference_fixtures import load_model


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

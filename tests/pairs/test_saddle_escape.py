"""A pair relaxation that converges to a saddle goes on along the saddle's softest mode."""

from __future__ import annotations

import numpy as np
import pytest

from emlpack.nn import EMLP, ModelConfig
from emlpack.nn.scatter import segment_sum
from emlpack.pairs.relax import relax_pairs
from emlpack.structure import Structure
from tests.nn.helpers import SMALL

A, W, B = 1.0, 0.5, 1.0  # eV/Å^4, Å, eV/Å^2


class DoubleWell(EMLP):
    """Each pair in a double well along y, ``A (y^2 - W^2)^2 + B (x^2 + z^2)`` (eV; Å), and
    nothing else: a ridge at y = 0 (curvature -4 A W^2) between two wells at y = +-W."""

    def energy_parts(self, g, positions=None, cell=None, field=None, held=None,
                     long_range=True):
        pos = g.positions if positions is None else positions
        p = pos[g.is_pair]
        e = A * (p[:, 1] ** 2 - W**2) ** 2 + B * (p[:, 0] ** 2 + p[:, 2] ** 2)
        return {"energy": segment_sum(e, g.batch[g.is_pair], g.n_structures)}


@pytest.fixture(scope="module")
def well():
    return DoubleWell(ModelConfig(short_range=SMALL)).double()


def _on_the_ridge(*pairs) -> Structure:
    return Structure([1, 1], np.array([[-0.37, 0.0, 0.0], [0.37, 0.0, 0.0]]),
                     np.array(pairs, float))


@pytest.mark.parametrize("method", ["coulomb", "exact"])
def test_a_saddle_is_left_along_its_softest_mode(well, method):
    """Started at the saddle (zero gradient: converged at once), the relaxation fails there
    without escapes; with them, it ends in one of the wells. (One pair, 3 coordinates: fewer
    than Davidson's 4 start directions, which once left its curvature at 0.)"""
    start = _on_the_ridge([0.0, 0.0, 0.0])
    stuck = relax_pairs(well, start, initial_hessian=method, saddle_escapes=0)[0]
    assert stuck.failed and "saddle" in stuck.reason
    assert stuck.min_curvature == pytest.approx(-4 * A * W**2, rel=1e-3)
    r = relax_pairs(well, start, initial_hessian=method)[0]
    assert not r.failed, r.reason
    assert abs(r.pairs[0, 1]) == pytest.approx(W, abs=1e-4)
    assert r.energy == pytest.approx(0.0, abs=1e-7) and r.energy < stuck.energy
    assert r.min_curvature == pytest.approx(min(8 * A * W**2, 2 * B), rel=1e-3)
    assert r.n_hessians > stuck.n_hessians  # the escape's exact Hessian is counted


def test_escapes_need_the_curvature_check_and_leave_minima_alone(well):
    """Without the curvature check nothing is known of the saddle (a converged result, as
    before); a start in a well is relaxed as without escapes."""
    ridge = relax_pairs(well, _on_the_ridge([0.0, 0.0, 0.0]), check_curvature=False)[0]
    assert not ridge.failed and np.all(ridge.pairs == 0.0)
    in_well = _on_the_ridge([0.1, 0.3, 0.0])
    a = relax_pairs(well, in_well)[0]
    b = relax_pairs(well, in_well, saddle_escapes=0)[0]
    assert not a.failed and a.pairs[0, 1] == pytest.approx(W, abs=1e-4)
    np.testing.assert_array_equal(a.pairs, b.pairs)
    assert a.n_evaluations == b.n_evaluations

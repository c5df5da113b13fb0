"""Born-Oppenheimer relaxation of the electron pairs at fixed cores (batched, float64).

Minimises the eMLP energy over the electron-pair positions of many structures at once.

Default method (``initial_hessian="coulomb"``): a quasi-Newton on the per-structure pair block
(3P x 3P for P pairs) whose model is ``H_el(x) + M``:

1. ``H_el(x)``: the exact analytic electrostatic pair Hessian at the current pairs (Gaussian
   Coulomb for molecules, reciprocal Ewald at fixed cell for crystals;
   :func:`emlpack.nn.electrostatics.coulomb_pair_derivatives`,
   :func:`~emlpack.nn.electrostatics.ewald_reciprocal_derivatives`), recomputed every step;
2. ``M``: the short-range remainder, started block-diagonal from three batched forward
   differences of the gradient ("lumped": per pair the row sum of its short-range couplings)
   and refined by symmetric-rank-one updates from ``y - y_el`` (change of gradient minus change
   of the electrostatic gradient) after every evaluated step;
3. step ``(H_el + M + mu I) p = -g`` with ``mu`` lifting the smallest eigenvalue to 1e-2 eV/Å^2
   (model curvatures below ``-mirror_curvature`` are taken by their magnitude instead and
   left out of ``mu``), in a trust radius (largest pair displacement, at most ``max_step``)
   that is halved to a rejected step and doubled after an accepted one (Armijo test);
4. structures not converged after ``newton_after`` iterations (nearly flat modes) finish with
   the exact-Hessian Newton method below;
5. (``bond_rotations``, molecules) the step is taken in cylindrical coordinates about the axis
   through each pair's two nearest cores (:class:`BondRotations`): its tangential part turns
   the pair about that bond instead of moving it along the tangent (acetylene's triple-bond
   pairs have a soft rotation about the C-C axis that straight steps zig-zag along);
6. (with 5) the model lives in those coordinates: per turned pair radial, arc length and axial
   (``M`` is Cartesian; the step model adds the connection term of the gradient, ``-g_r/rho``
   tangential and ``g_t/rho`` radial-tangential, :meth:`BondRotations.connection`); the SR1
   secant is the turned step with the new gradient turned back less that term of the
   short-range gradient, and ``M`` turns with the accepted pairs;
7. (with 5) once per structure, near its minimum, a step along the collective rotation of the
   pairs about each double or triple bond (``rotation_probe``): the lumped start sees those
   pairs turning one at a time, stiff, while together they turn almost freely; its secant
   gives ``M`` that curvature.

Every evaluation holds the core-core edges fixed when the short-range family can (their
vectors do not change at fixed cores and cell; capability
:class:`~emlpack.nn.short_range.protocol.HoldsEdges`, SchNet's filters;
:meth:`emlpack.nn.potential.EMLP.hold_edges`). A model with EMLP's own energy
(:func:`~emlpack.properties.hessian.standard_energy`) is evaluated without its
electrostatics, whose energy and gradient come from the analytic pair terms computed for
``H_el`` anyway. Float32 phase (``float32_above``, batches of
at least ``float32_min_pairs`` pairs): while a structure's largest pair force is above it, its
evaluations are float32 (Armijo test with a 1e-6 |E| allowance, steps below that resolution
accepted on a lower pair-gradient norm), then float64, so the minima are float64 minima.

``initial_hessian="exact"``: Newton with exact pair Hessians (short-range blocks,
:func:`~emlpack.nn.short_range.hessian.short_range_position_hessian`, plus the analytic
electrostatics, :meth:`PairProblem.hessians`),
refreshed when the line search backtracks or every ``hessian_every`` steps, damped BFGS updates
in between. ``"bfgs"``: damped BFGS from a scaled identity.

Convergence: the largest pair-force norm (projected on the box) below ``fmax`` (eV/Å); a
structure whose pairs collapse onto one point (``collapse_distance``) stops. The graph (the
short-range neighbour list) is built at the start pairs; a structure whose neighbour list at the
result holds an edge the start lacked is relaxed again from its result on a graph built there.
Diagnostics per structure: converged flag, iterations, energy+gradient evaluations, Hessian
evaluations, final max force, smallest eigenvalue of the exact pair Hessian at the result
(default method: Davidson iterations on Hessian-vector products of the structures not yet
converged, preconditioned by the quasi-Newton model, instead of the full Hessian), and a
failure reason from :func:`emlpack.pairs.checks.check_pairs` (no convergence, two pairs closer
than ``min_pair_distance``, a pair farther than ``max_core_distance`` from every core, minimum
image; a curvature at or below ``-flat_curvature``). :mod:`emlpack.pairs.solvers` wraps this
function as :class:`~emlpack.pairs.solvers.BatchedSolver`.

Why each piece is there, with the measurements and what was tried and dropped:
``docs/relaxation.md``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from emlpack.nn.potential import EMLP
from emlpack.pairs.checks import check_pairs
from emlpack.pairs.relax.curvature import davidson_min_curvature
from emlpack.pairs.relax.newton import damped_bfgs, relax_newton
from emlpack.pairs.relax.options import RelaxOptions, RelaxResult
from emlpack.pairs.relax.problem import TABLE_MIN_EDGES, pair_hessian
from emlpack.pairs.relax.quasi_newton import relax_coulomb
from emlpack.structure import Structure

if TYPE_CHECKING:
    from emlpack.pairs.relax.options import Bounds

__all__ = [
    "RelaxOptions",
    "RelaxResult",
    "TABLE_MIN_EDGES",
    "damped_bfgs",
    "davidson_min_curvature",
    "pair_hessian",
    "relax_pairs",
]


def relax_pairs(
    model: EMLP,
    structures: Structure | Sequence[Structure],
    options: RelaxOptions | None = None,
    bounds: Sequence[tuple[np.ndarray, np.ndarray] | None] | None = None,
    **overrides,
) -> list[RelaxResult]:
    """Relax the electron pairs of ``structures`` at fixed cores; one result per structure.

    Args:
        model: the eMLP (evaluated in float64).
        structures: starting structures (their ``pairs`` are the initial guess).
        options: :class:`RelaxOptions`; keyword ``overrides`` replace single fields.
        bounds: per structure ``None`` or ``(lower, upper)`` arrays of shape (P, 3) (Å) that box
            every pair coordinate (the paper's MD uses +-3x the largest core displacement).
    """
    if isinstance(structures, Structure):
        structures = [structures]
    opts = options or RelaxOptions()
    for k in overrides:
        if not hasattr(opts, k):
            raise TypeError(f"unknown relaxation option {k!r}")
    opts = replace(opts, **overrides)  # the caller's options are never changed
    if opts.short_range_start not in ("lumped", "zero"):
        raise ValueError(
            f"short_range_start must be 'lumped' or 'zero', not {opts.short_range_start!r}"
        )
    if opts.initial_hessian not in ("coulomb", "exact", "bfgs"):
        raise ValueError(
            f"initial_hessian must be 'coulomb', 'exact' or 'bfgs', not {opts.initial_hessian!r}"
        )
    structures = list(structures)
    # frozen parameters: no parameter gradients are needed, and a family may then use a
    # cheaper frozen-weight evaluation (SchNet's: emlpack.nn.short_range.schnet)
    grad_flags = [(p, p.requires_grad) for p in model.parameters()]
    for p, _ in grad_flags:
        p.requires_grad_(False)
    try:
        results = _relax_once(model, structures, opts, bounds)
        # the graph (short-range neighbour list) is built at the start pairs and kept: a structure
        # whose result has an edge within the cutoff that the start lacked is relaxed again
        # from its result with a graph built there (until the neighbour list holds)
        starts = list(structures)
        for rebuild in range(_MAX_GRAPH_REBUILDS + 1):
            stale = [k for k, r in enumerate(results)
                     if not r.failed and _missing_edges(model, starts[k], r.pairs)]
            if not stale:
                break
            if rebuild == _MAX_GRAPH_REBUILDS:  # still moving into the cutoff: not trusted
                for k in stale:
                    results[k].converged = False
                    results[k].reason = (f"the pairs still moved into the cutoff after"
                                         f" {rebuild} rebuilds of the neighbour list")
                break
            for k in stale:
                starts[k] = starts[k].copy(pairs=results[k].pairs)
            sub_bounds = None if bounds is None else [bounds[k] for k in stale]
            again = _relax_once(model, [starts[k] for k in stale], opts, sub_bounds)
            for k, r in zip(stale, again, strict=True):
                results[k] = _after(results[k], r)
        return results
    finally:
        for p, flag in grad_flags:
            p.requires_grad_(flag)


#: relaxations again from the result with a graph built there, at most (each one usually
#: takes one to three iterations; docs/relaxation.md)
_MAX_GRAPH_REBUILDS = 3


def _missing_edges(model: EMLP, start: Structure, pairs: np.ndarray) -> bool:
    """Whether particles within the short-range cutoff with the pairs at ``pairs`` [P, 3] (Å) were
    farther apart in ``start``, whose neighbour list the relaxation used (only edges of a pair
    can change at fixed cores; edges that left the cutoff contribute exactly zero)."""
    if start.n_pairs == 0 or np.array_equal(pairs, start.pairs):
        return False
    cutoff = model.config.cutoff
    if start.pbc:
        end = start.copy(pairs=pairs)
        from emlpack.nn.neighbors import half_neighbor_list

        def edges(s: Structure) -> set:
            # each unordered edge once, whichever way round the half list gives it
            i, j, shifts = half_neighbor_list(s.all_positions, s.cell, True, cutoff)
            return {min((int(a), int(b), *map(int, c)), (int(b), int(a), *map(int, -c)))
                    for a, b, c in zip(i, j, shifts, strict=True)}

        return not edges(end) <= edges(start)
    p0 = start.all_positions
    p1 = np.concatenate([start.positions, pairs], axis=0)
    d0 = np.linalg.norm(start.pairs[:, None] - p0[None], axis=-1)  # [P, n_particles]
    d1 = np.linalg.norm(pairs[:, None] - p1[None], axis=-1)
    return bool(np.any((d1 < cutoff) & (d0 >= cutoff)))


def _relax_once(model: EMLP, structures: Sequence[Structure], opts: RelaxOptions,
                bounds: Bounds) -> list[RelaxResult]:
    """One relaxation of ``structures`` on graphs built at their start pairs."""
    if opts.initial_hessian != "coulomb":
        return _escape_saddles(model, structures, relax_newton(model, structures, opts, bounds),
                               opts, bounds)
    results = relax_coulomb(model, structures, opts, bounds)
    # a failed quasi-Newton relaxation (e.g. slid into a merged pair, off to a neighbouring
    # basin of a poorly trained model) is tried again with the exact-Hessian Newton method
    # from the same start, so the default fails no more often than the exact method; a
    # converged saddle goes on to the escape along its softest mode instead (the exact
    # Newton method returns to the saddle, or worse)
    retry = [k for k, r in enumerate(results) if r.failed and not (
        opts.saddle_escapes > 0 and opts.check_curvature and _at_saddle(structures[k], r, opts))]
    if retry:
        sub_bounds = None if bounds is None else [bounds[k] for k in retry]
        again = relax_newton(model, [structures[k] for k in retry],
                             replace(opts, initial_hessian="exact"), sub_bounds)
        for k, r in zip(retry, again, strict=True):
            if r.failed:
                r.reason = f"{results[k].reason} (exact-Hessian retry: {r.reason})"
            results[k] = _after(results[k], r)
    return _escape_saddles(model, structures, results, opts, bounds)


def _at_saddle(structure: Structure, result: RelaxResult, opts: RelaxOptions) -> bool:
    """Whether ``result`` failed only by a negative pair curvature (a converged saddle)."""
    return bool(
        result.failed and result.max_force < opts.fmax
        and np.isfinite(result.min_curvature) and result.min_curvature <= -opts.flat_curvature
        and not check_pairs(result.pairs, structure.positions, structure.cell, structure.pbc,
                            min_pair_distance=opts.min_pair_distance,
                            max_core_distance=opts.max_core_distance)
    )


def _escape_saddles(model: EMLP, structures: Sequence[Structure], results: list[RelaxResult],
                    opts: RelaxOptions, bounds: Bounds) -> list[RelaxResult]:
    """``results`` with every converged saddle (:func:`_at_saddle`) relaxed again from its
    pairs displaced by ``opts.saddle_step`` along the softest mode of the exact pair Hessian,
    both ways (at most ``opts.saddle_escapes`` rounds): the lowest successful result replaces
    it, counts added up (one exact Hessian per escape)."""
    if opts.saddle_escapes <= 0 or not opts.check_curvature:
        return results
    inner = replace(opts, saddle_escapes=0)
    for _ in range(opts.saddle_escapes):
        stuck = [k for k, r in enumerate(results) if _at_saddle(structures[k], r, opts)]
        if not stuck:
            break
        starts, owners = [], []
        for k in stuck:
            at = structures[k].copy(pairs=results[k].pairs)
            mode = np.linalg.eigh(pair_hessian(model, at))[1][:, 0].reshape(-1, 3)
            mode *= opts.saddle_step / np.linalg.norm(mode, axis=1).max()
            for sign in (1.0, -1.0):
                pairs = at.pairs + sign * mode
                if bounds is not None and bounds[k] is not None:
                    pairs = np.clip(pairs, *bounds[k])
                starts.append(at.copy(pairs=pairs))
                owners.append(k)
        again = _relax_once(model, starts, inner,
                            None if bounds is None else [bounds[k] for k in owners])
        for k in stuck:
            tries = [r for o, r in zip(owners, again, strict=True) if o == k]
            # a minimum first, then a saddle to escape from in the next round; lowest energy
            best = min(tries, key=lambda r: (r.failed, not _at_saddle(structures[k], r, opts),
                                             r.energy))
            for r in tries:
                if r is not best:
                    best = _after(r, best)
            best.n_hessians += 1
            if best.failed:
                best.reason += " (relaxed again from a saddle along its softest mode)"
            results[k] = _after(results[k], best)
    return results


def _after(first: RelaxResult, then: RelaxResult) -> RelaxResult:
    """``then``, a relaxation that went on from ``first``, with both one's counts."""
    then.iterations += first.iterations
    then.n_evaluations += first.n_evaluations
    then.n_hessians += first.n_hessians
    return then

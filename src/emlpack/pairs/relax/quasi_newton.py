"""The default method (``initial_hessian="coulomb"``): quasi-Newton whose model is the exact
analytic electrostatic pair Hessian plus a symmetric-rank-one model of the short-range
remainder (:func:`relax_coulomb`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import torch

from emlpack.nn.potential import EMLP, for_evaluation
from emlpack.nn.scatter import segment_sum
from emlpack.nn.short_range import FrozenAnyDtype
from emlpack.pairs.relax.bond_rotations import BondRotations
from emlpack.pairs.relax.curvature import min_curvature
from emlpack.pairs.relax.newton import relax_newton
from emlpack.pairs.relax.options import RelaxOptions, RelaxResult
from emlpack.pairs.relax.problem import (
    ActiveEvaluator,
    CoulombPairs,
    PairProblem,
    relax_results,
    setup_problem,
)
from emlpack.pairs.relax.steps import newton_step
from emlpack.properties.hessian import standard_energy
from emlpack.structure import Structure

if TYPE_CHECKING:
    from emlpack.pairs.relax.options import Bounds


def _sr1_update(prob: PairProblem, short: torch.Tensor, curvilinear: BondRotations | None,
                x: torch.Tensor, g_short: torch.Tensor, step: torch.Tensor,
                newton: torch.Tensor, rot: torch.Tensor | None, g_short_new: torch.Tensor,
                active: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Symmetric-rank-one update of the short-range model ``short`` (B, m, m; eV/Å^2) from a
    step (P, 3; Å) evaluated at ``x`` + ``step``: short-range gradients ``g_short`` at ``x`` and
    ``g_short_new`` there (eV/Å), only for the ``active`` (B,) structures, skipped when r.s is
    tiny. With ``rot`` (the pairs' rotations from :meth:`BondRotations.turn` of ``newton``,
    the step before turning) the secant is taken in the cylindrical coordinates of the turned
    pairs: the step (tangential part the arc) and the short-range gradient in them, less the
    connection term of the short-range gradient (``short`` is Cartesian). Returns the model and
    which pairs turned (P,) bool (None for straight steps)."""
    turned_pair = None
    if rot is None:
        s = prob.pad(step)
        r = prob.pad(g_short_new - g_short) - (short @ s[:, :, None]).squeeze(-1)
    else:
        turned_pair = (rot - torch.eye(3, dtype=rot.dtype)).abs().amax((1, 2)) > 0
        s_pairs = torch.where(turned_pair[:, None], newton, step)
        conn = curvilinear.connection(x, g_short)
        conn = torch.where(turned_pair[:, None, None], conn, 0.0)
        y = (curvilinear.generalized(x, newton, rot, g_short_new) - g_short
             - (conn @ s_pairs[:, :, None]).squeeze(-1))
        s = prob.pad(s_pairs)
        r = prob.pad(y) - (short @ s[:, :, None]).squeeze(-1)
    rs = (r * s).sum(1)
    size = torch.linalg.norm(r, dim=1) * torch.linalg.norm(s, dim=1)
    ok = active & (rs.abs() > 1e-8 * size) & (rs.abs() > 1e-30)
    upd = r[:, :, None] * r[:, None, :] / torch.where(ok, rs, 1.0)[:, None, None]
    return torch.where(ok[:, None, None], short + upd, short), turned_pair


def _blocks_to_padded(prob: PairProblem, blocks: torch.Tensor) -> torch.Tensor:
    """Per-pair 3x3 blocks (P_total, 3, 3) -> block-diagonal padded (B, 3 Pmax, 3 Pmax)."""
    b, n = prob.g.n_structures, prob.n_max
    out = blocks.new_zeros(b, n, n, 3, 3)
    out[prob.pair_batch, prob.local, prob.local] = blocks
    return out.permute(0, 1, 3, 2, 4).reshape(b, 3 * n, 3 * n)


def relax_coulomb(model: EMLP, structures: Sequence[Structure], opts: RelaxOptions,
                  bounds: Bounds) -> list[RelaxResult]:
    """Quasi-Newton with the exact analytic electrostatic pair Hessian at every iterate plus a
    symmetric-rank-one model of the short-range remainder, learnt from the change of gradient
    minus the change of the electrostatic gradient (one energy+gradient per iteration)."""
    dtype = torch.float64
    g, prob, x, lower, upper, projected = setup_problem(model, structures, bounds, dtype,
                                                      opts.filter_table)
    b = g.n_structures
    bounded = bool(torch.isfinite(lower).any() or torch.isfinite(upper).any())
    coulomb = CoulombPairs(model, prob)
    # float32 phase: structures with a pair force above opts.float32_above (measured on the
    # trained benchmark model: float32 energy+gradient 2.5x cheaper, gradient error 2e-5 eV/Å,
    # energy error 8e-6 eV at |E| = 12 eV)
    # (EMLP's own energy only: subclasses with their own energy_parts stay in float64)
    low = bool(opts.float32_above > 0 and g.n_pairs.max() > 0
               and int(g.n_pairs.sum()) >= opts.float32_min_pairs
               and standard_energy(model))
    prob32 = prob
    if low:
        # the held core-core edges rounded from float64 (not recomputed in float32); a family
        # that cannot evaluate float32 inputs on its float64 weights gets a float32 copy
        held32 = None if prob.held is None else prob.held.to(torch.float32)
        model32 = (model if isinstance(model.short_range, FrozenAnyDtype)
                   else for_evaluation(model, torch.float32))
        prob32 = PairProblem(model32, g.to(dtype=torch.float32), held=held32,
                             filter_table=prob.filter_table, tabulate=prob.tabulated)
    work = prob32 if low else prob
    # EMLP's own energy: the model evaluations leave out the electrostatics, whose energy and
    # gradient come from the analytic derivatives computed at every iterate anyway (float64)
    analytic = standard_energy(model)
    lr = not analytic  # whether the model evaluations include the electrostatics
    energy, grad = (t.to(dtype) for t in work.energy_gradient(x.to(work.g.dtype), lr))
    use32 = torch.full((b,), bool(low))
    exact64 = ~use32  # energy and gradient are float64 values
    gc, hc, e_coulomb = coulomb(x, energy=analytic)
    g_short = grad if analytic else grad - gc
    if analytic:
        energy, grad = energy + e_coulomb, grad + gc
    m = 3 * prob.n_max
    short = torch.zeros(b, m, m, dtype=dtype)
    n_eval = torch.ones(b, dtype=torch.long)
    pad_eye = torch.diag_embed(
        (torch.arange(m)[None, :] >= 3 * g.n_pairs[:, None]).to(dtype)
    )
    n_hess = torch.zeros(b, dtype=torch.long)
    iters = torch.zeros(b, dtype=torch.long)
    fmax = prob.per_structure_max_norm(projected(grad, x))
    converged = (fmax < opts.fmax) & exact64 | (g.n_pairs == 0)
    if opts.short_range_start == "lumped" and not bool(converged.all()):
        # float32: a larger difference step (measured: 3e-4 Å gives 3e-4 relative error)
        short = _lumped_short_range(work, coulomb, x, g_short, 3e-4 if low else 1e-4, lr)
        n_eval += 3 * (~converged).long()
    evaluate = ActiveEvaluator(model, prob)
    evaluate32 = ActiveEvaluator(prob32.model, prob32)
    curvilinear = BondRotations(structures, x) if opts.bond_rotations else None
    # structures with a group of pairs about one bond take one step along its collective
    # rotation (``rotation_probe``) instead of a Newton step, once; then ``probed``
    unprobed = torch.zeros(b, dtype=torch.bool)
    probed = torch.zeros(b, dtype=torch.bool)
    if curvilinear is not None and opts.rotation_probe > 0:
        unprobed = segment_sum(curvilinear.collective(x, 1.0, opts.rotation_probe_pairs).abs()
                               .sum(1), prob.pair_batch, b) > 0
    # trust radius (Å, largest pair displacement): halved to the rejected step's length,
    # doubled from an accepted one's up to max_step
    radius = torch.full((b,), opts.max_step, dtype=dtype)
    stalled = torch.zeros(b, dtype=torch.bool)
    quasi_newton = min(opts.max_iterations, opts.newton_after or opts.max_iterations)
    # float32 structures leave the float32 phase below this largest pair force (eV/Å)
    leave32 = max(opts.float32_above, opts.fmax)
    for _ in range(quasi_newton):
        active = ~converged & ~stalled
        if not bool(active.any()):
            break
        # float32 structures below the threshold take their next step in float64, accepted
        # when it lowers the pair-gradient norm (no float64 energy to compare with yet); when
        # it does not, they are re-evaluated in float64 where they are (no step), then go on
        trying = active & use32 & (fmax < leave32)
        if int(g.n_pairs[active & use32 & ~trying].sum()) < opts.float32_min_pairs:
            # too few float32 pairs left: a float32 call that small is dispatch-bound (no
            # cheaper than float64) and a second model call per iteration; all leave float32
            # (measured: 33 -> 25 model calls on the 64-structure benchmark)
            trying = active & use32
        switch = active & ~use32 & ~exact64
        moving = active & ~switch
        gp = prob.pad(projected(grad, x))
        held = None
        if bounded:
            held = prob.pad(((x <= lower) | (x >= upper)) & (projected(grad, x) == 0)) > 0
        model_hessian = hc + short + pad_eye
        if curvilinear:
            # the model in the cylindrical coordinates of the turned steps
            model_hessian = model_hessian + _blocks_to_padded(
                prob, curvilinear.connection(x, grad))
        # (a structure whose rotation was probed: its soft mode is in the model, and the
        # floor would shorten the steps along it)
        floor = torch.where(probed, opts.rotation_floor, 1e-2)
        step = newton_step(prob, model_hessian, gp, held, floor, moving,
                           torch.ones_like(radius), radius, opts.mirror_curvature or None)
        probing = moving & unprobed & (fmax < opts.rotation_probe_below)
        if bool(probing.any()):
            # the lumped start sees a triple bond's pairs turning one at a time, stiff, while
            # together they turn almost freely near the minimum (measured: docs/relaxation.md):
            # a step along that rotation, downhill, puts its curvature into the SR1 model
            rotation = curvilinear.collective(x, opts.rotation_probe, opts.rotation_probe_pairs)
            slope = segment_sum((grad * rotation).sum(1), prob.pair_batch, b)
            downhill = torch.where(slope > 0, -1.0, 1.0).to(dtype)
            step = torch.where(probing[prob.pair_batch, None],
                               downhill[prob.pair_batch, None] * rotation, step)
            unprobed &= ~probing
            probed |= probing
        newton = step
        rot = None
        if curvilinear:
            x_new, rot = curvilinear.turn(x, step)
            if bounded:
                x_turn, x_new = x_new, torch.clamp(x_new, lower, upper)
                # a pair moved by the box bound takes the chord in the secant
                rot = torch.where((x_new != x_turn).any(1)[:, None, None],
                                  torch.eye(3, dtype=dtype), rot)
        else:
            x_new = torch.clamp(x + step, lower, upper) if bounded else x + step
        step = x_new - x
        in32 = moving & use32 & ~trying
        in64 = active & ~in32
        e_new, g_new = energy, grad
        if bool(in64.any()):
            e_new, g_new = evaluate(x_new, in64, energy, grad, lr)
        if bool(in32.any()):
            e32, g32 = evaluate32(x_new.float(), in32, energy.float(), grad.float(), lr)
            e_new = torch.where(in32, e32.to(dtype), e_new)
            g_new = torch.where(in32[prob.pair_batch, None], g32.to(dtype), g_new)
        gc_new, hc_new, ec_new = coulomb(x_new, active, energy=analytic)
        if analytic:
            e_new = torch.where(active, e_new + ec_new, energy)
            g_new = torch.where(active[prob.pair_batch, None], g_new + gc_new, grad)
        n_eval += active.long()
        iters += moving.long()
        slope = segment_sum((grad * step).sum(1), prob.pair_batch, b)
        # structures sent to float64 above leave32 (the small float32 tail) compare their
        # float64 energy with the float32 one, with the float32 allowance
        forced = trying & (fmax >= leave32)
        noisy = in32 | forced
        noise = torch.where(noisy, 1e-6, 1e-12) * energy.abs()
        accept = switch | (moving & ~trying | forced) & (e_new <= energy + 1e-4 * slope + noise)
        # steps whose predicted decrease is below the float32 energy's resolution (near the
        # minimum) are accepted when they lower the pair-gradient norm instead
        flat = noisy & (slope.abs() < noise)
        by_norm = trying & ~forced | flat
        if bool(by_norm.any()):
            norm_new = segment_sum((projected(g_new, x_new) ** 2).sum(1), prob.pair_batch, b)
            norm_old = segment_sum((projected(grad, x) ** 2).sum(1), prob.pair_batch, b)
            accept |= by_norm & (norm_new < norm_old)
        exact64 |= switch | trying & accept
        use32 &= ~trying
        reject = active & ~accept
        # SR1 from every evaluated step, rejected ones included (measured: updating from
        # accepted steps only needs 2-5x more iterations)
        short, turned_pair = _sr1_update(prob, short, curvilinear, x, grad - gc, step, newton,
                                         rot, g_new - gc_new, active)
        if rot is not None:
            # the short-range model turns with the accepted pairs (only the structures with a
            # turned pair: the others' rotations are the identity)
            turning = accept & (segment_sum(turned_pair.to(dtype), prob.pair_batch, b) > 0)
            ks = torch.nonzero(turning).squeeze(1)
            if len(ks):
                rows = turning[prob.pair_batch]
                turn = torch.eye(3, dtype=dtype).repeat(len(ks), prob.n_max, 1, 1)
                new_index = torch.cumsum(turning.long(), 0) - 1
                turn[new_index[prob.pair_batch[rows]], prob.local[rows]] = rot[rows]
                blocks = short[ks].reshape(len(ks), prob.n_max, 3, prob.n_max, 3)
                short[ks] = torch.einsum("biac,bicjd,bjed->biaje", turn, blocks,
                                         turn).reshape(len(ks), m, m)
        acc_p = accept[prob.pair_batch, None]
        x = torch.where(acc_p, x_new, x)
        grad = torch.where(acc_p, g_new, grad)
        gc = torch.where(acc_p, gc_new, gc)
        hc = torch.where(accept[:, None, None], hc_new, hc)
        energy = torch.where(accept, e_new, energy)
        taken = prob.per_structure_max_norm(step)
        old_radius = radius
        radius = torch.where(accept, torch.clamp(torch.maximum(radius, 2.0 * taken),
                                                 max=opts.max_step), radius)
        radius = torch.where(reject, 0.5 * taken, radius)
        radius = torch.where(probing, old_radius, radius)  # a probe leaves the trust radius
        stalled |= reject & (radius < 1e-7)
        if opts.collapse_distance > 0:
            stalled |= accept & (prob.closest_pair_distance(x) < opts.collapse_distance)
        fmax = prob.per_structure_max_norm(projected(grad, x))
        converged = converged | (fmax < opts.fmax) & exact64

    # the few structures still unconverged (nearly flat modes: the SR1 model learns them
    # slowly) finish with the exact-Hessian Newton method
    late = ~converged & ~stalled & (g.n_pairs > 0)
    left = opts.max_iterations - quasi_newton
    if left > 0 and bool(late.any()):
        ks = torch.nonzero(late).squeeze(1).tolist()
        xs = x.detach().numpy()
        pb = prob.pair_batch.numpy()
        sub = [structures[k].copy(pairs=xs[pb == k]) for k in ks]
        sub_opts = replace(opts, initial_hessian="exact", max_iterations=left,
                           check_curvature=False)
        sub_bounds = None if bounds is None else [bounds[k] for k in ks]
        for k, r in zip(ks, relax_newton(model, sub, sub_opts, sub_bounds), strict=True):
            rows = prob.pair_batch == k
            x[rows] = torch.as_tensor(r.pairs, dtype=dtype)
            grad[rows] = -torch.as_tensor(r.pair_forces, dtype=dtype)
            energy[k] = r.energy
            fmax[k] = r.max_force
            converged[k] = r.max_force < opts.fmax
            iters[k] += r.iterations
            n_eval[k] += r.n_evaluations
            n_hess[k] += r.n_hessians

    model_hessian = hc + short + pad_eye
    min_curv = min_curvature(prob, x, grad, lower, upper, projected, opts, n_hess,
                             model_hessian, prob32)
    return relax_results(structures, prob, x, energy, grad, converged, iters, n_eval, n_hess,
                         fmax, min_curv, opts)


def _lumped_short_range(prob: PairProblem, coulomb: CoulombPairs, x: torch.Tensor,
                        g_short: torch.Tensor, step: float = 1e-4,
                        long_range: bool = True) -> torch.Tensor:
    """Block-diagonal (3x3 per pair) estimate of the short-range pair Hessian from three
    forward differences of the short-range gradient ``g_short`` (probe: one Cartesian
    direction on every pair at once, ``step`` Å; three batched energy+gradient evaluations in
    ``prob``'s dtype, differences in ``x``'s; ``long_range``: the evaluations include the
    electrostatics, taken off with ``coulomb``): each pair's block is the row sum of its
    short-range couplings (off-diagonal blocks lumped onto it)."""
    n = prob.n_max
    b = prob.g.n_structures
    blocks = x.new_zeros(len(x), 3, 3)
    for c in range(3):
        shifted = x.clone()
        shifted[:, c] += step
        _, g_shift = prob.energy_gradient(shifted.to(prob.g.dtype), long_range)
        g_shift = g_shift.to(x.dtype)
        if long_range:
            g_shift = g_shift - coulomb(shifted, hessian=False)[0]
        blocks[:, :, c] = (g_shift - g_short) / step
    blocks = 0.5 * (blocks + blocks.transpose(1, 2))
    out = x.new_zeros(b, n, n, 3, 3)
    out[prob.pair_batch, prob.local, prob.local] = blocks
    return out.permute(0, 1, 3, 2, 4).reshape(b, 3 * n, 3 * n)
